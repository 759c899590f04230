"""How a run's step cost grows with its heated zone: ms per step over windows of process time.

    python scripts/tools/step_cost.py CASE --t-end T [--window W] [--set key=value ...] [--out FILE]
                                      [--checkpoint FILE] [--restart FILE]
    mpirun -n 2 python scripts/tools/step_cost.py CASE --t-end T ...

Runs the case (in one process, or decomposed when launched by mpirun) from t = 0 to T and
prints, for every window of W seconds of process time: the steps, the wall time per step,
the neighbour rebuilds, and the particles the step integrates and works on (active, work;
summed over ranks), and at the end the projection of the case's whole ``run.t_end_s`` from
the last window's cost (process time per wall second). With ``--out`` the table is also
written as JSON. The set-up is timed apart. Nothing else is written (no snapshots), but
with ``--checkpoint`` the state at T (a checkpoint `python -m torchsph CASE --restart FILE`
continues, and the deposition bench's late state). With ``--restart`` (on any number of ranks)
the run continues from a checkpoint of the case (``python -m torchsph CASE --out DIR`` or ``--checkpoint``)
instead of starting at t = 0: the cost beyond a first leg.
"""
from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[2]))
from torchsph.__main__ import mpi_size  # noqa: E402
from torchsph.io.config import load_case  # noqa: E402
from torchsph.run.runner import STEP_MODE, SerialRun  # noqa: E402
from torchsph.run.build import make_simulation  # noqa: E402
from torchsph.step.loop import run_steps  # noqa: E402


@STEP_MODE()  # as a run of the CLI steps (torchsph.run.runner.run_case)
def main():
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("case")
    ap.add_argument("--t-end", type=float, required=True, help="process time to run to, s")
    ap.add_argument("--window", type=float, default=1e-3, help="process time per table row, s")
    ap.add_argument("--set", dest="overrides", action="append", default=[])
    ap.add_argument("--out", type=Path, default=None)
    ap.add_argument("--checkpoint", type=Path, default=None, help="write the state at --t-end here")
    ap.add_argument("--restart", type=Path, default=None, help="continue from this checkpoint (its run's config.json)")
    a = ap.parse_args()
    _, cfg = load_case(a.case, a.overrides)
    if a.restart is not None:  # the run's own case, as its checkpoint was written with
        cfg = json.loads((a.restart.parent / "config.json").read_text())
        cfg.pop("case", None)
        resolved = load_case(a.case, a.overrides)[1] if a.overrides else None
        for item in a.overrides:  # (step-control keys: checkpoint.STEP_CONTROL), resolved as the case's
            sec, key = item.split("=", 1)[0].split(".", 1)
            cfg[sec][key] = resolved[sec][key]
    comm = procs = None
    if mpi_size() > 1:
        from parallel.run import SlabRun
        from parallel.setup import install_abort_hook
        install_abort_hook()
        procs = SlabRun(cfg)
        comm = procs.comm
    root = comm is None or comm.rank == 0
    sum_ = (lambda v: v) if comm is None else comm.sum
    t0 = time.perf_counter()
    _, sim = make_simulation(cfg) if procs is None else procs.make(cfg)
    if a.restart is not None:  # (a one-process or a global checkpoint, on any number of ranks)
        (procs or SerialRun()).restore(sim, a.restart, cfg, (procs or SerialRun()).recorded(a.restart))
    setup = time.perf_counter() - t0
    ranks = 1 if comm is None else comm.size
    n_all = sim.state.n if comm is None else int(sum_([comm.n_owned])[0])  # (a collective: every rank)
    if root:
        print(f"{a.case}: {n_all} particles, "
              f"{ranks} process(es), set-up {setup:.1f} s")
        print(f"{'t_ms':>7} {'steps':>6} {'ms/step':>8} {'rebuilds':>8} {'active':>8} {'work':>8}")
    rows = []
    while sim.t < a.t_end * (1 - 1e-12):
        s0, b0, w0 = sim.step, sim.nl.n_builds, time.perf_counter()
        run_steps(sim, t_end=min(sim.t + a.window, a.t_end))
        wall = time.perf_counter() - w0
        act = sim.active_set.active if sim.active_set is not None else None
        own = sim.comm.owned(sim)
        if act is None:
            n_act = n_work = sim.state.n if own is None else int(own.sum())
        else:
            work = sim.active_set.work
            n_act, n_work = (int(m.sum()) if own is None else int((m & own).sum()) for m in (act, work))
        n_act, n_work = (int(v) for v in sum_([n_act, n_work]))
        row = {"t_ms": sim.t * 1e3, "steps": sim.step - s0, "ms_per_step": wall / max(sim.step - s0, 1) * 1e3,
               "rebuilds": sim.nl.n_builds - b0, "active": n_act, "work": n_work, "wall_s": wall}
        rows.append(row)
        if root:
            print(f"{row['t_ms']:7.2f} {row['steps']:6d} {row['ms_per_step']:8.1f} {row['rebuilds']:8d} "
                  f"{n_act:8d} {n_work:8d}", flush=True)
    if a.checkpoint is not None:
        from torchsph.io import checkpoint as ckpt
        args = (sim, a.checkpoint, ckpt.config_hash(cfg), {}, ckpt.physics(cfg))
        if comm is None:
            SerialRun().save(*args)
        else:
            from parallel.run import save_global
            save_global(*args[:1], comm, *args[1:])
        if root:  # the case beside it, as a run's (what --restart reads)
            from torchsph.io import snapshots as sio
            sio.write_json(a.checkpoint.parent / "config.json", {"case": str(a.case), **cfg})
    if root:
        total = sum(r["wall_s"] for r in rows)
        last = rows[-1]
        rate = a.window / last["wall_s"]  # process s per wall s, at the end
        t_full = cfg["run"]["t_end_s"]
        print(f"{sum(r['steps'] for r in rows)} steps in {total:.1f} s ({total / max(sum(r['steps'] for r in rows), 1) * 1e3:.1f} "
              f"ms/step over the run); at the last window's rate the case's t_end = {t_full:g} s would take "
              f"{(t_full - sim.t) / rate / 3600 + total / 3600:.1f} h more in all (the cost still grows with the "
              "heated zone: a lower bound)")
        if a.out is not None:
            a.out.write_text(json.dumps({"case": a.case, "ranks": ranks, "setup_s": setup, "rows": rows}, indent=1))


if __name__ == "__main__":
    main()
