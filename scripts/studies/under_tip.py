"""What the fed wire's tip meets: the melt under the wire against the stalls of the feed.

    python scripts/studies/under_tip.py RUN_DIR [RUN_DIR ...] [--from-s 0.1]

The feed waits (``scene.wire_stall``) while unmelted wire touches solid substrate, or melt
is squeezed between the rigid tip and solid substrate. Per run, over its snapshots from
``--from-s`` on (lab frame: the wire's axis is x = y = 0): the height of the solid wire's
lowest particle above the substrate's original top (z = 0); the depth of the melt under the
wire's footprint (|x|, |y| < wire radius: the lowest liquid there, below z = 0, plus half a
spacing; 0 where none); the share of the substrate's top layer in that footprint that is
solid (melt, of the wire or the substrate, is not); and, from the run's ``deposit.json``, the
time the feed waited, its number of waits, and that time by the rule that began each wait.
"""
from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[2]))
from torchsph.post import analysis as post  # noqa: E402
from torchsph.io.snapshots import read_snapshot  # noqa: E402
from torchsph.post.analysis import WIRE  # noqa: E402
from torchsph.core.state import Phase  # noqa: E402


def under_tip(run: Path, t_from: float = 0.1) -> dict:
    cfg, snaps = post.load_run(run)
    dx, rw = cfg["scene"]["dx_m"], 0.5 * cfg["scene"]["wire_diameter_m"]
    tips, depths, solid_top = [], [], []
    for t, path in snaps:
        if t < t_from:
            continue
        s = read_snapshot(path)
        x = s["position"]
        wire = (s["body"] == WIRE) & (s["phase"] == Phase.SOLID)
        tips.append(x[wire, 2].min() if wire.any() else np.nan)
        foot = (np.abs(x[:, 0]) < rw) & (np.abs(x[:, 1]) < rw) & ~wire
        low = foot & (s["phase"] == Phase.FLUID) & (x[:, 2] < 0.0)
        depths.append(0.5 * dx - x[low, 2].min() if low.any() else 0.0)
        top = foot & (x[:, 2] > -dx) & (x[:, 2] <= 0.0)  # (melt of any origin: its body tag is 0)
        solid_top.append((top & (s["phase"] == Phase.SOLID)).sum() / max(top.sum(), 1))
    dep = json.loads((Path(run) / "deposit.json").read_text())[-1]
    by = dep.get("wire_stalled_by")
    return {"run": str(run), "dx_mm": dx * 1e3, "snapshots": len(tips), "t_end_s": dep["t_s"],
            "tip_height_mean_mm": 1e3 * float(np.nanmean(tips)), "tip_height_min_mm": 1e3 * float(np.nanmin(tips)),
            "melt_depth_under_wire_mm": 1e3 * float(np.mean(depths)),
            "no_melt_under_wire_share": float(np.mean(np.asarray(depths) == 0.0)),
            "solid_top_under_wire_share": float(np.mean(solid_top)),
            "feed_wait_s": dep["wire_stalled_s"], "waits": dep["wire_stalls"],
            # by the rule that began each wait (runs from stop 40 on; "-" before)
            "wait_unmelted_s": by["unmelted"]["s"] if by else "-", "wait_squeezed_s": by["squeezed"]["s"] if by else "-"}


def main():
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("runs", nargs="+", type=Path)
    ap.add_argument("--from-s", type=float, default=0.1, help="skip the snapshots before this time (the start)")
    a = ap.parse_args()
    rows = [under_tip(r, a.from_s) for r in a.runs]
    cols = list(rows[0])
    print("| " + " | ".join(cols) + " |")
    print("|" + "---|" * len(cols))
    for r in rows:
        print("| " + " | ".join(f"{v:.3g}" if isinstance(v, float) else str(v) for v in r.values()) + " |")


if __name__ == "__main__":
    main()
