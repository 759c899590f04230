"""Bead geometry vs source power and orientation (the thesis's Fig. 6.5) for the four
deposition cases: a matplotlib PNG and a markdown/CSV table.

    python scripts/studies/compare_cases.py --preview            # runs the four previews (minutes each)
    python scripts/studies/compare_cases.py --read RUN250 RUN300 RUN350 RUNPERP   # finished runs
    python scripts/studies/compare_cases.py --read ... --time 0.30 --start-skip-mm 1 --pool-margin-mm 1.5

``--time`` takes every run's snapshot nearest that time (default: each run's last), so runs
of different length are compared at the same process time. ``--section-mm X0`` adds the
transverse section at substrate-frame x0 of every case, side by side (OUT_sections.png), and
its numbers to the table; ``--render`` draws the same sections with PyVista (OUT_sections3d.png:
the deposit behind the cut as cubes, one per particle, the fusion zone in crimson).

Per case: the bead averaged over its steady part (width, height above the original top,
penetration, added area; NaN where the run is too short for a bead behind the wire) and the
melt pool at the last snapshot (length, width, depth, peak temperature).
"""
from __future__ import annotations

import argparse
import csv
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]
sys.path.insert(0, str(ROOT))

from torchsph.post import analysis as post  # noqa: E402
from torchsph.post import pictures  # noqa: E402
from torchsph.io.snapshots import read_snapshot  # noqa: E402

CASES = ["along_250W", "along_300W", "along_350W", "perpendicular_350W"]


def snapshot_at(run: Path, time: float | None):
    cfg, snaps = post.load_run(run)
    if time is None:
        t_snap, path = snaps[-1]
    else:
        t_snap, path = min(snaps, key=lambda s: abs(s[0] - time))
        if abs(t_snap - time) > 0.5 * cfg["run"]["output_interval_s"] + 1e-9:
            raise SystemExit(f"{run}: no snapshot near t = {time} s (nearest {t_snap:.4g} s)")
    return cfg, read_snapshot(path)


def measure(run: Path, time: float | None = None, start_skip: float = 2.0e-3, pool: float = 2.5e-3,
            section_x0: float | None = None, ax=None) -> dict:
    cfg, last = snapshot_at(run, time)
    prof = post.bead_profile(last, cfg)
    b = post.steady_average(prof, *post.default_steady_range(last, cfg, start_skip=start_skip, pool=pool))
    mp = post.melt_pool(last, cfg["thermal"]["liquidus_K"], cfg["scene"]["dx_m"], vol=post.volumes(last, cfg),
                        bottom=post.substrate_bottom(cfg))
    sc = cfg["scene"]
    out = {"case": Path(cfg["case"]).parent.name, "layout": sc["source_layout"], "power_W": sc["source_power_W"],
            "dx_mm": sc["dx_m"] * 1e3, "t_s": float(last["time"]), "bead_x_mm": "{:.2f}..{:.2f}".format(*(1e3 * v for v in b["x_range_m"])),
            "bead_columns": b["columns"],
            "bead_width_mm": b["width_m"] * 1e3, "bead_height_mm": b["height_m"] * 1e3,
            "penetration_mm": b["penetration_m"] * 1e3, "added_area_mm2": b["added_area_m2"] * 1e6,
            "toe_angle_deg": b["toe_angle_deg"],
            "pool_length_mm": mp["length_m"] * 1e3, "pool_width_mm": mp["width_m"] * 1e3,
            "pool_depth_mm": mp["depth_m"] * 1e3, "peak_K": mp["peak_temperature_K"]}
    if section_x0 is not None:
        sec = post.section(last, cfg, section_x0, ax=ax)
        out |= {"section_x0_mm": sec["x0_m"] * 1e3, "section_width_mm": sec["width_m"] * 1e3,
                "section_height_mm": sec["height_m"] * 1e3, "section_penetration_mm": sec["penetration_m"] * 1e3,
                "section_added_mm2": sec["added_area_m2"] * 1e6}
        if ax is not None:
            ax.set_title(f"{out['case']}, x0 = {out['section_x0_mm']:.2f} mm, t = {out['t_s']:.2f} s", fontsize=8)
    return out


def plot(rows: list[dict], png: Path):
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, 2, figsize=(9, 3.4), dpi=110)
    bead = any(r["bead_columns"] > 0 for r in rows)
    keys = (("bead_width_mm", "width"), ("bead_height_mm", "height"), ("penetration_mm", "penetration")) if bead \
        else (("pool_width_mm", "pool width"), ("pool_length_mm", "pool length"), ("pool_depth_mm", "pool depth"))
    along = [r for r in rows if r["layout"] == "along"]
    perp = [r for r in rows if r["layout"] == "perpendicular"]
    for key, label in keys:
        axes[0].plot([r["power_W"] for r in along], [r[key] for r in along], "o-", label=label)
        if perp:
            axes[0].plot([r["power_W"] for r in perp], [r[key] for r in perp], "s", ms=8,
                         label=f"{label}, perpendicular")
    axes[0].set_xlabel("power per source, W")
    axes[0].set_ylabel("mm")
    axes[0].set_title(("bead" if bead else "melt pool") + " vs power (lines: along)", fontsize=9)
    axes[0].legend(fontsize=7)
    axes[1].plot([r["power_W"] for r in along], [r["peak_K"] for r in along], "o-", label="along")
    axes[1].plot([r["power_W"] for r in perp], [r["peak_K"] for r in perp], "s", ms=8, label="perpendicular")
    axes[1].set_xlabel("power per source, W")
    axes[1].set_ylabel("peak temperature, K")
    axes[1].legend(fontsize=7)
    t = max(r["t_s"] for r in rows)
    fig.suptitle(f"deposition cases at dx = {rows[0]['dx_mm']:.2f} mm, t = {t * 1e3:.0f} ms", fontsize=9)
    fig.tight_layout()
    fig.savefig(png)
    plt.close(fig)


def main():
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--preview", action="store_true", help="run the four previews first")
    ap.add_argument("--read", nargs="+", type=Path, help="finished run folders")
    ap.add_argument("--out", type=Path, default=ROOT / "docs" / "compare_cases")
    ap.add_argument("--time", type=float, help="compare at the snapshot nearest this time, s (default: the last)")
    ap.add_argument("--start-skip-mm", type=float, default=2.0,
                    help="bead columns start this far behind the substrate-frame origin (default 2)")
    ap.add_argument("--section-mm", type=float, help="also the transverse section at this substrate-frame x0, mm")
    ap.add_argument("--render", action="store_true", help="with --section-mm: the PyVista picture of the sections")
    ap.add_argument("--pool-margin-mm", type=float, default=2.5,
                    help="and end this far behind the wire's axis (default 2.5: past the pool)")
    a = ap.parse_args()
    runs = a.read
    if runs is None:
        runs = []
        for c in CASES:
            out = ROOT / "cases" / c / "output_preview"
            if a.preview:
                subprocess.run([sys.executable, "-m", "torchsph", str(ROOT / "cases" / c), "--preview", "--quiet",
                                "--out", str(out)], cwd=ROOT, check=True)
            runs.append(out)
    axes = [None] * len(runs)
    if a.section_mm is not None:
        import matplotlib
        matplotlib.use("Agg")
        import matplotlib.pyplot as plt

        ncol = 2 if len(runs) > 1 else 1
        nrow = (len(runs) + ncol - 1) // ncol
        fig, grid = plt.subplots(nrow, ncol, figsize=(6 * ncol, 3.1 * nrow), dpi=100, squeeze=False)
        axes = list(grid.ravel())
        for ax in axes[len(runs):]:
            ax.set_visible(False)
    x0 = a.section_mm * 1e-3 if a.section_mm is not None else None
    rows = [measure(r, a.time, a.start_skip_mm * 1e-3, a.pool_margin_mm * 1e-3, x0, ax) for r, ax in zip(runs, axes)]
    if a.section_mm is not None:
        fig.suptitle("transverse sections, coloured by peak temperature; cyan: fusion line (T_L); "
                     "dashed: original top", fontsize=8)
        fig.tight_layout()
        a.out.parent.mkdir(parents=True, exist_ok=True)
        fig.savefig(a.out.with_name(a.out.name + "_sections.png"))
        plt.close(fig)
    a.out.parent.mkdir(parents=True, exist_ok=True)
    if a.render and x0 is not None:
        shown = []
        for r, row in zip(runs, rows):
            cfg, snap = snapshot_at(r, a.time)
            shown.append((snap, cfg, f"{row['case']} ({row['power_W']:.0f} W, {row['layout']}, dx {row['dx_mm']:.2f} mm)"))
        pictures.render_sections(shown, x0, a.out.with_name(a.out.name + "_sections3d.png"))
    with open(a.out.with_suffix(".csv"), "w", newline="") as f:
        w = csv.DictWriter(f, fieldnames=list(rows[0]))
        w.writeheader()
        w.writerows(rows)
    plot(rows, a.out.with_suffix(".png"))
    cols = list(rows[0])
    print("| " + " | ".join(cols) + " |")
    print("|" + "---|" * len(cols))
    for r in rows:
        print("| " + " | ".join(f"{v:.4g}" if isinstance(v, float) else str(v) for v in r.values()) + " |")
    print(f"wrote {a.out.with_suffix('.png')} and .csv")


if __name__ == "__main__":
    main()
