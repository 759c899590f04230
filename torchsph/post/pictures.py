"""PyVista pictures of a run: the particles coloured by a field, the sections of several runs
side by side, a time-lapse GIF."""
from __future__ import annotations

from pathlib import Path

import numpy as np

from torchsph.io.snapshots import read_snapshot
from torchsph.post.analysis import SOLID, WIRE, detached, load_run, section, substrate_x


# --- renders -----------------------------------------------------------------------------
def focus_box(snap: dict, cfg: dict | None = None, pad_m: float = 1.5e-3):
    """(lo, hi) of the box around what has melted (peak temperature above the liquidus:
    the melt pool, the bead and the wire's melting tip), padded by ``pad_m``; None where
    nothing has melted (the picture frames everything). A full-resolution deposition scene
    has a 30 mm wire and a 20 mm substrate: framing them all leaves the pool a few pixels."""
    TL = (cfg or {}).get("thermal", {}).get("liquidus_K")
    if TL is None:
        return None
    hot = snap["peak_temperature"] > TL
    if not hot.any():
        return None
    p = snap["position"][hot]
    return p.min(0) - pad_m, p.max(0) + pad_m


def render(snap: dict, png: str | Path, cfg: dict | None = None, what: str = "temperature",
           window=(900, 600)) -> bool:
    """Off-screen PyVista render of one snapshot, framed on the melt pool and bead
    (:func:`focus_box`): the particles as points coloured by temperature (what =
    "temperature"), or the melt coloured by its speed with arrows of its velocity over the
    solid in grey (what = "velocity"; nothing is drawn, and False returned, where there is
    no melt). Colour bars carry their units."""
    import pyvista as pv

    pv.OFF_SCREEN = True
    pos = snap["position"]
    box = focus_box(snap, cfg)
    inside = np.ones(len(pos), bool) if box is None else np.all((pos >= box[0]) & (pos <= box[1]), axis=1)
    liquid = (snap["phase"] == 0) & inside
    if what != "temperature" and not liquid.any():
        return False
    bar = dict(vertical=True, position_x=0.86, position_y=0.15, width=0.06, height=0.7, n_labels=5,
               title_font_size=14, label_font_size=12, fmt="%.0f")
    p = pv.Plotter(off_screen=True, window_size=list(window))
    mm = pos * 1e3
    if what == "temperature":
        cloud = pv.PolyData(mm[inside])
        cloud["temperature (K)"] = snap["temperature"][inside]
        p.add_mesh(cloud, scalars="temperature (K)", cmap="inferno", point_size=9, render_points_as_spheres=True,
                   scalar_bar_args={**bar, "title": "temperature (K)"})
    else:
        solid = inside & ~liquid
        p.add_mesh(pv.PolyData(mm[solid]), color="lightgrey", opacity=0.25, point_size=4,
                   render_points_as_spheres=True)
        u = snap["velocity"][liquid]
        speed = np.linalg.norm(u, axis=1)
        cloud = pv.PolyData(mm[liquid])
        cloud["speed (m/s)"] = speed
        args = {**bar, "title": "melt speed (m/s)", "fmt": "%.2g"}
        p.add_mesh(cloud, scalars="speed (m/s)", cmap="viridis", point_size=7, render_points_as_spheres=True,
                   scalar_bar_args=args)
        extent = float(np.ptp(mm[liquid], axis=0).max()) if liquid.sum() > 1 else 1.0
        cloud["vec"] = u
        arrows = cloud.glyph(orient="vec", scale="speed (m/s)", factor=0.25 * max(extent, 0.5) / max(speed.max(), 1e-12))
        p.add_mesh(arrows, color="black")
    p.add_text(f"t = {float(snap['time']) * 1e3:.1f} ms" + ("" if box is None else ", framed on the melt"),
               font_size=10)
    p.camera_position = "iso"
    p.camera.azimuth = 30
    p.reset_camera()
    p.show_axes()
    p.screenshot(str(png))
    p.close()
    return True


def render_sections(runs: list[tuple[dict, dict, str]], x0: float, png: str | Path, behind_m: float = 2.0e-3,
                    half_width_m: float = 3.0e-3, depth_m: float = 2.0e-3, panel=(640, 420)) -> list[dict]:
    """Off-screen PyVista picture of the transverse section at substrate-frame x0 (the thesis's
    Fig. 6.6), one panel per (snapshot, case, title) in ``runs``: the deposit behind the cut
    (substrate-frame x in [x0 - behind_m, x0]; the bead, the substrate to depth_m below its
    top, |y| <= half_width_m) drawn as cubes of side dx, one per particle, seen from the
    cut's side. Colour: peak temperature from the ambient up to the liquidus; what passed the
    liquidus (the fusion zone: the bead and the melted substrate) is crimson. Each panel's
    caption carries the section's width, height and penetration (:func:`section`), which
    are returned."""
    import pyvista as pv

    pv.OFF_SCREEN = True
    ncol = 2 if len(runs) > 1 else 1
    nrow = (len(runs) + ncol - 1) // ncol
    p = pv.Plotter(off_screen=True, shape=(nrow, ncol), window_size=[panel[0] * ncol, panel[1] * nrow],
                   border=False)
    out = []
    for k, (snap, cfg, title) in enumerate(runs):
        dx = cfg["scene"]["dx_m"]
        TL = cfg["thermal"]["liquidus_K"]
        nums = section(snap, cfg, x0)
        out.append(nums)
        xs = substrate_x(snap, cfg)
        pos = snap["position"]
        keep = ~((snap["body"] == WIRE) & (snap["phase"] == SOLID)) & ~detached(snap, dx)
        keep &= (xs <= nums["x0_m"] + 0.5 * dx) & (xs >= nums["x0_m"] - behind_m)
        keep &= (np.abs(pos[:, 1]) <= half_width_m) & (pos[:, 2] >= -depth_m)
        pts = np.column_stack([xs[keep], pos[keep, 1], pos[keep, 2]]) * 1e3
        cloud = pv.PolyData(pts)
        cloud["peak temperature (K)"] = snap["peak_temperature"][keep]
        cubes = cloud.glyph(geom=pv.Cube(x_length=dx * 1e3, y_length=dx * 1e3, z_length=dx * 1e3), scale=False,
                            orient=False)
        p.subplot(k // ncol, k % ncol)
        ambient = float(cfg["thermal"].get("ambient_K", 300.0))
        p.add_mesh(cubes, scalars="peak temperature (K)", cmap="cividis", clim=[ambient, TL], above_color="crimson",
                   show_edges=False, scalar_bar_args=dict(title="peak T (K); crimson: above T_L", n_labels=4,
                                                          fmt="%.0f", title_font_size=12, label_font_size=10,
                                                          position_x=0.2, position_y=0.02, width=0.6, height=0.06))
        p.add_text(f"{title}\nx0 = {nums['x0_m'] * 1e3:.1f} mm, t = {float(snap['time']):.2f} s: "
                   f"W {nums['width_m'] * 1e3:.2f}, H {nums['height_m'] * 1e3:.2f}, "
                   f"P {nums['penetration_m'] * 1e3:.2f} mm", font_size=9)
        focus = pts.mean(0)  # seen from the cut's side, a little from above and aside; fitted to the panel
        p.camera_position = [tuple(focus + np.array([9.0, 2.5, 2.6])), tuple(focus), (0, 0, 1)]
        p.reset_camera()
        p.camera.zoom(1.3)
    p.screenshot(str(png))
    p.close()
    return out


def timelapse(run_dir: str | Path, path: str | Path, what: str = "temperature", fps: int = 5):
    """GIF (or MP4, by the suffix) of renders of every snapshot, via imageio."""
    import tempfile

    import imageio.v2 as imageio

    cfg, snaps = load_run(run_dir)
    frames = []
    with tempfile.TemporaryDirectory() as td:
        for k, (_, p) in enumerate(snaps):
            f = Path(td) / f"f{k:05d}.png"
            render(read_snapshot(p), f, cfg, what, window=(640, 420))
            frames.append(imageio.imread(f))
    imageio.mimsave(path, frames, duration=1.0 / fps) if str(path).endswith(".gif") else \
        imageio.mimsave(path, frames, fps=fps)
