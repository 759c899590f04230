"""Exact solutions the verification compares with (SPEC §6): the Taylor-Green vortex, start-up
Poiseuille flow, conduction into a semi-infinite solid, a diffusing Gaussian bump in a
periodic box, the one-phase Stefan problem (Neumann), and a box heated from within. The scenes use some of them as
initial conditions; :mod:`torchsph.post.rosenthal` holds the moving point source."""
from __future__ import annotations

import itertools
import math

import numpy as np
import torch


def taylor_green_exact(x, t, L, U, nu):
    """Velocity field of the 2-D Taylor-Green vortex, u = -U cos(kx) sin(ky) e^{-2 k^2 nu t}."""
    k = 2.0 * math.pi / L
    decay = math.exp(-2.0 * k * k * nu * t)
    u = -U * torch.cos(k * x[:, 0]) * torch.sin(k * x[:, 1]) * decay
    v = U * torch.sin(k * x[:, 0]) * torch.cos(k * x[:, 1]) * decay
    return torch.stack([u, v], dim=-1)


def poiseuille_exact(y, t, H, F, nu, terms=200):
    """Start-up Poiseuille flow between plates y = 0 and y = H driven by acceleration F."""
    u = F / (2.0 * nu) * y * (H - y)
    if t == math.inf:
        return u
    for n in range(terms):
        k = 2 * n + 1
        u = u - 4.0 * F * H * H / (nu * math.pi**3 * k**3) * torch.sin(k * math.pi * y / H) * \
            math.exp(-(k * k) * math.pi**2 * nu * t / (H * H))
    return u


def conduction_1d_exact(x, t, alpha, T_face, T0):
    """Semi-infinite solid, face x = 0 held at T_face from t = 0: T0 + dT erfc(x / 2 sqrt(a t))."""
    if t <= 0:
        return torch.where(x > 0, torch.full_like(x, T0), torch.full_like(x, T_face))
    return T0 + (T_face - T0) * torch.special.erfc(x / (2.0 * math.sqrt(alpha * t)))


def gaussian_bump_exact(x, t, alpha, center, sigma, A, Tb, domain):
    """Diffusion of T = Tb + A exp(-r^2 / (2 sigma^2)) in a periodic box: the free-space
    solution summed over the 3^d nearest periodic images of the bump."""
    d = x.shape[1]
    s2 = sigma * sigma + 2.0 * alpha * t
    c = torch.as_tensor(center, dtype=x.dtype, device=x.device)
    r0 = domain.minimum_image(x - c)
    L = torch.as_tensor(domain.length, dtype=x.dtype, device=x.device)
    total = torch.zeros_like(x[:, 0])
    for img in itertools.product((-1, 0, 1), repeat=d):
        r = r0 + torch.as_tensor(img, dtype=x.dtype, device=x.device) * L
        total = total + torch.exp(-(r * r).sum(-1) / (2.0 * s2))
    return Tb + A * (sigma * sigma / s2) ** (d / 2) * total


def neumann_lambda(stefan: float) -> float:
    """Root of lambda exp(lambda^2) erf(lambda) = St / sqrt(pi) (one-phase Stefan problem)."""
    lo, hi = 0.0, 5.0
    for _ in range(200):
        mid = 0.5 * (lo + hi)
        if mid * math.exp(mid * mid) * math.erf(mid) > stefan / math.sqrt(math.pi):
            hi = mid
        else:
            lo = mid
    return 0.5 * (lo + hi)


def melt_front(x: torch.Tensor, T: torch.Tensor, T_m: float) -> float:
    """Position where the (cross-section averaged) temperature profile T(x), decreasing
    in x, crosses T_m, by linear interpolation between particle columns."""
    xs, inv = torch.unique(x, return_inverse=True)
    Tm = torch.zeros_like(xs).index_add_(0, inv, T) / torch.bincount(inv, minlength=xs.numel()).to(T.dtype)
    below = torch.nonzero(Tm < T_m)
    if below.numel() == 0:
        return float(xs[-1])
    k = int(below[0])
    if k == 0:
        return float(xs[0])
    x0, x1, T0, T1 = float(xs[k - 1]), float(xs[k]), float(Tm[k - 1]), float(Tm[k])
    return x0 + (T0 - T_m) * (x1 - x0) / (T0 - T1)


def box_source_rise(x: torch.Tensor, t: float, lo, hi, alpha: float, rho_cp: float, q: float,
                    ends=None, n: int = 400) -> torch.Tensor:
    """T - T0 at points ``x`` (N, d) for a uniform volumetric source ``q`` (W/m^3) in the
    box [lo, hi], switched on at t = 0 in a medium at rest at T0 (no latent heat):
    q / (rho c_p) int_0^t prod_axes F_a(s) ds, with the 1-D slab factor
    F = [erf((b - x) / 2 sqrt(alpha s)) - erf((a - x) / 2 sqrt(alpha s))] / 2. ``ends``: per
    axis, insulated faces (e0, e1) of a finite body, by the first images of the box in each
    (accurate while sqrt(alpha t) is small against the body). Gauss-Legendre in s, ``n`` nodes."""
    s, w = np.polynomial.legendre.leggauss(n)
    s = torch.tensor(0.5 * t * (s + 1.0), dtype=x.dtype, device=x.device)
    w = torch.tensor(0.5 * t * w, dtype=x.dtype, device=x.device)
    L = 2.0 * torch.sqrt(alpha * s)
    prod = torch.ones(x.shape[0], s.numel(), dtype=x.dtype, device=x.device)
    for a in range(x.shape[1]):
        xa = x[:, a:a + 1]

        def slab(p, q_):
            return 0.5 * (torch.erf((q_ - xa) / L) - torch.erf((p - xa) / L))
        f = slab(lo[a], hi[a])
        if ends is not None:
            e0, e1 = ends[a]
            f = f + slab(2 * e0 - hi[a], 2 * e0 - lo[a]) + slab(2 * e1 - hi[a], 2 * e1 - lo[a])
        prod = prod * f
    return q / rho_cp * (prod * w).sum(1)


def circular_cap(size: float, theta: float, dim: int = 2) -> dict:
    """The circular cap (2-D: a circle's segment of area ``size``; 3-D: a sphere's cap of
    volume ``size``) that meets a flat plate at the contact angle ``theta`` (rad), valid below
    the capillary length (SPEC 3b): radius R, base width W = 2 R sin(theta), height
    H = R (1 - cos(theta)); 2-D area R^2 (theta - sin(theta) cos(theta)), 3-D volume
    pi R^3 (2 - 3 cos(theta) + cos^3(theta)) / 3."""
    c = math.cos(theta)
    if dim == 2:
        R = math.sqrt(size / (theta - math.sin(theta) * c))
    else:
        R = (3.0 * size / (math.pi * (2.0 - 3.0 * c + c**3))) ** (1.0 / 3.0)
    return {"R": R, "W": 2.0 * R * math.sin(theta), "H": R * (1.0 - c)}


# Harkins & Brown (1919, J. Am. Chem. Soc. 41, 499): the drop-weight correction f(r / V^(1/3))
# of Tate's law m g = 2 pi r sigma f, as tabulated in Adamson & Gast, "Physical Chemistry of
# Surfaces" (the falling drop's mass m and volume V, the tip's outer radius r).
HARKINS_BROWN = ((0.30, 0.7256), (0.40, 0.6828), (0.50, 0.6515), (0.60, 0.6250), (0.70, 0.6093),
                 (0.80, 0.6000), (0.90, 0.5998), (1.00, 0.6098), (1.10, 0.6280), (1.20, 0.6535))


def harkins_brown(psi: float) -> float:
    """The Harkins-Brown factor f at psi = r / V^(1/3), linear between the table's rows
    (0.3 <= psi <= 1.2, where the table holds)."""
    lo, hi = HARKINS_BROWN[0][0], HARKINS_BROWN[-1][0]
    if not lo <= psi <= hi:
        raise ValueError(f"r / V^(1/3) = {psi:.3f} lies outside the Harkins-Brown table ({lo}-{hi})")
    for (a, fa), (b, fb) in zip(HARKINS_BROWN, HARKINS_BROWN[1:]):
        if psi <= b:
            return fa + (fb - fa) * (psi - a) / (b - a)
    return HARKINS_BROWN[-1][1]


def tate_mass(r: float, sigma: float, g: float, rho: float) -> tuple[float, float]:
    """The mass of the drop that falls from a tip of outer radius ``r`` under gravity ``g``
    by Tate's law with the Harkins-Brown factor, m g = 2 pi r sigma f(r / (m / rho)^(1/3))
    (solved by fixed point; f varies slowly): (m, f)."""
    lo, hi = HARKINS_BROWN[0][0], HARKINS_BROWN[-1][0]
    f = 0.6
    for _ in range(100):
        m = 2.0 * math.pi * r * sigma * f / g
        f_new = harkins_brown(min(max(r / (m / rho) ** (1.0 / 3.0), lo), hi))  # (the iterates may stray)
        if abs(f_new - f) < 1e-12:
            break
        f = f_new
    m = 2.0 * math.pi * r * sigma * f / g
    harkins_brown(r / (m / rho) ** (1.0 / 3.0))  # the solution must lie in the table
    return m, f
