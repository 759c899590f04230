"""A run's summary (melt pool, bead, settling, solidification) and pictures: ``python -m
torchsph.post RUN`` (:func:`main`)."""
from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np

from torchsph.io.snapshots import read_snapshot
from torchsph.post.analysis import (
    bead_profile,
    default_steady_range,
    load_run,
    melt_pool,
    melt_pool_history,
    section,
    settling_report,
    steady_average,
    volumes,
)
from torchsph.post.pictures import render, timelapse
from torchsph.post.solidification import solidification, write_exaca_csv


def summarize(run_dir: str | Path, section_x: float | None = None, exaca: bool = False,
              render_png: bool = False, gif: bool = False) -> dict:
    run_dir = Path(run_dir)
    cfg, snaps = load_run(run_dir)
    out_dir = run_dir / "post"
    out_dir.mkdir(exist_ok=True)
    last = read_snapshot(snaps[-1][1])
    res = {"run": str(run_dir), "melt_pool": melt_pool_history(run_dir),
           "liquid_all": melt_pool(last, cfg["thermal"]["liquidus_K"], cfg["scene"]["dx_m"], vol=volumes(last, cfg),
                                   connected=False) if cfg["scene"].get("dx_m") and "thermal" in cfg else None}
    if cfg["scene"]["type"] == "deposition":
        prof = bead_profile(last, cfg)
        lo, hi = default_steady_range(last, cfg)
        res["bead_steady"] = steady_average(prof, lo, hi)
        res["bead_settling"] = settling_report(run_dir, lo, hi)
        res["bead_profile"] = {k: np.asarray(v).tolist() for k, v in prof.items()}
        sx = section_x if section_x is not None else 0.5 * (lo + hi)
        res["section"] = section(last, cfg, sx, out_dir / "section.png")
    if exaca:
        V = (cfg["scene"].get("substrate_velocity_m_s") or [0.0])[0]
        sol = solidification([read_snapshot(p) for _, p in snaps], cfg["thermal"]["liquidus_K"],
                             cfg["scene"]["dx_m"], V)
        res["exaca_rows"] = write_exaca_csv(out_dir / "exaca.csv", sol, cfg["scene"]["dx_m"])
    if render_png:
        render(last, out_dir / "temperature.png", cfg, "temperature")
        res["velocity_png"] = render(last, out_dir / "velocity.png", cfg, "velocity")
    if gif:
        timelapse(run_dir, out_dir / "temperature.gif")
    (out_dir / "post.json").write_text(json.dumps(res, indent=1, default=float) + "\n")
    return res


def main(argv=None):
    ap = argparse.ArgumentParser(prog="python -m torchsph.post.analysis", description=__doc__,
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("run", type=Path, help="a run's output folder")
    ap.add_argument("--section", type=float, default=None, metavar="X0_M",
                    help="substrate-frame x of the transverse section (default: mid steady range)")
    ap.add_argument("--exaca", action="store_true", help="write post/exaca.csv (x,y,z,tm,tl,cr)")
    ap.add_argument("--render", action="store_true", help="PNG renders of the last snapshot (PyVista)")
    ap.add_argument("--gif", action="store_true", help="time-lapse GIF (PyVista + imageio)")
    a = ap.parse_args(argv)
    res = summarize(a.run, a.section, a.exaca, a.render, a.gif)
    mp = res["melt_pool"][-1]
    print(f"melt pool at t = {mp['time_s']:.4g} s (the largest connected liquid body reaching into the substrate): "
          f"length {mp['length_m'] * 1e3:.3f} mm, width {mp['width_m'] * 1e3:.3f} mm, depth "
          f"{mp['depth_m'] * 1e3:.3f} mm, volume {mp['volume_m3'] * 1e9:.4f} mm^3, peak {mp['peak_temperature_K']:.0f} K")
    la = res.get("liquid_all")
    if la is not None and la.get("n_liquid", 0) > mp.get("n_liquid", 0):
        print(f"all liquid (deposit.json's measure: with drops on the wire and spatter): length "
              f"{la['length_m'] * 1e3:.3f} mm, width {la['width_m'] * 1e3:.3f} mm, volume {la['volume_m3'] * 1e9:.4f} mm^3")
    if "bead_steady" in res:
        b = res["bead_steady"]
        if b["columns"] == 0 or not np.isfinite(b["width_m"]):
            print(f"bead: none yet at t = {mp['time_s']:.4g} s (no deposited column behind the pool and past the "
                  "start; the bead forms once the substrate has carried melt past the pool: run longer)")
        else:
            print(f"bead over x0 in [{b['x_range_m'][0] * 1e3:.2f}, {b['x_range_m'][1] * 1e3:.2f}] mm "
                  f"({b['columns']} columns): width {b['width_m'] * 1e3:.3f} mm, height {b['height_m'] * 1e3:.3f} mm, "
                  f"penetration {b['penetration_m'] * 1e3:.3f} mm, added area {b['added_area_m2'] * 1e6:.3f} mm^2, "
                  f"toe angle {b['toe_angle_deg']:.1f} deg (circular segment)")
        st = res["bead_settling"]
        if "error" in st:
            print(f"bead settling: not yet measurable ({st['error']})")
        elif not st["settled_bins"]:
            print(f"bead settling: no 1 mm bin has stopped filling yet ({len(st['bins'])} bins behind the pool)")
        else:
            print(f"bead settling (deposit.json, 1 mm bins, changed <= {st['tolerance']:.0%} since t = "
                  f"{st['t_before_s']:.3g} s): {st['settled_bins']} of {len(st['bins'])} bins settled, "
                  f"mean added area {st['settled_m2'] * 1e6:.3f} mm^2")
    if res.get("velocity_png") is False:
        print("no melt in the last snapshot: no velocity picture")
    print(f"wrote {Path(a.run) / 'post'}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
