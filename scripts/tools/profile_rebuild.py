"""Where a neighbour rebuild's time goes: cProfile of every rebuild over some steps of a run's
checkpoint (one thread), with the rebuilds' mean wall time.

    python scripts/tools/profile_rebuild.py CHECKPOINT [--steps 100] [--top 40] [--sort cumulative]
        [--set numerics.KEY=VALUE]

The run continues from the checkpoint with a full neighbour build, 5 steps untimed, then
``--steps`` steps; only the rebuilds (``Simulation.refresh_pairs`` where the pairs changed)
are profiled and timed."""
from __future__ import annotations

import argparse
import cProfile
import pstats
import sys
import time
from pathlib import Path

import torch

sys.path.insert(0, str(Path(__file__).resolve().parents[2]))
from torchsph.step.loop import run_steps  # noqa: E402
from torchsph.run.build import simulation_from_run  # noqa: E402


def main():
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("checkpoint", type=Path)
    ap.add_argument("--steps", type=int, default=100)
    ap.add_argument("--top", type=int, default=40)
    ap.add_argument("--sort", default="cumulative")
    ap.add_argument("--set", dest="overrides", action="append", default=[], metavar="numerics.KEY=VALUE",
                    help="a step-control key of the run's numerics (e.g. numerics.conduction_window=0.25)")
    a = ap.parse_args()
    torch.set_num_threads(1)
    numerics = {}
    for o in a.overrides:
        key, _, value = o.partition("=")
        if not key.startswith("numerics.") or not value:
            ap.error(f"--set {o!r}: expected numerics.KEY=VALUE")
        numerics[key.split(".", 1)[1]] = float(value)
    _, sim = simulation_from_run(a.checkpoint, numerics=numerics or None)
    sim.rebuild()
    run_steps(sim, steps=5)
    prof = cProfile.Profile()
    walls = []
    plain = sim.refresh_pairs

    def profiled(*args, **kw):
        builds = sim.nl.n_builds
        t = time.perf_counter()
        prof.enable()
        out = plain(*args, **kw)
        prof.disable()
        if sim.nl.n_builds > builds:
            walls.append(time.perf_counter() - t)
        return out

    sim.refresh_pairs = profiled
    run_steps(sim, steps=a.steps)
    n = len(walls)
    print(f"{n} rebuilds in {a.steps} steps, {1e3 * sum(walls) / max(n, 1):.1f} ms each (under the profiler)")
    if n:  # (with none, the profiler holds nothing to print: take more steps)
        pstats.Stats(prof).sort_stats(a.sort).print_stats(a.top)


if __name__ == "__main__":
    main()
