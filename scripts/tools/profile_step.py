"""Per-step profile of the solver: where one time step spends its time.

    python scripts/tools/profile_step.py [CASE_DIR] [--steps N] [--compile] [--set key=value ...]
    python scripts/tools/profile_step.py --restart RUN_DIR/checkpoint.pt [--steps N] [--set numerics.KEY=VALUE]

With ``--restart`` the step is profiled in the state of a run's checkpoint (the case is the
run's own ``config.json``), e.g. late in a deposition run, where the melt pool, the fed
wire and the active set make the step's cost what it is.

Prints the torch profiler's table of operators (self CPU time) over N steps after a
warm-up. Every per-step operation is a whole-array torch call (gathers, reductions over
the neighbour axis, index_copy); the only Python loops in the step run over the 3^d
cell-stencil offsets of a neighbour rebuild and over spatial components.
"""
from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

from torch.profiler import ProfilerActivity, profile

sys.path.insert(0, str(Path(__file__).resolve().parents[2]))
from torchsph.io.config import load_case  # noqa: E402
from torchsph.run.build import make_simulation  # noqa: E402
from torchsph.step.loop import run_steps  # noqa: E402


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("case", nargs="?", default=str(Path(__file__).resolve().parents[2] / "cases/taylor_green_2d"))
    ap.add_argument("--steps", type=int, default=40)
    ap.add_argument("--compile", action="store_true")
    ap.add_argument("--set", dest="overrides", action="append", default=[])
    ap.add_argument("--restart", type=Path, default=None, metavar="CHECKPOINT")
    a = ap.parse_args()
    if a.restart is not None:
        from torchsph.run.build import simulation_from_run
        import tomllib  # (--set numerics.KEY=VALUE: the step-control keys a restart may change)
        nm = {o.split("=", 1)[0].removeprefix("numerics."): tomllib.loads("v = " + o.split("=", 1)[1])["v"]
              for o in a.overrides}
        cfg, sim = simulation_from_run(a.restart, numerics=nm, compile=a.compile)
    else:
        _, cfg = load_case(a.case, a.overrides)
        _, sim = make_simulation(cfg, compile=a.compile)
    run_steps(sim, steps=5)
    t = time.perf_counter()
    run_steps(sim, steps=a.steps)
    el = time.perf_counter() - t
    print(f"{sim.state.n} particles, {sim.nl.table.n_pairs()} pairs: {el / a.steps * 1e3:.2f} ms/step, "
          f"{sim.state.n * a.steps / el:.3g} particle-steps/s")
    with profile(activities=[ProfilerActivity.CPU]) as prof:
        run_steps(sim, steps=a.steps)
    print(prof.key_averages().table(sort_by="self_cpu_time_total", row_limit=15))


if __name__ == "__main__":
    main()
