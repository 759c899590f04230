"""A late-run cost probe: a run's checkpoint with its cold solid warmed, so that the active set
takes in what a long run's heated zone would.

    python scripts/tools/warm_state.py CHECKPOINT OUT_DIR [--dT 3] [--x-max X]

Every particle within 1 K of ambient (and with x < ``--x-max``, m, if given) is warmed by
``--dT`` kelvin; three steps are taken (the active set takes them in), and the state is
written as ``OUT_DIR/checkpoint.pt`` beside the run's ``config.json``, a checkpoint that
``python -m torchsph CASE --restart``, ``scripts/tools/step_cost.py --restart`` and
``scripts/tools/slab_bound.py`` read. The physics of the warmed state is not a run's (a step
of dT at the old heated zone's edge); its cost is: late in the full scene the heated zone takes
in the whole substrate (``scripts/tools/work_projection.py``), and a step's cost follows the
particles it works on.
"""
from __future__ import annotations

import argparse
import shutil
import sys
from pathlib import Path

import torch

sys.path.insert(0, str(Path(__file__).resolve().parents[2]))
from torchsph.io import checkpoint as ckpt  # noqa: E402
from torchsph.step.loop import run_steps  # noqa: E402
from torchsph.run.build import simulation_from_run  # noqa: E402


def main():
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("checkpoint", type=Path)
    ap.add_argument("out", type=Path)
    ap.add_argument("--dT", type=float, default=3.0, help="kelvin added to the cold particles")
    ap.add_argument("--x-max", type=float, default=None, help="warm only particles with x below this (m)")
    a = ap.parse_args()
    torch.set_num_threads(1)
    cfg, sim = simulation_from_run(a.checkpoint)
    s = sim.state
    ambient = float(cfg["thermal"]["ambient_K"])
    cold = (s.T - ambient).abs() <= 1.0
    if a.x_max is not None:
        cold &= s.x[:, 0] < a.x_max
    s.T = torch.where(cold, s.T + a.dT, s.T)  # (set by hand: the step refreshes the active set)
    run_steps(sim, steps=3)
    a.out.mkdir(parents=True, exist_ok=True)
    shutil.copy(a.checkpoint.parent / "config.json", a.out / "config.json")
    ckpt.save(sim, a.out / "checkpoint.pt", ckpt.config_hash(cfg), phys=ckpt.physics(cfg))
    work = sim.active_set.work if sim.active_set is not None else None
    print(f"{int(cold.sum())} particles warmed by {a.dT:g} K; t = {sim.t:.6g} s, "
          f"{s.n} particles, {s.n if work is None else int(work.sum())} working, "
          f"{sim.thermal.rows.numel() if sim.thermal is not None else 0} conducting; {a.out / 'checkpoint.pt'}")


if __name__ == "__main__":
    main()
