"""Run time against bead error: a deposition case at a ladder of resolutions.

    python scripts/resolution_study.py cases/along_350W --dx 0.4 0.3 0.25 0.2 --t-end 0.4
    python scripts/resolution_study.py cases/along_350W --dx 0.4 0.3 --t-end 0.4 --jobs 2 --leg-s 3000
    python scripts/resolution_study.py cases/along_350W --dx 0.4 0.3 0.25 --t-end 0.4 --read

Each resolution (dx in mm) runs the case with ``--set scene.dx_m=...`` over the same process
window (0 .. --t-end) into OUT/dx<mm> (OUT: --out, default output_resolution/<case>), with a
checkpoint every --checkpoint-every steps. A run that is not finished continues from its
checkpoint when the study is started again (``--restart``), so a fine run goes in legs:
--leg-s stops each run after that much wall time (Ctrl-C to the run: it writes its
checkpoint and summary) and the next invocation continues it. The run's own summary adds
up the legs' wall time. --jobs runs that many resolutions at once (one thread each).

Then one table: dx, particles, steps, wall s, particle-steps/s; the settled bead's added
cross-section by mass (the bins behind the wire whose area changed by at most 5 % over the
last 50 ms; where none has, the mean of the window's bins, as the settled count shows), the
bins' spread along the track ((max - min) / mean: a steady bead is the same along x; a row above
50 % is flagged below the table, with its bins) and its error against the nominal pi d^2 V_wire / (4 V_sub); the wire fed over the
window against the nominal feed (the feed waits on contact) and the bead's error against the
area of the wire actually fed (so that a wait is not counted as a resolution error); from the last
snapshot the bead's mean width, height, penetration and toe angle over the solidified range
behind the wire (torchsph.post.analysis.bead_profile); the melt pool's length, width and depth at the
end; the peak temperature; the share of the fed wire that lies on the substrate (the
deposit's mass over the mass fed); the time the feed waited on contact. Then each column's
value extrapolated to dx -> 0 (Richardson from the three finest, with the observed order;
torchsph.post.analysis.richardson) and each row's difference from it; the two finest rows' difference
per column, and the spacing at which rungs of their ratio would differ by less than 10 % (from
the order and the limit). Unfinished runs are listed with the time they reached and left out
of the table. --plot draws the bead's error
against wall time (log-log). --json writes the rows.
"""
from __future__ import annotations

import argparse
import json
import math
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
from torchsph.io.snapshots import read_snapshot  # noqa: E402
from torchsph.post.analysis import (bead_profile, bead_settling, default_steady_range, load_run,  # noqa: E402
                           nominal_wire_fed_kg, richardson, steady_average)

COLUMNS = [  # key, header, format, extrapolated
    ("dx_mm", "dx mm", "{:.3f}", False), ("particles", "particles", "{:,}", False), ("steps", "steps", "{:,}", False),
    ("wall_s", "wall s", "{:.0f}", False), ("psteps", "particle-steps/s", "{:.3g}", False),
    ("area_mm2", "bead area mm2", "{:.3f}", True), ("settled_bins", "bins settled", "{}", False),
    ("bins_spread", "bins spread", "{:.0%}", False),
    ("area_error", "error vs nominal", "{:+.1%}", False),
    ("fed_share", "fed / nominal feed", "{:.1%}", False), ("area_error_fed", "error vs fed", "{:+.1%}", False),
    ("width_mm", "width mm", "{:.3f}", True), ("height_mm", "height mm", "{:.3f}", True),
    ("penetration_mm", "penetration mm", "{:.3f}", True), ("toe_deg", "toe angle deg", "{:.1f}", True),
    ("pool_length_mm", "pool L mm", "{:.2f}", True), ("pool_width_mm", "pool W mm", "{:.2f}", True),
    ("pool_depth_mm", "pool D mm", "{:.2f}", True), ("peak_K", "peak T K", "{:.0f}", True),
    ("on_substrate", "fed wire on substrate", "{:.1%}", True), ("wait_s", "feed wait s", "{:.3f}", False),
]


def run_dir(out: Path, dx_mm: float) -> Path:
    return out / f"dx{dx_mm:g}"


def reached(d: Path) -> float:
    """Process time a run has reached (its last deposition record), 0 if none."""
    p = d / "deposit.json"
    if not p.exists():
        return 0.0
    try:
        return float(json.loads(p.read_text())[-1]["t_s"])
    except (ValueError, IndexError, KeyError):
        return 0.0


def command(case: str, d: Path, dx_mm: float, t_end: float, every: int, extra: list[str]) -> list[str]:
    cmd = [sys.executable, "-m", "torchsph", case, "--out", str(d), "--t-end", repr(t_end), "--quiet",
           "--checkpoint-every", str(every), "--set", f"scene.dx_m={dx_mm:g}e-3"]
    for s in extra:
        cmd += ["--set", s]
    if (d / "checkpoint.pt").exists():
        cmd += ["--restart", str(d / "checkpoint.pt")]
    return cmd


def run_all(a, out: Path):
    """Start (or continue) the unfinished resolutions, --jobs at a time, each for at most
    --leg-s of wall time."""
    todo = [dx for dx in a.dx if reached(run_dir(out, dx)) < a.t_end * (1 - 1e-9)]
    env = {**os.environ, "OMP_NUM_THREADS": "1", "MKL_NUM_THREADS": "1"}
    running: list[tuple[float, subprocess.Popen, float, object]] = []
    while todo or running:
        while todo and len(running) < a.jobs:
            dx = todo.pop(0)
            d = run_dir(out, dx)
            d.mkdir(parents=True, exist_ok=True)
            cmd = command(a.case, d, dx, a.t_end, a.checkpoint_every, a.overrides)
            log = open(d / "study.log", "a")
            log.write(" ".join(cmd) + "\n")
            log.flush()
            print(f"dx = {dx:g} mm: {' '.join(cmd)}", flush=True)
            running.append((dx, subprocess.Popen(cmd, cwd=ROOT, env=env, stdout=log, stderr=subprocess.STDOUT),
                            time.monotonic(), log))
        time.sleep(2.0)
        for item in list(running):
            dx, p, t0, log = item
            if a.leg_s is not None and p.poll() is None and time.monotonic() - t0 > a.leg_s:
                p.send_signal(signal.SIGINT)  # the run writes its checkpoint and summary
                p.wait()
            if p.poll() is not None:
                running.remove(item)
                log.close()
                print(f"dx = {dx:g} mm: exit {p.returncode}, reached t = {reached(run_dir(out, dx)):.4f} s", flush=True)


def analyse(d: Path, dx_mm: float) -> dict:
    """One row of the table from a finished run."""
    summary = json.loads((d / "summary.json").read_text())
    history = json.loads((d / "deposit.json").read_text())
    cfg, snaps = load_run(d)
    last = read_snapshot(snaps[-1][1])
    lo, hi = default_steady_range(last, cfg)
    steady = steady_average(bead_profile(last, cfg), lo, hi)
    e = history[-1]
    try:
        settle = bead_settling(history, lo, hi, lag_s=0.05, tolerance=0.05)
    except ValueError:  # a window shorter than the lag: nothing can have settled
        settle = {"settled_m2": float("nan"), "settled_bins": 0,
                  "bins": [{"area_m2": a} for x, a in zip(e["bin_centres_m"], e["added_area_m2"]) if lo <= x <= hi]}
    pool = e["melt_pool"]
    nominal = e["expected_area_m2"]
    fed = e["wire_fed_kg"]
    row = {"dx_mm": dx_mm, "particles": summary["n_particles"], "steps": summary["steps"],
           "wall_s": summary["wall_s"], "t_s": e["t_s"],
           "settled_bins": f"{settle['settled_bins']} of {len(settle['bins'])}",
           "nominal_mm2": nominal * 1e6,
           "width_mm": steady["width_m"] * 1e3, "height_mm": steady["height_m"] * 1e3,
           "penetration_mm": steady["penetration_m"] * 1e3, "toe_deg": steady["toe_angle_deg"],
           "pool_length_mm": pool.get("length_m", 0.0) * 1e3, "pool_width_mm": pool.get("width_m", 0.0) * 1e3,
           "pool_depth_mm": pool.get("depth_below_top_m", 0.0) * 1e3, "peak_K": e["peak_temperature_K"],
           "on_substrate": e["deposit_kg"] / fed if fed > 0 else float("nan"),
           "wait_s": e.get("wire_stalled_s") or 0.0}
    # the settled bins' mean; where none has settled yet (a short window at coarse dx: bins
    # of 4 dx), the mean of the window's bins, marked in ``settled_bins``
    window = [b["area_m2"] for b in settle["bins"]]
    row["area_mm2"] = (settle["settled_m2"] if settle["settled_bins"] else
                       (sum(window) / len(window) if window else float("nan"))) * 1e6
    # a steady bead is the same along x: (max - min) / mean of the window's bins (a bin may
    # stop changing while the bead is a ramp, e.g. melt held on the wire and dropped in turns)
    row["bins_mm2"] = [a * 1e6 for a in window]
    row["bins_spread"] = spread(row["bins_mm2"])
    row["psteps"] = row["particles"] * row["steps"] / row["wall_s"] if row["wall_s"] > 0 else float("nan")
    row["area_error"] = row["area_mm2"] / row["nominal_mm2"] - 1.0
    # the wire actually fed against the nominal feed over the window (the feed waits on
    # contact), and the bead against the area of the wire actually fed: a wait is then not
    # counted as a resolution error (a window mean: the bins behind the wire were fed earlier)
    nominal_fed = nominal_wire_fed_kg(cfg, e["t_s"])
    row["fed_share"] = fed / nominal_fed if nominal_fed > 0 else float("nan")
    row["area_error_fed"] = (row["area_mm2"] / (row["nominal_mm2"] * row["fed_share"]) - 1.0
                             if row["fed_share"] > 0 else float("nan"))
    return row


STEADY_SPREAD = 0.5  # bins spread above this: the window's mean is not a steady bead's


def fmt(key: str, v) -> str:
    spec = next(f for k, _, f, _ in COLUMNS if k == key)
    if v is None:
        return "–"  # (a row recorded before the column existed)
    if isinstance(v, float) and math.isnan(v):
        return "nan"
    return spec.format(v)


def table(rows: list[dict]) -> str:
    lines = ["| " + " | ".join(h for _, h, _, _ in COLUMNS) + " |", "|" + "---|" * len(COLUMNS)]
    for r in rows:
        lines.append("| " + " | ".join(fmt(k, r.get(k)) for k, _, _, _ in COLUMNS) + " |")
    if rows:
        h = [r["dx_mm"] for r in rows]
        ext = {k: richardson(h, [r[k] for r in rows]) for k, _, _, e in COLUMNS if e}
        cells = []
        for k, _, _, e in COLUMNS:
            if k == "dx_mm":
                cells.append("→ 0 (Richardson)")
            elif e:
                x = ext[k]
                cells.append("nan" if math.isnan(x["f0"]) else f"{fmt(k, x['f0'])} (p = {x['p']:.2f})")
            elif k == "area_error" and not math.isnan(ext["area_mm2"]["f0"]):
                cells.append(fmt(k, ext["area_mm2"]["f0"] / rows[0]["nominal_mm2"] - 1.0))
            else:
                cells.append("")
        lines.append("| " + " | ".join(cells) + " |")
        why = {x["why"] for x in ext.values() if x["why"]}
        if why:
            lines.append("")
            lines.append("Not extrapolated (nan): " + "; ".join(sorted(why)) + ".")
        lines.append("")
        lines.append("Each row's difference from the extrapolated value:")
        lines.append("")
        keys = [k for k, _, _, e in COLUMNS if e]
        lines.append("| dx mm | " + " | ".join(k for k in keys) + " |")
        lines.append("|" + "---|" * (len(keys) + 1))
        for r in rows:
            cells = []
            for k in keys:
                f0 = ext[k]["f0"]
                cells.append("nan" if math.isnan(f0) or f0 == 0 else f"{r[k] / f0 - 1:+.1%}")
            lines.append(f"| {r['dx_mm']:.3f} | " + " | ".join(cells) + " |")
        lines += ["", convergence(rows, ext, keys)]
    lines += ["\n" + n for n in map(unsteady, rows) if n]
    return "\n".join(lines)


def spread(bins_mm2: list[float]) -> float:
    """(max - min) / mean of a window's bins (NaN for none)."""
    mean = sum(bins_mm2) / len(bins_mm2) if bins_mm2 else 0.0
    return (max(bins_mm2) - min(bins_mm2)) / mean if mean > 0 else float("nan")


def unsteady(row: dict) -> str | None:
    """The note for a row whose bins spread more than :data:`STEADY_SPREAD` (None if they do not)."""
    if not (row.get("bins_spread") or 0.0) > STEADY_SPREAD:
        return None
    return (f"Not a steady bead at dx = {row['dx_mm']:g} mm: the window's bins hold "
            + ", ".join(f"{a:.2f}" for a in row["bins_mm2"]) + f" mm2 (spread {row['bins_spread']:.0%} > "
            f"{STEADY_SPREAD:.0%}): its mean is not a settled cross-section.")


def convergence(rows: list[dict], ext: dict, keys: list[str], tol: float = 0.1) -> str:
    """The two finest rows' difference per column (relative to the finer), and, from the
    observed order p and limit f0, the spacing below which two rungs of the same ratio would
    differ by less than ``tol``: with f(h) = f0 + C h^p (C from the finest row), |C| h^p (r^p - 1)
    < tol |f0|, r = h2 / h1."""
    fine = sorted(rows, key=lambda r: r["dx_mm"])[:2]
    if len(fine) < 2:
        return ""
    (h1, r1), (h2, r2) = ((r["dx_mm"], r) for r in fine)
    out = [f"Convergence: the two finest ({h2:g} and {h1:g} mm) differ by, and the spacing at which two rungs "
           f"{h2 / h1:.3f} apart would differ by less than {tol:.0%} (from p and the limit):", "",
           "| column | difference | spacing for < " + f"{tol:.0%}" + " mm |", "|---|---|---|"]
    for k in keys:
        f1, f2 = r1[k], r2[k]
        diff = (f2 - f1) / f1 if f1 else float("nan")
        x = ext[k]
        need = "nan"
        if not math.isnan(x["f0"]) and x["f0"] != 0 and f1 != x["f0"]:
            C = (f1 - x["f0"]) / h1 ** x["p"]
            need = f"{(tol * abs(x['f0']) / (abs(C) * ((h2 / h1) ** x['p'] - 1.0))) ** (1.0 / x['p']):.3g}"
        out.append(f"| {k} | {diff:+.1%} | {need} |")
    return "\n".join(out)


def plot(rows: list[dict], png: Path, title: str):
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    fig, ax = plt.subplots(figsize=(5.6, 4.0), dpi=110)
    w = [r["wall_s"] for r in rows]
    err = [abs(r["area_error"]) for r in rows]
    ax.loglog(w, err, "o-")
    for r, x, y in zip(rows, w, err):
        ax.annotate(f"dx {r['dx_mm']:g} mm", (x, y), textcoords="offset points", xytext=(4, 4), fontsize=8)
    ax.set_xlabel("wall time (s, one core)")
    ax.set_ylabel("|bead cross-section error| vs nominal")
    ax.set_title(title, fontsize=9)
    ax.grid(True, which="both", alpha=0.3)
    ax.xaxis.set_minor_formatter(matplotlib.ticker.NullFormatter())  # ticks at the runs' own times
    shown = []  # the runs' own times, less those within 25 % of one already labelled
    for x in sorted(w):
        if not shown or x > 1.25 * shown[-1]:
            shown.append(x)
    ax.set_xticks(shown, [f"{x:.0f}" for x in shown])
    fig.tight_layout()
    fig.savefig(png)
    print(f"wrote {png}")


def recorded_rows(paths: list[Path], t_end: float, case: str) -> dict:
    """Rows of finished runs from ``--json`` files, by dx (mm): for rungs whose run folders are
    elsewhere (a fine rung is hours of runs); a file for another case or window is refused."""
    out = {}
    for p in paths:
        d = json.loads(Path(p).read_text())
        if Path(d["case"]).name != Path(case).name or abs(d["t_end_s"] - t_end) > 1e-9 * t_end:
            raise SystemExit(f"--rows {p}: rows of {d['case']} over 0 .. {d['t_end_s']} s, not of {case} "
                             f"over 0 .. {t_end:g} s")
        for r in d["rows"]:
            out[round(r["dx_mm"], 6)] = r
    return out


def main():
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("case")
    ap.add_argument("--dx", type=float, nargs="+", required=True, help="resolutions, mm")
    ap.add_argument("--t-end", type=float, default=0.4, help="process time of every run, s")
    ap.add_argument("--out", type=Path, default=None)
    ap.add_argument("--jobs", type=int, default=1)
    ap.add_argument("--leg-s", type=float, default=None, help="stop each run after this wall time (continue later)")
    ap.add_argument("--checkpoint-every", type=int, default=2000)
    ap.add_argument("--set", dest="overrides", action="append", default=[], help="extra case overrides")
    ap.add_argument("--read", action="store_true", help="only tabulate the runs there are")
    ap.add_argument("--plot", type=Path, default=None)
    ap.add_argument("--json", type=Path, default=None)
    ap.add_argument("--rows", type=Path, nargs="+", default=[],
                    help="rows of earlier runs (a --json file) for the resolutions whose run folder is not "
                         "under --out (a run there takes precedence); tabulated and plotted with the others")
    a = ap.parse_args()
    if any(dx <= 0 for dx in a.dx) or a.t_end <= 0 or a.jobs < 1:
        ap.error("--dx values, --t-end and --jobs must be positive")
    out = a.out or ROOT / "output_resolution" / Path(a.case).name
    if not a.read:
        run_all(a, out)
    rows, missing = [], []
    earlier = recorded_rows(a.rows, a.t_end, a.case)
    for dx in sorted(a.dx, reverse=True):
        d = run_dir(out, dx)
        t = reached(d)
        if t >= a.t_end * (1 - 1e-9) and (d / "summary.json").exists():
            rows.append(analyse(d, dx))
        elif round(dx, 6) in earlier:
            rows.append(earlier[round(dx, 6)])
        else:
            missing.append(f"dx = {dx:g} mm: reached t = {t:.4f} of {a.t_end:g} s")
    print(f"# {a.case}, 0 .. {a.t_end:g} s, {len(rows)} resolutions finished")
    print(table(rows))
    for m in missing:
        print("unfinished:", m)
    if a.json is not None:
        a.json.write_text(json.dumps({"case": a.case, "t_end_s": a.t_end, "rows": rows, "unfinished": missing},
                                     indent=1, default=float))
    if a.plot is not None and rows:
        plot(rows, a.plot, f"{Path(a.case).name}, 0 .. {a.t_end:g} s")


if __name__ == "__main__":
    main()
