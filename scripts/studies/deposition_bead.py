"""Steady-bead mass check of a deposition case (issue 5, must-show 1).

Runs a deposition case (default: its preview resolution on a longer substrate, long enough
for the bead behind the wire to become steady), then reads ``deposit.json`` and reports the
bead's added cross-section, averaged over the substrate-frame x range that has passed the
wire and solidified and lies beyond the start-up transient, against the mass-conservation
value pi d^2 V_wire / (4 V_sub) (2.26 mm^2 for the thesis's scene), and against the
cross-section of the wire actually fed while that range passed under the wire (less than
the nominal value by the time the feed waited on contact, ``scene.wire_stall``).

    python scripts/studies/deposition_bead.py cases/perpendicular_350W --t-end 0.5
    python scripts/studies/deposition_bead.py --read OUT_DIR      # analyse a finished run
    python scripts/studies/deposition_bead.py --read OUT_DIR --plot bead.png   # and draw each bin's history

A bin counts as settled when its area changed by at most ``--tolerance`` over the last
``--lag-s`` seconds (melt running back along the bead keeps filling a bin for a while after
the wire has passed it); the steady bead is the mean over the settled bins.
"""
from __future__ import annotations

import argparse
import json
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]
sys.path.insert(0, str(ROOT))
from torchsph.post.analysis import bead_settling, fed_cross_section  # noqa: E402

LONG = ["scene.dx_m=2.5e-4", "scene.substrate_size_m=[10.0e-3, 6.0e-3, 2.5e-3]",
        "scene.wire_length_m=3.0e-3", "scene.wire_offset_m=1.5e-3", "run.output_interval_s=0.01"]


def analyse(out: Path, start_skip_m: float = 2.0e-3, pool_margin_m: float = 2.5e-3,
            lag_s: float = 0.05, tolerance: float = 0.05) -> dict:
    cfg = json.loads((out / "config.json").read_text())
    history = json.loads((out / "deposit.json").read_text())
    d = history[-1]
    V = cfg["scene"]["substrate_velocity_m_s"][0]
    t = d["t_s"]
    lo, hi = -V * t + pool_margin_m, -start_skip_m  # solidified, past the start transient
    rows = [(x, a) for x, a in zip(d["bin_centres_m"], d["added_area_m2"]) if lo <= x <= hi]
    mean = sum(a for _, a in rows) / len(rows) if rows else float("nan")
    fed = fed_cross_section(history, lo, hi, V, cfg["fluid"]["rho0_kg_m3"]) if rows else float("nan")
    settle = bead_settling(history, lo, hi, lag_s, tolerance)
    settled = settle["settled_m2"]
    return {"t_s": t, "window_m": [lo, hi], "bins": len(rows), "added_area_mm2": mean * 1e6,
            "expected_mm2": d["expected_area_m2"] * 1e6,
            "error": mean / d["expected_area_m2"] - 1 if rows else float("nan"),
            "fed_area_mm2": fed * 1e6, "error_vs_fed": mean / fed - 1 if rows else float("nan"),
            "settled_bins": f"{settle['settled_bins']} of {len(settle['bins'])} "
                            f"(changed <= {tolerance:.0%} since t = {settle['t_before_s']:.3f} s)",
            "settled_area_mm2": settled * 1e6, "settled_error": settled / d["expected_area_m2"] - 1,
            "bin_changes": [f"x0 {r['x0_m'] * 1e3:+.2f} mm: {r['area_m2'] * 1e6:.3f} mm2 ({r['change']:+.1%})"
                            for r in settle["bins"]],
            "wire_fed_kg": d["wire_fed_kg"], "wire_inserted_kg": d["wire_inserted_kg"],
            "wire_melted_kg": d["wire_melted_kg"], "deposit_kg": d["deposit_kg"],
            "welded_kg": d.get("welded_kg"), "off_substrate_kg": d.get("off_substrate_kg"),
            "wire_stalled_s": d.get("wire_stalled_s"),
            "profile_mm2": [(round(x * 1e3, 3), round(a * 1e6, 3)) for x, a in
                            zip(d["bin_centres_m"], d["added_area_m2"])],
            "peak_temperature_K": d["peak_temperature_K"], "melt_pool": d["melt_pool"]}


def plot_history(out: Path, png: Path, lo: float, hi: float):
    """Each bin's added cross-section against time, with the nominal value."""
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    history = json.loads((out / "deposit.json").read_text())
    ts = [e["t_s"] for e in history]
    fig, ax = plt.subplots(figsize=(6.4, 3.6), dpi=110)
    for j, x in enumerate(history[-1]["bin_centres_m"]):
        if lo - 1.0e-3 <= x <= hi:
            ax.plot(ts, [e["added_area_m2"][j] * 1e6 for e in history], marker=".",
                    label=f"x0 = {x * 1e3:.0f} mm")
    ax.axhline(history[-1]["expected_area_m2"] * 1e6, color="k", ls="--", label="nominal")
    ax.axhspan(0.9 * history[-1]["expected_area_m2"] * 1e6, 1.1 * history[-1]["expected_area_m2"] * 1e6,
               color="0.9", zorder=0)
    ax.set_xlabel("t (s)")
    ax.set_ylabel("added cross-section (mm$^2$)")
    ax.legend(fontsize=7, ncol=2)
    ax.set_title(out.name, fontsize=9)
    fig.tight_layout()
    fig.savefig(png)
    print(f"wrote {png}")


def main():
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("case", nargs="?", default=str(ROOT / "cases" / "perpendicular_350W"))
    ap.add_argument("--t-end", type=float, default=0.5)
    ap.add_argument("--out", type=Path, default=None)
    ap.add_argument("--read", type=Path, default=None, help="only analyse this finished run")
    ap.add_argument("--set", action="append", default=[], help="extra overrides")
    ap.add_argument("--start-skip-mm", type=float, default=2.0,
                    help="leave out the first this many mm of the bead (start transient)")
    ap.add_argument("--pool-margin-mm", type=float, default=2.5,
                    help="leave out this many mm behind the wire (the pool, not yet solid)")
    ap.add_argument("--lag-s", type=float, default=0.05,
                    help="a bin is settled when its area changed by at most --tolerance over this time")
    ap.add_argument("--tolerance", type=float, default=0.05)
    ap.add_argument("--plot", type=Path, default=None, help="draw each bin's area against time")
    a = ap.parse_args()
    out = a.read
    if out is None:
        out = a.out or Path(a.case) / "output_bead"
        cmd = [sys.executable, "-m", "torchsph", a.case, "--out", str(out), "--t-end", str(a.t_end),
               "--checkpoint-every", "2000"] + [x for s in LONG + a.set for x in ("--set", s)]
        print(" ".join(cmd), flush=True)
        r = subprocess.run(cmd, cwd=ROOT)
        if r.returncode:
            sys.exit(r.returncode)
    res = analyse(out, a.start_skip_mm * 1e-3, a.pool_margin_mm * 1e-3, a.lag_s, a.tolerance)
    print(json.dumps({k: v for k, v in res.items() if k != "profile_mm2"}, indent=1))
    print("added cross-section by substrate-frame x (mm, mm^2):", res["profile_mm2"])
    if a.plot is not None:
        plot_history(out, a.plot, *res["window_m"])


if __name__ == "__main__":
    main()
