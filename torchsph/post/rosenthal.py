"""The Rosenthal study: a beam moving over a thick steel plate in conduction mode (no
flow, constant properties, insulated surface) against the quasi-steady Rosenthal
solution T - T0 = Q / (2 pi k R) exp(-v (xi + R) / (2 alpha)), R = |(xi, y, z)|,
xi = x - x_beam, and against its superposition over the beam's Gaussian spot.

The T = T_L isotherm's length (along the travel) and width are measured on the top
particle layer, by the same interpolation for the SPH field and the analytic ones.
"""
from __future__ import annotations

import math
import time

import torch

from torchsph.io.config import validate
from torchsph.run.build import make_simulation
from torchsph.step.loop import run_steps

K, RHO, CP, T0, TL = 42.0, 7890.0, 450.0, 300.0, 1753.15


def rosenthal(xi, y, z, Q, v):
    alpha = K / (RHO * CP)
    R = torch.sqrt(xi * xi + y * y + z * z).clamp_min(1e-9)
    return T0 + Q / (2 * math.pi * K * R) * torch.exp(-v * (xi + R) / (2 * alpha))


def rosenthal_gaussian(xi, y, z, Q, v, r, n=41):
    """Superposition of point sources over the Gaussian spot (1/e^2 radius r)."""
    s = torch.linspace(-2.5 * r, 2.5 * r, n, dtype=xi.dtype)
    a, b = torch.meshgrid(s, s, indexing="ij")
    w = torch.exp(-2 * (a * a + b * b) / (r * r))
    w = (w / w.sum()).reshape(-1)
    out = torch.zeros_like(xi)
    for wk, ak, bk in zip(w.tolist(), a.reshape(-1).tolist(), b.reshape(-1).tolist()):
        out += wk * (rosenthal(xi - ak, y - bk, z, Q, v) - T0)
    return T0 + out


def extent(coord, T):
    """Interval of ``coord`` (sorted) where T > TL, by linear interpolation at both ends."""
    above = torch.nonzero(T > TL).squeeze(1)
    if above.numel() == 0:
        return 0.0, 0.0
    i0, i1 = int(above[0]), int(above[-1])
    def cross(i, j):
        return float(coord[i] + (TL - T[i]) * (coord[j] - coord[i]) / (T[j] - T[i]))
    lo = cross(i0 - 1, i0) if i0 > 0 else float(coord[i0])
    hi = cross(i1, i1 + 1) if i1 + 1 < coord.numel() else float(coord[i1])
    return lo, hi


def isotherm(x, y, T, dx):
    """Length along x on the rows nearest y = 0 and full width over the x columns."""
    ys = torch.unique(y)
    row = ys[ys.abs().argmin()]
    sel = (y - row).abs() < 1e-9 * dx + 1e-12
    o = torch.argsort(x[sel])
    lo, hi = extent(x[sel][o], T[sel][o])
    width = 0.0
    for xc in torch.unique(x).tolist():
        c = ((x - xc).abs() < 1e-12) & (y > 0)
        if not bool(c.any()):
            continue
        o = torch.argsort(y[c])
        yy, TT = y[c][o], T[c][o]
        if TT[0] <= TL:
            continue
        above = torch.nonzero(TT > TL).squeeze(1)
        i1 = int(above[-1])
        if i1 + 1 < yy.numel():
            width = max(width, 2 * float(yy[i1] + (TL - TT[i1]) * (yy[i1 + 1] - yy[i1]) / (TT[i1 + 1] - TT[i1])))
    return hi - lo, width


def run_study(dx: float, t_end: float = 0.3, power: float = 500.0, speed: float = 0.015,
              radius: float = 0.2e-3, compile: bool = False, x_start: float = -3e-3,
              length: float = 10e-3, width: float = 5e-3, depth: float = 3e-3) -> dict:
    """Run the beam over a length x width x depth plate (centred on x = y = 0, top at z = 0) from
    x_start for t_end and measure the isotherm; lengths in m."""
    raw = {
        "scene": {"type": "block", "dim": 3, "size_m": [length, width, depth], "dx_m": dx, "temperature_K": T0},
        "fluid": {"rho0_kg_m3": RHO},
        "thermal": {"conductivity_W_mK": K, "specific_heat_J_kgK": CP},
        "beam": [{"power_W": power, "efficiency": 1.0, "radius_m": radius, "direction": [0.0, 0.0, -1.0],
                  "aim_m": [x_start, 0.0, 0.0], "velocity_m_s": [speed, 0.0, 0.0]}],
        "numerics": {"compile": compile},
        "run": {"t_end_s": t_end},
    }
    _, sim = make_simulation(validate(raw))
    t0 = time.perf_counter()
    run_steps(sim, t_end=t_end)
    wall = time.perf_counter() - t0
    s = sim.state
    top = s.x[:, 2] > -dx
    xb = x_start + speed * sim.t
    x, y, z, T = s.x[top, 0], s.x[top, 1], s.x[top, 2], s.T[top]
    out = {"n": s.n, "steps": sim.step, "wall_s": wall}
    out["sph"] = isotherm(x, y, T, dx)
    out["gaussian"] = isotherm(x, y, rosenthal_gaussian(x - xb, y, z, power, speed, radius), dx)
    out["point"] = isotherm(x, y, rosenthal(x - xb, y, z, power, speed), dx)
    return out
