"""One measurement of ``scripts/tools/bench.py --deposition --mpi``: a case's step timed in this
process, or on the ranks of ``mpirun``; prints one JSON line (rank 0).

    [mpirun -n K] python scripts/tools/bench_mpi.py CASE --steps N [--warm W] [--restart CK] [--set key=value ...]

From t = 0 (the full scene's first steps), or from a checkpoint (``--restart``: a developed
state, e.g. one ``scripts/tools/step_cost.py --checkpoint`` or ``warm_state.py`` wrote), W steps
are taken to warm up, then N are timed. Reported: ms per step (wall, the slowest rank's), the
particles, and per rank the owned and ghost particles, the halo (m), the bytes this rank sent
per step (array payloads of every message: ghost refreshes, migrations, reductions), its work
(wall less the time in communication) and the imbalance (max / mean work over ranks)."""
from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[2]))
from torchsph.__main__ import mpi_size  # noqa: E402
from torchsph.io.config import load_case  # noqa: E402
from torchsph.run.build import make_simulation, resume  # noqa: E402
from torchsph.run.runner import STEP_MODE  # noqa: E402
from torchsph.step.loop import run_steps  # noqa: E402


@STEP_MODE()
def main():
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("case")
    ap.add_argument("--steps", type=int, default=100)
    ap.add_argument("--warm", type=int, default=5)
    ap.add_argument("--restart", type=Path, default=None)
    ap.add_argument("--set", dest="overrides", action="append", default=[])
    a = ap.parse_args()
    _, cfg = load_case(a.case, a.overrides)
    comm = None
    if mpi_size() > 1:
        from parallel.run import restore_global
        from parallel.setup import install_abort_hook, make_comm
        from torchsph.io.checkpoint import read
        install_abort_hook()
        comm = make_comm(cfg)
    t0 = time.perf_counter()
    _, sim = make_simulation(cfg, comm=comm)
    if a.restart is not None:
        if comm is None:
            resume(sim, a.restart, cfg)
        else:
            restore_global(sim, comm, read(a.restart), cfg, str(a.restart))
    setup = time.perf_counter() - t0
    run_steps(sim, steps=a.warm)
    c = comm.c if comm is not None else None
    sent0, waited0 = (c.sent, c.waited) if c is not None else (0, 0.0)
    if c is not None:
        c.Barrier()
    t1 = time.perf_counter()
    run_steps(sim, steps=a.steps)
    wall = time.perf_counter() - t1
    mine = {"rank": comm.rank if comm is not None else 0, "wall_s": wall,
            "work_s": wall - ((c.waited - waited0) if c is not None else 0.0),
            "owned": comm.n_owned if comm is not None else sim.state.n,
            "ghosts": sim.state.n - comm.n_owned if comm is not None else 0,
            "sent_bytes_per_step": ((c.sent - sent0) / a.steps) if c is not None else 0.0}
    ranks = c.gather(mine, root=0) if c is not None else [mine]
    if c is not None and comm.rank != 0:
        return
    work = [r["work_s"] for r in ranks]
    print(json.dumps({"case": str(a.case), "ranks": len(ranks), "steps": a.steps, "t_end": sim.t, "setup_s": setup,
                      "particles": sum(r["owned"] for r in ranks),
                      "ms_per_step": 1e3 * max(r["wall_s"] for r in ranks) / a.steps,
                      "halo_m": comm.halo if comm is not None else 0.0,
                      "imbalance": max(work) / (sum(work) / len(work)) if sum(work) > 0 else 1.0,
                      "per_rank": ranks}), flush=True)


if __name__ == "__main__":
    main()
