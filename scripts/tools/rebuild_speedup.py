"""Side-by-side cost of the partial neighbour rebuild, from a run's checkpoint.

    python scripts/tools/rebuild_speedup.py RUN_DIR [--steps 200] [--threads 1]

Restores ``RUN_DIR/checkpoint.pt`` (with the run's ``config.json``) twice and steps it
``--steps`` steps with ``numerics.partial_rebuild`` on and off, one after the other; prints
ms per step, particle-steps/s, the neighbour builds (and how many were partial) and the
largest differences of temperature and position between the two end states. Both runs
hold the same pairs; only the order within rows differs, so the two differ by rounding,
which the melt's dynamics then amplifies over many steps.
"""
from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import torch

ROOT = Path(__file__).resolve().parents[2]
sys.path.insert(0, str(ROOT))

from torchsph.step.loop import run_steps  # noqa: E402
from torchsph.run.build import simulation_from_run  # noqa: E402


def run(run_dir: Path, steps: int, partial: bool):
    _, sim = simulation_from_run(run_dir / "checkpoint.pt", {"partial_rebuild": partial})
    b0, p0, t0 = sim.nl.n_builds, sim.nl.n_partial, time.perf_counter()
    run_steps(sim, steps=steps)
    wall = time.perf_counter() - t0
    return sim, {"ms_per_step": 1e3 * wall / steps, "particle_steps_per_s": sim.state.n * steps / wall,
                 "builds": sim.nl.n_builds - b0, "partial": sim.nl.n_partial - p0, "t_s": sim.t}


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("run_dir", type=Path)
    ap.add_argument("--steps", type=int, default=200)
    ap.add_argument("--threads", type=int, default=1)
    a = ap.parse_args(argv)
    torch.set_num_threads(a.threads)
    sim_p, on = run(a.run_dir, a.steps, True)
    sim_f, off = run(a.run_dir, a.steps, False)
    for name, r in (("partial", on), ("full", off)):
        print(f"{name:8s}: {r['ms_per_step']:7.1f} ms/step, {r['particle_steps_per_s']:.3g} particle-steps/s, "
              f"{r['builds']} neighbour builds ({r['partial']} partial), t = {r['t_s']:.6f} s")
    dT = float((sim_p.state.T - sim_f.state.T).abs().max()) if sim_p.state.n == sim_f.state.n else float("nan")
    dx = float((sim_p.state.x - sim_f.state.x).abs().max()) if sim_p.state.n == sim_f.state.n else float("nan")
    print(f"speed-up {off['ms_per_step'] / on['ms_per_step']:.2f}x over {a.steps} steps on {a.threads} thread(s); "
          f"largest |dT| {dT:.3g} K, |dx| {dx:.3g} m between the two end states")


if __name__ == "__main__":
    main()
