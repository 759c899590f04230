"""Post-processing of a run's HDF5 snapshots: melt pool, bead geometry, the fusion-zone
section, solidification data (ExaCA CSV) and PyVista renders.

    python -m torchsph.post.analysis RUN_DIR [--section X_M] [--exaca] [--render] [--gif]

Geometry works on particles: a particle stands for a cube of side dx around its centre, so
an extent of particle centres plus dx is the extent of the material. Frames: the deposition
scene's substrate moves along +x with V_sub; bead measures are in the substrate frame
x0 = x - V_sub t, with the original substrate top at z = 0. Everything here reads numpy
arrays (no torch state), so it also works on snapshots copied off a GPU machine.
"""
from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from torchsph.io.snapshots import read_snapshot

SOLID, SUBSTRATE, WIRE = 2, 1, 2  # phase code of rigid solid; body tags of substrate and wire


# --- loading ----------------------------------------------------------------------
def load_run(run_dir: str | Path) -> tuple[dict, list[tuple[float, Path]]]:
    """The resolved case (config.json) and the snapshots [(t, path)] in time order."""
    run_dir = Path(run_dir)
    cfg = json.loads((run_dir / "config.json").read_text())
    snaps = []
    for p in sorted(run_dir.glob("snap_*.h5")):
        snaps.append((float(read_snapshot(p)["time"]), p))
    return cfg, sorted(snaps)


def volumes(snap: dict, cfg: dict | None = None) -> np.ndarray:
    """Particle volumes m / rho (snapshots without masses: dx^3 from the case)."""
    if "mass" in snap:
        return snap["mass"] / snap["density"]
    dx = cfg["scene"]["dx_m"]
    return np.full(snap["density"].shape, dx**3)


def substrate_x(snap: dict, cfg: dict) -> np.ndarray:
    """x in the substrate frame (x - V_sub t; V_sub = 0 for scenes that do not travel)."""
    v = cfg["scene"].get("substrate_velocity_m_s") or [0.0, 0.0, 0.0]
    return snap["position"][:, 0] - v[0] * float(snap["time"])


# --- melt pool ----------------------------------------------------------------------
def components(x: np.ndarray, link: float) -> np.ndarray:
    """Connected-component labels of points linked within ``link`` (cell-list pairs, label
    propagation: a loop over sweeps, not over points)."""
    import torch

    from torchsph.core.neighbors import Domain, build_pairs

    n = x.shape[0]
    if n == 0:
        return np.zeros(0, np.int64)
    i, j = build_pairs(torch.as_tensor(x, dtype=torch.float64), link, Domain([0.0] * 3, [1.0] * 3, [False] * 3))
    lab = torch.arange(n)
    while True:
        new = lab.scatter_reduce(0, i, lab[j], "amin")
        if torch.equal(new, lab):
            return lab.numpy()
        lab = new


def melt_pool(snap: dict, T_liquidus: float, dx: float, top: float = 0.0, vol=None,
              connected: bool = True, bottom: float = -np.inf) -> dict:
    """Length (x), width (y), depth below ``top`` and volume of the liquid (T > T_L), and
    the peak temperature. Extents are of the particles' cubes (centres +- dx/2). With
    ``connected`` the pool is the largest connected body of liquid (particles within 1.5 dx
    linked) that reaches below ``top`` (else the largest): drops on the wire and spatter are
    counted apart (``n_detached``). ``bottom``: the substrate's bottom face; liquid only
    below it (spatter falling past the substrate) does not reach into it."""
    T = snap["temperature"]
    x = snap["position"]
    liquid = T > T_liquidus
    out = {"time_s": float(snap["time"]), "peak_temperature_K": float(T.max())}
    if connected and liquid.sum() > 1:
        idx = np.nonzero(liquid)[0]
        lab = components(x[idx], 1.5 * dx)
        counts = np.bincount(lab)
        z = x[idx, 2]
        low = np.unique(lab[(z < top) & (z > bottom)])  # bodies that reach into the substrate
        big = low[counts[low].argmax()] if low.size else counts.argmax()
        out["n_detached"] = int((lab != big).sum())
        liquid = np.zeros_like(liquid)
        liquid[idx[lab == big]] = True
    out["n_liquid"] = int(liquid.sum())
    if not liquid.any():
        return out | {"length_m": 0.0, "width_m": 0.0, "depth_m": 0.0, "volume_m3": 0.0}
    p = x[liquid]
    vol = np.full(T.shape, dx**3) if vol is None else vol
    return out | {"length_m": float(np.ptp(p[:, 0]) + dx), "width_m": float(np.ptp(p[:, 1]) + dx),
                  "depth_m": float(max(0.0, top - (p[:, 2].min() - 0.5 * dx))),
                  "volume_m3": float(vol[liquid].sum())}


def substrate_bottom(cfg: dict) -> float:
    """z of the substrate's bottom face (the top is z = 0), less a spacing; -inf if unknown."""
    sc = cfg.get("scene", {})
    size = sc.get("substrate_size_m")
    return -(size[2] + sc["dx_m"]) if size is not None else -np.inf


def melt_pool_history(run_dir: str | Path) -> list[dict]:
    cfg, snaps = load_run(run_dir)
    TL, dx = cfg["thermal"]["liquidus_K"], cfg["scene"]["dx_m"]
    out = []
    for _, p in snaps:
        s = read_snapshot(p)
        out.append(melt_pool(s, TL, dx, vol=volumes(s, cfg), bottom=substrate_bottom(cfg)))
    return out


# --- bead geometry --------------------------------------------------------------------
def detached(snap: dict, dx: float, among: np.ndarray | None = None) -> np.ndarray:
    """Mask of the material above the original top (z > 0) that is not attached to the
    substrate: its connected component (links of 1.5 dx) among ``among`` particles at
    z > -dx holds no particle at or below the top: spatter and drops in flight."""
    pos = snap["position"]
    among = np.ones(pos.shape[0], bool) if among is None else among
    idx = np.nonzero(among & (pos[:, 2] > -dx))[0]
    out = np.zeros(pos.shape[0], bool)
    if idx.size == 0:
        return out
    lab = components(pos[idx], 1.5 * dx)
    grounded = np.zeros(idx.size, bool)
    grounded[np.isin(lab, lab[pos[idx, 2] <= 0.0])] = True
    out[idx[~grounded]] = True
    return out


def bead_profile(snap: dict, cfg: dict, T_liquidus: float | None = None, x0=None, vol=None) -> dict:
    """Bead geometry per substrate-frame column of width dx: width (y extent of the material
    above the original top z = 0), height (top of that material), penetration (depth below
    z = 0 of the fusion line: the deepest particle whose peak temperature passed T_L), the
    added cross-section (volume above the top minus the substrate volume missing below
    it, per unit length), and the toe angle of the circular segment of that width and
    height (tan(theta / 2) = 2 H / W; SPEC 3b). The solid wire is not part of the deposit, nor is material above
    the top that is not attached to the substrate (:func:`detached`: spatter, drops in flight)."""
    sc = cfg["scene"]
    dx = sc["dx_m"]
    TL = cfg["thermal"]["liquidus_K"] if T_liquidus is None else T_liquidus
    x0 = substrate_x(snap, cfg) if x0 is None else x0
    pos = snap["position"]
    vol = volumes(snap, cfg) if vol is None else vol
    deposit = ~((snap["body"] == WIRE) & (snap["phase"] == SOLID))
    deposit &= ~detached(snap, dx, deposit)
    size = sc.get("substrate_size_m")
    if size is not None:  # spatter fallen past the substrate or flung beside it is not the bead's
        deposit &= (pos[:, 2] >= substrate_bottom(cfg)) & (np.abs(pos[:, 1]) <= 0.5 * size[1] + dx)
    lo = x0[deposit].min()
    rigid = deposit & (snap["body"] == SUBSTRATE) & (snap["phase"] == SOLID)
    if rigid.any():  # columns centred on the substrate's lattice, whatever lies furthest back
        anchor = x0[rigid].min()
        lo = anchor - dx * np.ceil((anchor - lo) / dx - 1e-6)
    k = np.floor((x0 - lo) / dx + 0.5).astype(np.int64)  # columns centred on the lattice
    nb = int(k[deposit].max()) + 1
    centres = lo + np.arange(nb) * dx
    above = deposit & (pos[:, 2] > 0)
    below = deposit & (pos[:, 2] <= 0)
    width = np.zeros(nb)
    height = np.zeros(nb)
    pen = np.zeros(nb)
    ka = k[above]
    if ka.size:
        ymin = np.full(nb, np.inf)
        ymax = np.full(nb, -np.inf)
        np.minimum.at(ymin, ka, pos[above, 1])
        np.maximum.at(ymax, ka, pos[above, 1])
        has = np.isfinite(ymin)
        width[has] = ymax[has] - ymin[has] + dx
        np.maximum.at(height, ka, pos[above, 2] + 0.5 * dx)
    fused = below & (snap["peak_temperature"] > TL)
    if fused.any():
        np.maximum.at(pen, k[fused], -pos[fused, 2] + 0.5 * dx)
    v_above = np.bincount(ka, vol[above], minlength=nb)
    v_below = np.bincount(k[below], vol[below], minlength=nb)
    counts = sc.get("substrate_size_m")
    if counts is not None:  # the substrate's own volume per column, from the case
        full = round(counts[1] / dx) * round(counts[2] / dx) * dx**3
    else:
        full = np.median(v_below[v_below > 0])
    area = (v_above - np.maximum(full - v_below, 0.0)) / dx
    # the toe (contact) angle of the circular segment of that width and height (SPEC 3b):
    # tan(theta / 2) = 2 H / W
    toe = np.degrees(2.0 * np.arctan2(2.0 * height, np.where(width > 0, width, np.inf)))
    return {"x0_m": centres, "width_m": width, "height_m": height, "penetration_m": pen,
            "added_area_m2": area, "toe_angle_deg": toe}


def steady_average(profile: dict, x_lo: float, x_hi: float) -> dict:
    """Mean of each bead measure over the columns with x_lo <= x0 <= x_hi."""
    sel = (profile["x0_m"] >= x_lo) & (profile["x0_m"] <= x_hi)
    out = {"x_range_m": [x_lo, x_hi], "columns": int(sel.sum())}
    for key in ("width_m", "height_m", "penetration_m", "added_area_m2", "toe_angle_deg"):
        out[key] = float(profile[key][sel].mean()) if sel.any() else float("nan")
    return out


def default_steady_range(snap: dict, cfg: dict, start_skip: float = 2.0e-3, pool: float = 2.5e-3):
    """Substrate-frame x range behind the wire that has solidified and is past the start."""
    V = cfg["scene"]["substrate_velocity_m_s"][0]
    return -V * float(snap["time"]) + pool, -start_skip


def richardson(h, f) -> dict:
    """Richardson extrapolation to h -> 0 of values ``f`` at resolutions ``h`` (any order,
    distinct), from the three finest: the observed order p solves
    (f3 - f2) / (f2 - f1) = (h3^p - h2^p) / (h2^p - h1^p) (h1 < h2 < h3; bisection over
    0.05 <= p <= 8), and f0 = f1 - (f2 - f1) / ((h2 / h1)^p - 1). With two values, or where
    the three do not converge monotonically (the differences change sign, or no order in
    that range fits), ``f0`` and ``p`` are NaN and ``why`` says so."""
    pts = sorted(zip(h, f))
    nan = float("nan")
    if len(pts) < 3:
        return {"f0": nan, "p": nan, "why": "fewer than three resolutions"}
    (h1, f1), (h2, f2), (h3, f3) = pts[:3]
    d1, d2 = f2 - f1, f3 - f2
    if d1 == 0.0 or d2 == 0.0 or (d1 > 0) != (d2 > 0):
        return {"f0": nan, "p": nan, "why": "not monotone in h (oscillating or flat)"}
    ratio = d2 / d1

    def g(p):
        return (h3**p - h2**p) / (h2**p - h1**p) - ratio

    lo, hi = 0.05, 8.0
    if g(lo) * g(hi) > 0:
        return {"f0": nan, "p": nan, "why": f"no order in [{lo}, {hi}] fits"}
    for _ in range(200):
        mid = 0.5 * (lo + hi)
        if g(lo) * g(mid) <= 0:
            hi = mid
        else:
            lo = mid
    p = 0.5 * (lo + hi)
    return {"f0": f1 - d1 / ((h2 / h1) ** p - 1.0), "p": p, "why": ""}


def nominal_wire_fed_kg(cfg: dict, t: float) -> float:
    """Wire mass the feed brings by time t if it never waits: rho0 pi d^2 / 4 V_wire (t - t_start)."""
    sc = cfg["scene"]
    feed_s = max(t - sc.get("wire_feed_start_s", 0.0), 0.0)
    return cfg["fluid"]["rho0_kg_m3"] * np.pi * sc["wire_diameter_m"] ** 2 / 4.0 * sc["wire_feed_m_s"] * feed_s


def fed_cross_section(history: list[dict], x_lo: float, x_hi: float, V_sub: float, rho0: float) -> float:
    """Cross-section (m^2) of the wire actually fed while the substrate-frame columns
    x_lo <= x0 <= x_hi passed under the wire (t = -x_hi/V ... -x_lo/V; ``wire_fed_kg`` of
    the deposition measures ``history``, linear between them): what the bead there holds if
    all that was fed then was laid there. It is the nominal pi d^2 V_wire / (4 V_sub) less
    the time the feed waited on contact. NaN if that time span is not in the history."""
    ts = np.array([e["t_s"] for e in history])
    fed = np.array([e["wire_fed_kg"] for e in history])
    t1, t2 = -x_hi / V_sub, -x_lo / V_sub
    if not (ts[0] - 1e-12 <= t1 < t2 <= ts[-1] + 1e-12):
        return float("nan")
    return float(np.interp(t2, ts, fed) - np.interp(t1, ts, fed)) / (rho0 * V_sub * (t2 - t1))


def bead_settling(history: list[dict], x_lo: float, x_hi: float, lag_s: float,
                  tolerance: float = 0.05) -> dict:
    """Whether the bead's added cross-section has stopped changing: for each bin of the
    deposition measures ``history`` (``bin_centres_m``/``added_area_m2``, the bins the
    same in every entry) with x_lo <= x0 <= x_hi, its area in the last entry and in the
    last entry at least ``lag_s`` older, and the relative change between them (of the
    later value). A bin is settled when that change is within ``tolerance``; ``settled_m2``
    is the mean over the settled bins (NaN when none is). Melt running back along the bead
    keeps filling a bin for a while after the wire has passed it; a bead is steady where
    its bins are settled."""
    if not history:
        raise ValueError("bead_settling: empty history")
    last = history[-1]
    t_now = last["t_s"]
    earlier = [e for e in history if e["t_s"] <= t_now - lag_s + 1e-12]
    if not earlier:
        raise ValueError(f"bead_settling: no entry {lag_s} s before t = {t_now} s")
    then = earlier[-1]
    if then["bin_centres_m"] != last["bin_centres_m"]:
        raise ValueError("bead_settling: the bins differ between the two entries")
    rows = []
    for x, a, a0 in zip(last["bin_centres_m"], last["added_area_m2"], then["added_area_m2"]):
        if x_lo <= x <= x_hi:
            change = (a - a0) / a if a > 0 else float("inf")
            rows.append({"x0_m": x, "area_m2": a, "area_before_m2": a0, "change": change,
                         "settled": abs(change) <= tolerance})
    good = [r["area_m2"] for r in rows if r["settled"]]
    return {"t_s": t_now, "t_before_s": then["t_s"], "tolerance": tolerance, "bins": rows,
            "settled_bins": len(good),
            "settled_m2": float(np.mean(good)) if good else float("nan")}


# --- transverse section -----------------------------------------------------------------
def section(snap: dict, cfg: dict, x0: float, png: str | Path | None = None, title: str = "",
            ax=None) -> dict:
    """The transverse section at substrate-frame x0 (the thesis's Fig. 6.6): the particles of
    the column at x0, coloured by peak temperature, with the fusion line (the T_L contour
    of the peak temperature) and the original substrate top; returns its numbers. Drawn
    into ``png``, or into the matplotlib axes ``ax`` (a panel of a larger figure)."""
    dx = cfg["scene"]["dx_m"]
    TL = cfg["thermal"]["liquidus_K"]
    xs = substrate_x(snap, cfg)
    prof = bead_profile(snap, cfg)
    j = int(np.argmin(np.abs(prof["x0_m"] - x0)))
    nums = {k: float(prof[k][j]) for k in ("width_m", "height_m", "penetration_m", "added_area_m2")}
    nums["x0_m"] = float(prof["x0_m"][j])
    if png is not None or ax is not None:
        import matplotlib
        if ax is None:
            matplotlib.use("Agg")
        import matplotlib.pyplot as plt

        sel = (np.abs(xs - nums["x0_m"]) < 0.5 * dx) & ~((snap["body"] == WIRE) & (snap["phase"] == SOLID))
        y, z, Tp = snap["position"][sel, 1], snap["position"][sel, 2], snap["peak_temperature"][sel]
        own = ax is None
        if own:
            fig, ax = plt.subplots(figsize=(6, 3.2), dpi=110)
        else:
            fig = ax.figure
        sc_ = ax.scatter(y * 1e3, z * 1e3, c=Tp, s=14, cmap="inferno", marker="s")
        sub = z < 0.5 * dx  # the fusion line runs through the substrate; the bead above is all fused
        if sub.sum() > 3 and Tp[sub].max() > TL > Tp[sub].min():
            ax.tricontour(y[sub] * 1e3, z[sub] * 1e3, Tp[sub], levels=[TL], colors="cyan", linewidths=1.5)
        ax.axhline(0.0, color="w", lw=0.8, ls="--")
        ax.set_aspect("equal")
        ax.set_xlabel("y, mm")
        ax.set_ylabel("z, mm")
        ax.set_facecolor("0.85")
        fig.colorbar(sc_, ax=ax, label="peak temperature, K")
        ax.set_title(title or f"section x0 = {nums['x0_m'] * 1e3:.2f} mm, t = {float(snap['time']):.3f} s; "
                     "cyan: fusion line (T_L)", fontsize=8)
        if own:
            fig.tight_layout()
            fig.savefig(png)
            plt.close(fig)
    return nums


# --- command line ---------------------------------------------------------------------------
def settling_report(run_dir: Path, x_lo: float, x_hi: float, lag_s: float = 0.05) -> dict:
    """:func:`bead_settling` of the run's ``deposit.json`` over x_lo..x_hi (what of the
    bead there has stopped filling), or the reason it cannot be said."""
    path = Path(run_dir) / "deposit.json"
    if not path.exists():
        return {"error": "no deposit.json"}
    try:
        return bead_settling(json.loads(path.read_text()), x_lo, x_hi, lag_s)
    except ValueError as e:
        return {"error": str(e)}
