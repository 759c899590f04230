"""Post-processing of a run's HDF5 snapshots: melt pool, bead geometry, the fusion-zone
section, solidification data (ExaCA CSV) and PyVista renders.

    python -m torchsph.post RUN_DIR [--section X_M] [--exaca] [--render] [--gif]

Geometry works on particles: a particle stands for a cube of side dx around its centre, so
an extent of particle centres plus dx is the extent of the material. Frames: the deposition
scene's substrate moves along +x with V_sub; bead measures are in the substrate frame
x0 = x - V_sub t, with the original substrate top at z = 0. Everything here reads numpy
arrays (no torch state), so it also works on snapshots copied off a GPU machine.
"""
from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np

from .io import read_snapshot

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

    from .neighbors import Domain, build_pairs

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


# --- solidification: cooling rate, G, R, ExaCA --------------------------------------------
def _aligned(snaps: list[dict]):
    """Per-snapshot arrays aligned on particle id (rows of ids missing from a snapshot: NaN)."""
    ids = np.unique(np.concatenate([s["id"] for s in snaps]))
    n, K = ids.size, len(snaps)
    T = np.full((K, n), np.nan)
    X = np.full((K, n, 3), np.nan)
    for k, s in enumerate(snaps):
        r = np.searchsorted(ids, s["id"])
        T[k, r] = s["temperature"]
        X[k, r] = s["position"]
    return ids, T, X


def temperature_gradient(x: np.ndarray, T: np.ndarray, radius: float) -> np.ndarray:
    """Least-squares gradient of T over the neighbours within ``radius`` (cell list), (N, 3)."""
    import torch

    from .neighbors import Domain, build_pairs

    xt = torch.as_tensor(x, dtype=torch.float64)
    i, j = build_pairs(xt, radius, Domain([0.0] * 3, [1.0] * 3, [False] * 3))
    i, j = i.numpy(), j.numpy()
    d = x[j] - x[i]
    dT = T[j] - T[i]
    A = np.zeros((x.shape[0], 3, 3))
    b = np.zeros((x.shape[0], 3))
    np.add.at(A, i, d[:, :, None] * d[:, None, :])
    np.add.at(b, i, d * dT[:, None])
    A += np.eye(3) * 1e-30
    ok = np.linalg.det(A) > 0
    g = np.zeros_like(b)
    g[ok] = np.linalg.solve(A[ok], b[ok][..., None])[..., 0]
    return g


def solidification(snaps: list[dict], T_liquidus: float, dx: float, V_sub: float = 0.0) -> dict:
    """Where each particle last crossed the liquidus while cooling: the crossing time tl
    (linear in time between the two snapshots around it), the melting time tm (its first
    upward crossing), the cooling rate cr = -dT/dt over that interval, the thermal gradient
    G = |grad T| at the snapshot nearest tl, and the solidification rate R = cr / G.
    Positions are in the substrate frame at tl. Vectorised over particles (a loop over
    snapshots only)."""
    t = np.array([float(s["time"]) for s in snaps])
    ids, T, X = _aligned(snaps)
    K, n = T.shape
    above = T >= T_liquidus
    down = above[:-1] & (T[1:] < T_liquidus)  # (K-1, n) cooling crossings
    up = (~above[:-1]) & (T[1:] >= T_liquidus) & np.isfinite(T[:-1])
    has = down.any(0)
    last = (K - 2) - np.argmax(down[::-1], axis=0)  # last cooling interval
    cols = np.arange(n)
    T0, T1 = T[last, cols], T[last + 1, cols]
    t0, t1 = t[last], t[last + 1]
    frac = (T0 - T_liquidus) / np.where(T0 > T1, T0 - T1, 1.0)
    tl = t0 + frac * (t1 - t0)
    cr = (T0 - T1) / (t1 - t0)
    first_up = np.argmax(up, axis=0)
    tm = np.where(up.any(0), t[first_up] + (T_liquidus - T[first_up, cols]) /
                  np.where(T[first_up + 1, cols] > T[first_up, cols], T[first_up + 1, cols] - T[first_up, cols], 1.0)
                  * (t[first_up + 1] - t[first_up]), t[0])
    pos = X[last, cols] + frac[:, None] * (X[last + 1, cols] - X[last, cols])
    pos[:, 0] -= V_sub * tl
    G = np.full(n, np.nan)
    near = np.where(frac < 0.5, last, last + 1)
    for k in np.unique(near[has]):  # a loop over snapshots
        ok = np.isfinite(T[k])
        g = temperature_gradient(X[k][ok], T[k][ok], 2.01 * dx)
        gk = np.full(n, np.nan)
        gk[np.nonzero(ok)[0]] = np.linalg.norm(g, axis=1)
        sel = has & (near == k)
        G[sel] = gk[sel]
    R = cr / np.where(G > 0, G, np.nan)
    return {"id": ids[has], "x": pos[has, 0], "y": pos[has, 1], "z": pos[has, 2], "tm": tm[has],
            "tl": tl[has], "cr": cr[has], "G": G[has], "R": R[has]}


def write_exaca_csv(path: str | Path, sol: dict, dx: float):
    """ExaCA FromFile temperature data: header ``x,y,z,tm,tl,cr``; x, y, z in metres snapped
    to the Cartesian grid of spacing dx (ExaCA's cell size), tm, tl in s, cr in K/s. Where
    several particles fall in one cell the last to solidify is kept."""
    xyz = np.stack([sol["x"], sol["y"], sol["z"]], 1)
    cell = np.round(xyz / dx).astype(np.int64)
    order = np.argsort(sol["tl"], kind="stable")[::-1]  # latest first: np.unique keeps the first
    _, first = np.unique(cell[order], axis=0, return_index=True)
    keep = order[first]
    keep = keep[np.lexsort((cell[keep, 0], cell[keep, 1], cell[keep, 2]))]
    rows = np.column_stack([cell[keep] * dx, sol["tm"][keep], sol["tl"][keep], sol["cr"][keep]])
    np.savetxt(path, rows, delimiter=",", header="x,y,z,tm,tl,cr", comments="", fmt="%.9g")
    return rows.shape[0]


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
    ap = argparse.ArgumentParser(prog="python -m torchsph.post", description=__doc__,
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
