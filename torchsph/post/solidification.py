"""Solidification along the fusion line: where and when each particle froze, the temperature
gradient and the solidification rate there (the inputs of a grain-structure model, ExaCA)."""
from __future__ import annotations

from pathlib import Path

import numpy as np


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

    from torchsph.core.neighbors import Domain, build_pairs

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
