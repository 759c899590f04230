"""Whether two versions of the code compute the same thing: run a fixed set of cases for a
fixed number of steps, save every final array and the energy balance, and compare two such
files.

    python scripts/tools/same_states.py run OUT.npz          # in the tree to measure
    python scripts/tools/same_states.py diff A.npz B.npz     # largest relative difference

To compare with another commit, check it out into a worktree (``git worktree add /tmp/ref
COMMIT``) and run ``python /path/to/this/script run REF.npz`` from there: the script
imports the ``torchsph`` of the current directory. One thread. The cases cover the fluid
with walls, the free surface, melting, radiation, evaporation with a beam, and the
deposition preview (1500 steps: melt, feed, partial rebuilds, the active set)."""
from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np
import torch

CASES = [("taylor_green_2d", False, 100), ("poiseuille_2d", False, 100), ("static_drop_2d", False, 100),
         ("stefan_1d", False, 200), ("radiating_sphere", False, 100), ("thermocapillary_layer_2d", False, 200),
         ("cube_evaporation_preview", False, 300), ("perpendicular_350W", True, 1500)]


def run(out: Path):
    torch.set_num_threads(1)
    root = Path.cwd()
    sys.path.insert(0, str(root))
    try:  # this layout (torchsph/io, run, step), or a commit's from before it (a flat torchsph/)
        from torchsph.io.config import load_case
        from torchsph.run.build import make_simulation
        from torchsph.step.loop import run_steps
    except ImportError:
        from torchsph.config import load_case
        from torchsph.runner import make_simulation, run_steps

    arrays = {}
    for name, preview, steps in CASES:
        _, cfg = load_case(root / "cases" / name, [], preview=preview)
        _, sim = make_simulation(cfg)
        run_steps(sim, steps=steps)
        s = sim.state
        order = s.id.argsort()
        for k in ("x", "v", "rho", "T"):
            arrays[f"{name}.{k}"] = getattr(s, k)[order].numpy()
        arrays[f"{name}.t"] = np.array(sim.t)
        for k, v in sim.energy_balance().items():
            arrays[f"{name}.E.{k}"] = np.array(v)
        print(name, sim.step, sim.t, flush=True)
    np.savez(out, **arrays)


def diff(a_path: Path, b_path: Path) -> float:
    a, b = np.load(a_path), np.load(b_path)
    worst = 0.0
    for k in sorted(set(a.files) | set(b.files)):
        if k not in a.files or k not in b.files or a[k].shape != b[k].shape:
            print(f"{k}: only in one file, or shapes differ")
            worst = float("inf")
            continue
        d = float(np.abs(a[k] - b[k]).max()) if a[k].size else 0.0
        rel = d / max(float(np.abs(a[k]).max()) if a[k].size else 1.0, 1e-300)
        if rel > 0:
            print(f"{k}: max relative difference {rel:.3g}")
        worst = max(worst, rel)
    print(f"{len(a.files)} arrays; largest relative difference {worst:.3g}")
    return worst


def main():
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    sub = ap.add_subparsers(dest="cmd", required=True)
    r = sub.add_parser("run")
    r.add_argument("out", type=Path)
    d = sub.add_parser("diff")
    d.add_argument("a", type=Path)
    d.add_argument("b", type=Path)
    a = ap.parse_args()
    if a.cmd == "run":
        run(a.out)
    else:
        diff(a.a, a.b)


if __name__ == "__main__":
    main()
