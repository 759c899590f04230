"""Side-by-side cost of skipping (active set + multi-rate conduction) on a deposition preview.

    python scripts/skip_speedup.py cases/perpendicular_350W            # runs both (minutes)
    python scripts/skip_speedup.py --read OUT_SKIP OUT_NOSKIP           # compare two finished runs

Runs the case's preview twice, with the default skipping and with ``--no-skip`` (every
particle integrated every step, conduction every step), one after the other, and prints
wall time, particle-steps/s, the speed-up, and the differences in peak temperature (the
hottest any particle got), the melt-pool volume at the end, and the fused volume (every
particle that was ever above the liquidus).
"""
from __future__ import annotations

import argparse
import json
import subprocess
import sys
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from torchsph.io import read_snapshot  # noqa: E402


def measures(out: Path) -> dict:
    s = json.loads((out / "summary.json").read_text())
    cfg = json.loads((out / "config.json").read_text())
    TL = cfg["thermal"]["liquidus_K"]
    snap = read_snapshot(sorted(out.glob("snap_*.h5"))[-1])
    vol = snap["density"] ** -1.0  # per unit mass; times the mass below
    mass = None
    ck = out / "checkpoint.pt"
    if ck.exists():
        import torch
        mass = torch.load(ck, map_location="cpu", weights_only=False)["state"]
        order = torch.argsort(mass["id"])
        mass = mass["m"][order].numpy()
    V = vol * mass
    return {"wall_s": s["wall_s"], "steps": s["steps"], "psteps_per_s": s["particle_steps_per_s"],
            "peak_K": float(snap["peak_temperature"].max()),
            "pool_m3": float(V[snap["temperature"] > TL].sum()),
            "fused_m3": float(V[snap["peak_temperature"] > TL].sum()),
            "active": s.get("active_fraction", {}).get("conduction", {})}


def main():
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("case", nargs="?", default=str(ROOT / "cases" / "perpendicular_350W"))
    ap.add_argument("--read", nargs=2, type=Path, metavar=("SKIP", "NOSKIP"))
    a = ap.parse_args()
    if a.read:
        outs = a.read
    else:
        outs = [Path(a.case) / "output_skip", Path(a.case) / "output_noskip"]
        for out, extra in zip(outs, ([], ["--no-skip"])):
            subprocess.run([sys.executable, "-m", "torchsph", a.case, "--preview", "--quiet", "--out", str(out)]
                           + extra, cwd=ROOT, check=True)
    sk, ns = (measures(o) for o in outs)
    print("| run | wall s | steps | particle-steps/s | peak T K | melt pool mm^3 | fused mm^3 |")
    print("|---|---|---|---|---|---|---|")
    for name, m in (("skip (default)", sk), ("--no-skip", ns)):
        print(f"| {name} | {m['wall_s']:.0f} | {m['steps']} | {m['psteps_per_s']:.3g} | {m['peak_K']:.1f} | "
              f"{m['pool_m3'] * 1e9:.4f} | {m['fused_m3'] * 1e9:.4f} |")
    rel = lambda k: sk[k] / ns[k] - 1 if ns[k] else float("nan")  # noqa: E731
    print(f"speed-up {ns['wall_s'] / sk['wall_s']:.2f}x; peak T {rel('peak_K'):+.2%}, melt pool "
          f"{rel('pool_m3'):+.2%}, fused volume {rel('fused_m3'):+.2%}; active fraction (conduction) "
          f"{sk['active']}")


if __name__ == "__main__":
    np.seterr(divide="ignore")
    main()
