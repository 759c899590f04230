"""Side-by-side cost of skipping (the active set: cold solid left out) on a deposition preview.

    python scripts/tools/skip_speedup.py cases/perpendicular_350W            # runs both (minutes)
    python scripts/tools/skip_speedup.py --read OUT_SKIP OUT_NOSKIP [--control OUT_NOSKIP_PERTURBED]

Runs the case's preview twice, with the default skipping and with ``--no-skip`` (every
particle integrated every step), one after the other, and prints
wall time, particle-steps/s, the speed-up, and the differences in peak temperature (the
hottest any particle got), the melt-pool volume at the end, and the fused volume (every
particle that was ever above the liquidus) — at the end and at every snapshot. With
``--control``, a no-skip run perturbed by a tiny amount is compared with the no-skip run
the same way: once drops leave the wire the dynamics amplifies any difference, and this
measures how much without any skipping.
"""
from __future__ import annotations

import argparse
import json
import subprocess
import sys
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[2]
sys.path.insert(0, str(ROOT))

from torchsph.io.snapshots import read_snapshot  # noqa: E402


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
        from torchsph.io.checkpoint import read, state_arrays
        mass = state_arrays(read(ck))
        order = torch.argsort(mass["id"])
        mass = mass["m"][order].numpy()
    V = vol * mass
    return {"wall_s": s["wall_s"], "steps": s["steps"], "psteps_per_s": s["particle_steps_per_s"],
            "peak_K": float(snap["peak_temperature"].max()),
            "pool_m3": float(V[snap["temperature"] > TL].sum()),
            "fused_m3": float(V[snap["peak_temperature"] > TL].sum()),
            "active": s.get("active_fraction", {}).get("conduction", {})}


def history(out: Path, TL: float) -> list[dict]:
    """Per snapshot: time, the highest temperature any particle has reached, the liquid
    volume and the fused volume (every particle that has been above the liquidus)."""
    rows = []
    for f in sorted(out.glob("snap_*.h5")):
        sn = read_snapshot(f)
        V = sn["mass"] / sn["density"]
        rows.append({"t": float(sn["time"]), "peak_K": float(sn["peak_temperature"].max()),
                     "pool_m3": float(V[sn["temperature"] > TL].sum()),
                     "fused_m3": float(V[sn["peak_temperature"] > TL].sum())})
    return rows


def print_history(outs, names):
    """The two runs side by side at each snapshot: where (if at all) they part."""
    TL = json.loads((outs[0] / "config.json").read_text())["thermal"]["liquidus_K"]
    hs = [history(o, TL) for o in outs]
    print(f"\nper snapshot ({names[0]} vs {names[1]}; relative differences):")
    print("| t ms | highest T K | diff | melt mm^3 | diff | fused mm^3 | diff |")
    print("|---|---|---|---|---|---|---|")
    rel = lambda a, b: f"{a / b - 1:+.2%}" if b else "-"  # noqa: E731
    for a, b in zip(*hs):
        print(f"| {a['t'] * 1e3:.1f} | {a['peak_K']:.1f} / {b['peak_K']:.1f} | {rel(a['peak_K'], b['peak_K'])} | "
              f"{a['pool_m3'] * 1e9:.4f} / {b['pool_m3'] * 1e9:.4f} | {rel(a['pool_m3'], b['pool_m3'])} | "
              f"{a['fused_m3'] * 1e9:.4f} / {b['fused_m3'] * 1e9:.4f} | {rel(a['fused_m3'], b['fused_m3'])} |")


def main():
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("case", nargs="?", default=str(ROOT / "cases" / "perpendicular_350W"))
    ap.add_argument("--read", nargs=2, type=Path, metavar=("SKIP", "NOSKIP"))
    ap.add_argument("--control", type=Path, default=None,
                    help="a finished --no-skip run with a tiny perturbation (e.g. --set "
                         "scene.source_power_W=350.00035): the runs' own sensitivity")
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
    print_history(outs, ("skip", "no-skip"))
    if a.control:  # the no-skip run again, perturbed: how far two runs part without any skipping
        print_history([outs[1], a.control], ("no-skip", "no-skip perturbed"))


if __name__ == "__main__":
    np.seterr(divide="ignore")
    main()
