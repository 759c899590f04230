"""Energy equation: Cleary-Monaghan heat conduction (3.13) with per-particle conductivity
and the effective heat capacity of melting (2.11).

rho c_eff dT/dt = div(k grad T) is solved for every particle that is not a fixed-
temperature wall (fluid and rigid solid alike); wall particles hold their temperature
(a Dirichlet boundary). The step evaluates the pair sum with the cached sparse operator
of :mod:`torchsph.heat_operator`; :func:`conduction_pairs`, the same sum on a neighbour
table, is its reference (the tests compare the two at every step).
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import torch

from .fluid import embed, gather_nb, pair_geometry, tiny
from .free_surface import ColourGradient, colour_gradient_pairs  # noqa: F401 (re-exported)
from .beam import BeamPlan, beams_power, in_beam, reachable
from .heat_operator import ENTRY_BLOCK, ConductionOperator, SlowSplit, by_rows, row_entries
from .kernels import Kernel
from .neighbors import Domain
from .state import Array, Holder, ParticleState, Phase

# the conduction's per-particle arrays (the registry, torchsph.particles, carries them)
CONDUCTION_ARRAYS = {
    "k": Array("thermal conductivity", "W/(m K)", output="conductivity", from_case=True),
    "T_set": Array("the walls' prescribed temperature", "K"),
    "steady": Array("solid with no phase change since the conduction matrix was made", lazy=True),
    "x_op": Array("the positions the conduction matrix was made at", "m", lazy=True, vector=True),
    "zeta_cache": Array("the Laplacian's normalisation zeta at the last selection", lazy=True),
    "area_cache": Array("free-surface area of the losses at the last selection (0 off the surface)", "m^2",
                        output="surface_area", lazy=True),
    "normal": Array("outward normal of the losses' surface", lazy=True, vector=True),
    "zeta_ok": Array("rows whose zeta is up to date", lazy=True),
    "area_ok": Array("rows whose area is up to date", lazy=True),
    # the last rebuild's values, reused by the lazy recomputation: carried only while it is
    # pending (else unused, and kept out of the per-step ghost refresh)
    "zeta_prev": Array("zeta at the rebuild before", lazy=True, when=lambda th: getattr(th, "zeta_cache", None) is None),
    "area_prev": Array("area at the rebuild before", "m^2", lazy=True, when=lambda th: getattr(th, "area_cache", None) is None),
    "normal_prev": Array("normal at the rebuild before", lazy=True, vector=True, when=lambda th: getattr(th, "area_cache", None) is None),
    "lit": Array("lit by a beam at the last evaluation", output="lit", lazy=True),
}


@dataclass
class ThermalParams:
    conductivity: float  # W/(m K)
    specific_heat: float  # J/(kg K)
    latent_heat: float = 0.0  # J/kg, melting
    solidus: float = 0.0  # K
    liquidus: float = 0.0  # K


def effective_heat_capacity(T: torch.Tensor, prm: ThermalParams) -> torch.Tensor:
    """c_eff = c_p + h_f exp(-((T - T_SL)/(T_L - T_S))^2) / (sqrt(pi) (T_L - T_S)) (2.11);
    its integral over T adds exactly h_f to the enthalpy."""
    if prm.latent_heat <= 0.0:
        return torch.full_like(T, prm.specific_heat)
    dT = prm.liquidus - prm.solidus
    tsl = 0.5 * (prm.solidus + prm.liquidus)
    return prm.specific_heat + prm.latent_heat * torch.exp(-((T - tsl) / dT) ** 2) / (math.sqrt(math.pi) * dT)


def enthalpy(T: torch.Tensor, prm: ThermalParams, T_ref: float) -> torch.Tensor:
    """h(T) = int_{T_ref}^T c_eff dT' (J/kg), in closed form."""
    h = prm.specific_heat * (T - T_ref)
    if prm.latent_heat > 0.0:
        dT = prm.liquidus - prm.solidus
        tsl = 0.5 * (prm.solidus + prm.liquidus)
        h = h + 0.5 * prm.latent_heat * (torch.erf((T - tsl) / dT) - math.erf((T_ref - tsl) / dT))
    return h


def temperature_from_enthalpy(H: torch.Tensor, prm: ThermalParams, T_ref: float,
                              guess: torch.Tensor | None = None) -> torch.Tensor:
    """Invert h(T) = H (h from :func:`enthalpy`): exact for no latent heat; with latent
    heat, bisection on the bracket the latent part allows (h is strictly increasing, as
    c_eff >= c_p > 0), then two Newton polishes. Vectorised over particles.

    With a ``guess`` (last step's temperatures) three Newton steps are tried first; the
    rows whose residual |h(T) - H| is not below 1e-11 c_p max(T, 1) (e.g. a step across the
    mushy interval) fall back to the bisection."""
    cp = prm.specific_heat
    if prm.latent_heat <= 0.0:
        return T_ref + H / cp
    if guess is not None and H.numel():
        T, bad = newton_temperature(H, prm, T_ref, guess)
        if not bool(bad.any()):
            return T
        return fix_temperature(H, prm, T_ref, T, bad)
    dT = prm.liquidus - prm.solidus
    tsl = 0.5 * (prm.solidus + prm.liquidus)
    l_ref = 0.5 * prm.latent_heat * math.erf((T_ref - tsl) / dT)
    # latent part 0.5 h_f (erf(.) - erf(ref)) lies in [-0.5 h_f - l_ref, 0.5 h_f - l_ref]
    lo = T_ref + (H - (0.5 * prm.latent_heat - l_ref)) / cp
    hi = T_ref + (H + (0.5 * prm.latent_heat + l_ref)) / cp
    for _ in range(48):
        mid = 0.5 * (lo + hi)
        above = enthalpy(mid, prm, T_ref) > H
        hi = torch.where(above, mid, hi)
        lo = torch.where(above, lo, mid)
    T = 0.5 * (lo + hi)
    for _ in range(2):
        T = T - (enthalpy(T, prm, T_ref) - H) / effective_heat_capacity(T, prm)
    return T


def enthalpy_and_capacity(T: torch.Tensor, prm: ThermalParams, T_ref: float, capacity: bool = True):
    """(h(T), c_eff(T)) with latent heat, as a Newton step on h(T) = H takes them: one
    u = (T - T_SL) / (T_L - T_S) for both and the constants folded, h = c_p T + (h_f / 2) erf(u) + C,
    c_eff = c_p + K exp(-u^2): 11 operations where :func:`enthalpy` and
    :func:`effective_heat_capacity` apart take 16 (equal to round-off). ``capacity=False``: h only
    (c_eff None). Without latent heat: :func:`enthalpy` and c_p (T_L - T_S may then be 0)."""
    cp, L = prm.specific_heat, prm.latent_heat
    if L <= 0.0:
        return enthalpy(T, prm, T_ref), (effective_heat_capacity(T, prm) if capacity else None)
    dT = prm.liquidus - prm.solidus
    tsl = 0.5 * (prm.solidus + prm.liquidus)
    u = (T - tsl) / dT
    h = torch.erf(u).mul_(0.5 * L).add_(T, alpha=cp).sub_(cp * T_ref + 0.5 * L * math.erf((T_ref - tsl) / dT))
    if not capacity:
        return h, None
    return h, u.square_().neg_().exp_().mul_(L / (math.sqrt(math.pi) * dT)).add_(cp)


def newton_temperature(H: torch.Tensor, prm: ThermalParams, T_ref: float, guess: torch.Tensor):
    """(T after three Newton steps on h(T) = H from ``guess``, the mask of the rows whose
    residual is not below 1e-11 c_p max(T, 1)): no read of the host."""
    T = guess
    for _ in range(3):
        h, c = enthalpy_and_capacity(T, prm, T_ref)
        T = T - h.sub_(H).div_(c)
    h = enthalpy_and_capacity(T, prm, T_ref, capacity=False)[0]
    bad = ~(h.sub_(H).abs_() <= T.abs().clamp_min(1.0).mul_(1e-11 * prm.specific_heat))
    return T, bad


SATURATED = 6.0  # |T - T_SL| / (T_L - T_S) from which erf is exactly +-1 in float64 (erf(6) = 1 - 2e-17)


def linear_branches(prm: ThermalParams, T_ref: float) -> tuple[float, float, float, float]:
    """(H_lo, H_hi, c_lo, c_hi): below H_lo (above H_hi) the computed h(T) is exactly
    c_p (T - T_ref) + c_lo (+ c_hi), its latent part saturated, so T = T_ref + (H - c) / c_p
    inverts it in closed form."""
    dT = prm.liquidus - prm.solidus
    tsl = 0.5 * (prm.solidus + prm.liquidus)
    e_ref = math.erf((T_ref - tsl) / dT)
    c_lo, c_hi = 0.5 * prm.latent_heat * (-1.0 - e_ref), 0.5 * prm.latent_heat * (1.0 - e_ref)
    H_lo = prm.specific_heat * (tsl - SATURATED * dT - T_ref) + c_lo
    H_hi = prm.specific_heat * (tsl + SATURATED * dT - T_ref) + c_hi
    return H_lo, H_hi, c_lo, c_hi


def mushy_capacity(T: torch.Tensor, prm: ThermalParams) -> int:
    """How many rows :func:`banded_temperature` inverts by Newton: twice the rows now within
    a band 1.5 times as wide as the one where h(T) is not linear, and 64 more (read once,
    at a pair selection)."""
    if prm.latent_heat <= 0.0 or T.numel() == 0:
        return 0
    tsl, dT = 0.5 * (prm.solidus + prm.liquidus), prm.liquidus - prm.solidus
    return 2 * int(((T - tsl).abs() < 1.5 * SATURATED * dT).sum()) + 64


def banded_temperature(H: torch.Tensor, prm: ThermalParams, T_ref: float, guess: torch.Tensor, cap: int):
    """:func:`newton_temperature` with a fixed number of Newton rows: T in closed form where
    h(T) is linear (:func:`linear_branches`: most rows of a large scene, far from the mushy
    interval), Newton from ``guess`` on the ``cap`` rows whose enthalpy lies nearest the
    mushy interval's. ``bad``: Newton's unconverged rows, and any row of the band that was
    not among the ``cap`` (both inverted afresh by :meth:`Inversion.fixed`). Fixed shapes,
    no host read. With ``cap`` >= the rows, plain :func:`newton_temperature`."""
    if cap >= H.numel():
        return newton_temperature(H, prm, T_ref, guess)
    H_lo, H_hi, c_lo, c_hi = linear_branches(prm, T_ref)
    hi = H >= H_hi
    band = (H > H_lo) & ~hi
    T = T_ref + (H - torch.where(hi, c_hi, c_lo)) / prm.specific_heat
    near = torch.topk((H - 0.5 * (H_lo + H_hi)).abs(), cap, largest=False, sorted=False).indices
    Tn, bad_n = newton_temperature(H.index_select(0, near), prm, T_ref, guess.index_select(0, near))
    b_n = band.index_select(0, near)
    T.index_copy_(0, near, torch.where(b_n, Tn, T.index_select(0, near)))
    bad = band.index_copy(0, near, bad_n & b_n)  # (the band rows not among them stay flagged)
    return T, bad


def fix_temperature(H, prm: ThermalParams, T_ref: float, T: torch.Tensor, bad: torch.Tensor) -> torch.Tensor:
    """T with the ``bad`` rows inverted afresh by bisection (:func:`temperature_from_enthalpy`)."""
    idx = torch.nonzero(bad).squeeze(1)
    return T.index_copy(0, idx, temperature_from_enthalpy(H.index_select(0, idx), prm, T_ref))


def liquid_fraction(T: torch.Tensor, prm: ThermalParams) -> torch.Tensor:
    """phi = (T - T_S) / (T_L - T_S) clipped to [0, 1]."""
    if prm.liquidus <= prm.solidus:
        return (T > prm.liquidus).to(T.dtype)
    return ((T - prm.solidus) / (prm.liquidus - prm.solidus)).clamp(0.0, 1.0)


def conduction_pairs(x, T, k, m, rho, zeta, rows, nb, kernel: Kernel, h: float, domain: Domain):
    """(div k grad T)_i = sum_j 4 (m_j / rho_j) k_i k_j / (k_i + k_j) (T_i - T_j) (1/r) dW/dr
    (Cleary & Monaghan 1999), W/m^3, times 2 / (zeta_i + zeta_j) (see :func:`laplacian_norm`).
    dW/dr < 0, so heat flows from hot to cold; the pair exchange V_i q_ij is antisymmetric,
    so the total energy is conserved."""
    dx, r = pair_geometry(x, rows, nb, domain, h)
    dWr = kernel.dwdr(r, h) / r
    k_i = k.index_select(0, rows).unsqueeze(1)
    k_j = gather_nb(k, nb)
    kij = 4.0 * k_i * k_j / (k_i + k_j)
    corr = 2.0 / (zeta.index_select(0, rows).unsqueeze(1) + gather_nb(zeta, nb))
    dT = T.index_select(0, rows).unsqueeze(1) - gather_nb(T, nb)
    return (gather_nb(m, nb) / gather_nb(rho, nb) * kij * corr * dT * dWr).sum(1)


def laplacian_norm(x, m, rho, rows, nb, kernel: Kernel, h: float, domain: Domain):
    """zeta_i = -(1/d) sum_j V_j r_ij dW/dr: the discrete form of the identity
    -(1/d) int r dW/dr dV = 1 on which the SPH Laplacian rests. On a lattice it is off by
    the kernel's lattice error (Wendland C2, h = 1.5 dx: -0.26 % in 2-D), an error that
    does not shrink with dx at fixed h/dx; dividing the pair term by the mean zeta of the
    pair removes it and keeps the exchange antisymmetric."""
    dx, r = pair_geometry(x, rows, nb, domain, h)
    return -(gather_nb(m, nb) / gather_nb(rho, nb) * r * kernel.dwdr(r, h)).sum(1) / x.shape[1]


SIGMA_SB = 5.670374419e-8  # W/(m^2 K^4)
R_GAS = 8.314462618  # J/(mol K)


@dataclass
class SurfaceLosses:
    """Surface heat losses per unit area (W/m^2), each switched off by a zero coefficient:
    radiation sigma_SB eps (T^4 - T0^4) (2.9, fixed), convection q_h (T - T0) (2.8), and
    evaporation m_v [h_v + h(T)] (2.10) with m_v = 0.82 c_s p_v(T) sqrt(M / (2 pi R T)) and
    p_v = 0.54 p_a exp(-h_v M / R (1/T - 1/T_v)) (2.6, fixed: h_v of evaporation, per kg)."""

    ambient: float = 300.0  # T0, K
    emissivity: float = 0.0
    convection: float = 0.0  # q_h, W/(m^2 K)
    evaporation: bool = False
    boiling_point: float = 3090.0  # T_v, K
    evaporation_heat: float = 6.1e6  # h_v, J/kg
    molar_mass: float = 0.0558  # M, kg/mol
    ambient_pressure: float = 101325.0  # p_a, Pa
    sticking: float = 1.0  # c_s

    def vapour_pressure(self, T: torch.Tensor) -> torch.Tensor:
        CT = self.evaporation_heat * self.molar_mass / R_GAS
        return 0.54 * self.ambient_pressure * torch.exp(-CT * (1.0 / T - 1.0 / self.boiling_point))

    def evaporation_flux(self, T: torch.Tensor) -> torch.Tensor:
        """Evaporated mass per unit area and time m_v (kg/(m^2 s))."""
        CM = self.molar_mass / (2.0 * math.pi * R_GAS)
        return 0.82 * self.sticking * self.vapour_pressure(T) * torch.sqrt(CM / T)

    def flux(self, T: torch.Tensor, h_of_T) -> dict[str, torch.Tensor]:
        """Loss fluxes (W/m^2) by kind; ``h_of_T(T)`` gives the specific enthalpy the vapour
        carries away (evaluated only with evaporation on)."""
        out = {}
        if self.emissivity > 0:
            out["radiation"] = SIGMA_SB * self.emissivity * (T**4 - self.ambient**4)
        if self.convection > 0:
            out["convection"] = self.convection * (T - self.ambient)
        if self.evaporation:
            out["evaporation"] = self.evaporation_flux(T) * (self.evaporation_heat + h_of_T(T))
        return out

    @property
    def active(self) -> bool:
        return self.emissivity > 0 or self.convection > 0 or self.evaporation


def flat_surface_layers(kernel: Kernel, h_over_dx: float) -> list[tuple[float, float]]:
    """(depth, V |grad c| per unit area) for each lattice layer below a flat free surface
    (dx = 1; the surface lies dx/2 above the top layer), computed once."""
    import itertools

    dx = 1.0
    h = h_over_dx * dx
    n = int(math.ceil(2 * h_over_dx)) + 2
    d = kernel.dim
    rng = range(-n, n + 1)
    offs = torch.tensor(list(itertools.product(*([rng] * d))), dtype=torch.float64)
    out = []
    for layer in range(n + 1):  # particle at depth (layer + 1/2) dx below the surface
        z_i = -(layer + 0.5)
        pts = offs.clone()
        pts[:, -1] = pts[:, -1] + z_i  # neighbours on the lattice around the particle
        keep = pts[:, -1] < 0
        rel = torch.zeros(d, dtype=torch.float64)
        rel[-1] = z_i
        dxv = rel - pts[keep]
        r = dxv.norm(dim=-1)
        nz = r > 0
        g = (kernel.dwdr(r[nz], h) / r[nz]).unsqueeze(-1) * dxv[nz]
        out.append((-z_i, float(g.sum(0).norm())))  # V = dx^d = 1, per unit area: x dx^d / dx^(d-1)
    return out


def flat_surface_delta(kernel: Kernel, h_over_dx: float) -> float:
    """Sum over the layers of a flat lattice half-space of V |grad c| per unit area: the
    factor by which the discrete surface delta overestimates the area (computed once)."""
    return sum(w for _, w in flat_surface_layers(kernel, h_over_dx))


def wall_temperature_pairs(x, T, rows, nb, mask, kernel: Kernel, h: float, domain: Domain):
    """Shepard averages sum_f T_f W / sum_f W over the conducting neighbours of walls."""
    dx, r = pair_geometry(x, rows, nb, domain, h)
    Wk = kernel.w(r, h) * mask
    return (gather_nb(T, nb) * Wk).sum(1), Wk.sum(1)


def rigid_marks_direct(state: ParticleState, table, work=None) -> torch.Tensor:
    """:func:`rigid_marks` from every working row's own neighbours."""
    fluid = state.phase == Phase.FLUID
    solid = state.phase == Phase.SOLID
    w = None if work is None else torch.nonzero(work & table.has_row()).squeeze(1)  # (decomposed: outer ghosts have no row)
    nbw, mw = table.gather(torch.arange(state.n, device=state.x.device) if w is None else w, within=True)
    # solid next to melt is the melt's wall: its density follows the melt's pressure
    firm_w = (solid if w is None else solid.index_select(0, w)) & ~(gather_nb(fluid, nbw) & mw).any(1)
    firm = firm_w if w is None else solid.index_copy(0, w, firm_w)
    body_w = state.body if w is None else state.body.index_select(0, w)
    same = (gather_nb(firm, nbw) & (gather_nb(state.body, nbw) == body_w.unsqueeze(1))) | ~mw
    rigid_w = firm_w & same.all(1)
    return rigid_w if w is None else firm.index_copy(0, w, rigid_w)


def rigid_marks(state: ParticleState, table, work=None, cross=None) -> torch.Tensor:
    """Per particle: solid, not next to melt (solid next to melt is the melt's wall: its
    density follows the melt's pressure), and so are all its neighbours, of its body. Only
    the rows of the table's ``work`` set (None: all) are read: the others have no neighbours
    (a solid one is rigid).

    Read from the few rows that can make a particle not rigid: the table is symmetric, so
    a particle next to melt is a partner of a melt row, and a particle of the largest body
    is not rigid exactly when a partner is not firm or of another body, i.e. a partner
    whose own row is one of those few (not firm, or not of that body), which marks it. Only
    the rows of the particles outside that body, or not firm, are read, not the body's
    bulk. Where a working particle has no row (a decomposed run's outer ghosts) its
    partners cannot be marked from it: :func:`rigid_marks_direct` reads every row.

    With ``cross`` (the particles whose row may hold a partner of another body:
    :func:`~torchsph.bookkeeping.cross_rows`) only the rows not firm or in ``cross`` are read,
    of any body (a fed wire's rows too, but for its tip): a firm particle outside them is not
    rigid exactly when one of them lists it and is not firm or of another body."""
    n, dev = state.n, state.x.device
    has = table.has_row()
    if work is not None and not bool((work & ~has).any()):
        work = None  # every working particle has a row
    if work is not None or table.rows.numel() == 0:
        return rigid_marks_direct(state, table, work)
    solid = state.phase == Phase.SOLID
    fluid = torch.nonzero((state.phase == Phase.FLUID) & has).squeeze(1)
    fnb, fm = table.gather(fluid, within=True)
    near_melt = torch.zeros(n, dtype=torch.bool, device=dev).index_fill_(0, fnb[fm], True)
    firm = solid & ~near_melt
    if cross is None:
        fr = state.body.index_select(0, table.rows)[firm.index_select(0, table.rows)]
        main = int(torch.bincount(fr).argmax()) if fr.numel() else -1
        # the rows that can unmake a neighbour's rigidity, or whose own rigidity is read directly
        few = torch.nonzero(has & (~firm | (state.body != main))).squeeze(1)
    else:
        few = torch.nonzero(has & (~firm | cross)).squeeze(1)
    nb, m = table.gather(few, within=True)
    body_f = state.body.index_select(0, few)
    same_body = gather_nb(state.body, nb) == body_f.unsqueeze(1)
    if cross is None:
        marked = torch.zeros(n, dtype=torch.bool, device=dev).index_fill_(0, nb[m], True)
        rigid = firm & ~(marked & (state.body == main))  # the body's particles: no such partner
    else:  # marked by a listing row that is not firm or of another body
        bad = m & (~same_body | ~firm.index_select(0, few).unsqueeze(1))
        rigid = firm & ~torch.zeros(n, dtype=torch.bool, device=dev).index_fill_(0, nb[bad], True)
    # the other rows, each from its own neighbours
    same = (gather_nb(firm, nb) & same_body) | ~m
    return rigid.index_copy(0, few, firm.index_select(0, few) & same.all(1))


@dataclass
class Inversion:
    """Temperatures from :meth:`Conduction.to_temperature_unchecked`: ``T``, and ``bad``
    (None: exact) the rows where Newton did not converge, which ``fixed()`` inverts afresh."""
    T: torch.Tensor
    bad: torch.Tensor | None
    H: torch.Tensor
    prm: ThermalParams

    def fixed(self) -> torch.Tensor:
        return self.T if self.bad is None else fix_temperature(self.H, self.prm, 0.0, self.T, self.bad)


class Conduction(Holder):
    """Heat conduction for all non-wall particles. Wall particles are fixed-temperature
    (Dirichlet) boundaries: like the no-slip velocity of Adami et al. (2012), a wall
    particle takes the mirrored value T_w = 2 T_set - <T>_w (Shepard average of its
    conducting neighbours), so that the prescribed temperature holds on the wall surface
    between the last solid and the first wall layer rather than at the wall particles."""
    array_prefix, ARRAYS = "th", CONDUCTION_ARRAYS

    def __init__(self, params: ThermalParams, kernel: Kernel, h: float, domain: Domain,
                 conductivity: torch.Tensor, compile: bool = False, beams=(), dx: float = 0.0,
                 losses: SurfaceLosses | None = None, h_over_dx: float = 1.5, colour: ColourGradient | None = None):
        self.prm = params
        self.kernel = kernel
        self.h = h
        self.domain = domain
        self.k = conductivity  # (N,) W/(m K), per particle
        self.beams = list(beams)  # surface heat sources (2.7)
        self.dx = dx
        self.losses = losses if losses is not None else SurfaceLosses()
        self.delta_norm = flat_surface_delta(kernel, h_over_dx) if self.losses.active else 1.0
        self._zeta_fn = torch.compile(laplacian_norm, dynamic=True) if compile else laplacian_norm
        # the colour gradient, shared with the surface forces when both exist (one per step)
        self.colour = colour if colour is not None else ColourGradient(kernel, h, domain, compile=compile)
        self.area_want = None  # the area rows asked of the colour stage at the last selection
        self.surface_memo = None  # (rows, area, the surface rows: surface_rows)

    def select_pairs(self, state: ParticleState, table,
                     active: torch.Tensor | None = None, work: torch.Tensor | None = None,
                     x_ref: torch.Tensor | None = None, new_table: bool = True, reach: float | None = None, cross=None):
        """Rows: every particle but the walls, or with an active set only its active particles (and the
        walls of its work set). ``x_ref``: the positions at the last neighbour build (default: now);
        ``new_table``: the table was just built (else the phases changed, or the particles were swapped in
        with their arrays); ``reach``: how far a particle may move from ``x_ref`` before the next build
        (None: unknown); ``cross``: the only rigid rows read (:func:`~torchsph.bookkeeping.cross_rows`)."""
        wall = state.phase == Phase.WALL
        self.wall_mask = wall
        # Laplacian normalisation and surface area per particle (and the surface normal):
        # recomputed after each neighbour rebuild, except where they cannot have changed
        self._mark_rigid(state, table, work, cross)
        self.zeta_cache = None
        self.area_cache = None
        self.rows = torch.nonzero(~wall if active is None else ~wall & active).squeeze(1)
        self.table = table  # (its rows are read where computed: rows_and_table)
        x_ref = state.x if x_ref is None else x_ref
        comm = getattr(self, "comm", None)
        op = select_operator(self, table, state, x_ref, new_table)
        op.select(table, self.steady, state.body, work, cross)
        self.rows_w = torch.nonzero(wall if work is None else wall & work).squeeze(1)
        own = getattr(self, "owned", None)  # (ghosts off the rows: their owners count them)
        rest = torch.ones(state.n, dtype=torch.bool, device=state.rho.device) if own is None else own.clone()
        rest.index_fill_(0, self.rows, False).index_fill_(0, self.rows_w, False)
        self._rho_rest = torch.where(rest, state.rho, torch.full_like(state.rho, math.inf)).min()
        if not hasattr(self, "T_set"):
            self.T_set = state.T.clone()  # the walls' prescribed temperatures
        if self.rows_w.numel():
            nbw, mw = table.gather(self.rows_w, within=True)
            self.nb_w = nbw
            self.mask_w = (mw & ~gather_nb(wall, nbw)).to(state.dtype)
        self.beam_rows = self.beam_candidates(x_ref, reach, comm)
        self.mushy_cap = mushy_capacity(state.T.index_select(0, self.rows), self.prm)
        if self.losses.active:  # the rows whose area the next evaluation computes
            sub, _ = self._rows_to_compute("area")
            self.colour.want("area", self.rows if sub is None else self.rows.index_select(0, sub), table)
            self.area_want = (self.area_prev, self.area_ok)
            self.colour.want_norm(zeta_rows(self, table))

    def wall_temperature(self, state: ParticleState, T: torch.Tensor) -> torch.Tensor:
        """T with wall rows replaced by the mirrored Dirichlet value 2 T_set - <T>."""
        if not self.rows_w.numel():
            return T
        sT, sW = wall_temperature_pairs(state.x, T, self.rows_w, self.nb_w, self.mask_w,
                                        self.kernel, self.h, self.domain)
        Tset = self.T_set.index_select(0, self.rows_w)
        Tw = torch.where(sW > 0, 2.0 * Tset - sT / torch.where(sW > 0, sW, torch.ones_like(sW)), Tset)
        return T.index_copy(0, self.rows_w, Tw)

    # Cached geometry: zeta and the surface area (with the normal) of a particle depend only on
    # the positions and volumes of its neighbours. Where a particle and all its neighbours
    # (the Verlet list, a superset of the kernel support until the next rebuild) are solid,
    # of one rigid body and have no melt in their own lists (solid next to melt is the
    # melt's wall, its density set by the melt's pressure), they move together and keep
    # their volumes: the values computed at an earlier rebuild, when this was already so,
    # still hold (to round-off) and are kept. Phase changes re-select, so a neighbour that
    # melts marks the particle; particles added (a fed wire's layer) give old rows new
    # neighbours of their own body, so the next rebuild recomputes every row.
    zeta_ok = area_ok = None  # per particle: the cached value holds and was computed rigid
    steady = x_op = None  # per particle (CONDUCTION_ARRAYS): made with the conduction matrix
    zeta_prev = area_prev = normal_prev = None

    def forget_geometry(self):
        """Neighbours change (particles added or removed): zeta and the area are evaluated
        afresh for every row at the next evaluation; the conduction operator is made anew
        (its entries name particles by row)."""
        self.zeta_ok = self.area_ok = None
        self.op = None

    def _mark_rigid(self, state: ParticleState, table, work=None, cross=None):
        """Per particle: solid, not next to melt, and so are all its neighbours, of its body.
        Only the rows of the table's ``work`` set (None: all) are read: the others have no
        neighbours (a solid one is rigid). ``cross``: :func:`rigid_marks`'s."""
        self.rigid = rigid_marks(state, table, work, cross)
        n = state.n
        for name in ("zeta", "area"):
            ok = getattr(self, f"{name}_ok")
            val = getattr(self, f"{name}_cache", None)
            val = getattr(self, f"{name}_prev", None) if val is None else val  # (2 selections, 0 evaluations: kept)
            keep = ok is not None and val is not None and ok.shape[0] == n
            setattr(self, f"{name}_ok", ok & self.rigid if keep else None)
            setattr(self, f"{name}_prev", val if keep else None)
        self.normal_prev = getattr(self, "normal", None) if self.area_prev is not None else None
        if self.normal_prev is None or self.normal_prev.shape[0] != n:
            self.area_prev = self.area_ok = self.normal_prev = None

    def _rows_to_compute(self, name: str):
        """(positions in rows to compute, previous full-length values or None: compute all)."""
        ok, prev = getattr(self, f"{name}_ok"), getattr(self, f"{name}_prev")
        if prev is None:
            return None, None
        return torch.nonzero(~ok.index_select(0, self.rows)).squeeze(1), prev

    def _computed(self, name: str, n: int):
        """After computing: the values of every row hold; the rigid ones may be kept later."""
        in_rows = torch.zeros(n, dtype=torch.bool, device=self.rows.device).index_fill_(0, self.rows, True)
        setattr(self, f"{name}_ok", in_rows & self.rigid)
        setattr(self, f"{name}_prev", None)
        return in_rows

    def heat_rate(self, state: ParticleState, T: torch.Tensor) -> torch.Tensor:
        """div(k grad T) per unit volume (W/m^3) at temperatures ``T``; 0 on walls."""
        return embed(self.rows, self.heat_rate_rows(state, T), state.n)

    def prepare(self, state: ParticleState):
        """Once per pair selection, at its first evaluation: zeta and the operator's values (the
        step calls it before its second half, which then has no branch on them)."""
        if self.zeta_cache is None:
            self.zeta_cache = self.zeta(state)
        if not self.op.built:  # once per selection, when zeta is known
            self.op.build(self.k, self.zeta_cache, self.k_summary()[1])
            split_operator(self, state)
        if self.losses.active:  # the surface rows, made here outside the traced part of the step
            surface_rows(self, state)
        plan_beams(self, state, self.rows)  # the beams' tracing, outside the traced part of the step
        if self.int_rows_for is not self.rows or (self.op.split is not None and self.int_rows is None):
            integrated_rows(self)

    def heat_rate_rows(self, state: ParticleState, T: torch.Tensor) -> torch.Tensor:
        """div(k grad T) (W/m^3) on ``rows`` only."""
        T = self.wall_temperature(state, T)
        self.prepare(state)
        q = self.op.apply(state.x, T, self.k, state.m, state.rho, self.zeta_cache, self.slow_now)
        return q if self.op.at is None else T.new_zeros(self.rows.shape).index_copy_(0, self.op.at, q)

    def zeta(self, state: ParticleState) -> torch.Tensor:
        """Per-particle Laplacian normalisation, used where it lies in [0.95, 1.05] (else 1): it corrects the
        interior lattice error only; where the kernel is truncated (a free surface,
        zeta ~ 0.5) the plain SPH operator, which acts as an insulated boundary, is kept.
        Walls, and particles outside the rows (an active set's frozen halo), count as 1."""
        sub, prev = self._rows_to_compute("zeta")
        rows = self.rows if sub is None else self.rows.index_select(0, sub)
        z = zeta_of(self, state, rows)
        z = torch.where((z > 0.95) & (z < 1.05), z, torch.ones_like(z))
        in_rows = self._computed("zeta", state.n)
        one = torch.ones(state.n, dtype=z.dtype, device=z.device)  # off the rows (at 0 a halo pair had twice its g)
        return torch.where(in_rows, prev, one).index_copy(0, rows, z) if prev is not None else one.index_copy(0, rows, z)

    def power(self, state: ParticleState, T: torch.Tensor, t: float, per_particle: bool = False, rows_only: bool = False):
        """Heat per particle (W; ``rows_only``: of ``rows`` only): conduction V_i div(k grad T),
        beam power, minus surface losses; and the totals by kind (W) (``per_particle``: the
        per-particle arrays by kind instead, for a diagnosis). The step integrates the
        specific enthalpy, dh/dt = P_i / m_i, and recovers T from h(T) = int c_eff dT (2.11):
        the latent heat is absorbed exactly however narrow the mushy interval is compared
        with one step's temperature change. Conduction: one sparse product and the moving
        pairs on every row at every step (:mod:`torchsph.heat_operator`)."""
        rows, n = self.rows, state.n  # every term on the rows only (the others get none)
        parts = {"conduction": self.heat_rate_rows(state, T) * (state.m.index_select(0, rows) / state.rho.index_select(0, rows))}
        if self.beams:
            parts["beam"] = self.beam_power_rows(state, t, rows)
            lit = parts["beam"] > 0
            self.lit = torch.zeros(n, dtype=torch.bool, device=lit.device).index_copy_(0, rows, lit)
            self.n_lit = lit.sum()  # a tensor: the plan statistics sum it without a sync per step
        if self.losses.active:
            if self.area_cache is not None and self.area_want is not None:  # the area came back with the particles (a restore)
                self.area_want = None
                self.colour.want("area", None)
            at, srows, area = surface_rows(self, state)  # only they lose heat (the area made if due)
            fl = self.losses.flux(T.index_select(0, srows), lambda T_: enthalpy(T_, self.prm, 0.0))
            lost = {name: -f * area for name, f in fl.items()}
        else:
            lost = {}
        P = sum(parts.values())
        if lost:  # summed on the surface rows in the order of the kinds (the values of a sum of every row)
            P = P.index_copy(0, at, sum(lost.values(), P.index_select(0, at)))
            parts.update({k: v.new_zeros(rows.shape).index_copy_(0, at, v) for k, v in lost.items()}
                         if per_particle else {})
        P = P if rows_only else embed(rows, P, n)
        if per_particle:
            return P, {k: embed(rows, v, n) for k, v in parts.items()}
        own = getattr(self, "owned", None)  # a decomposed run books its own particles only
        mine = lambda v, r: v if own is None else torch.where(own.index_select(0, r), v, torch.zeros_like(v))  # noqa: E731
        totals = {k: mine(v, rows).sum() for k, v in parts.items()}
        totals.update({k: mine(v, srows).sum() for k, v in lost.items()})
        totals.setdefault("beam", torch.zeros((), dtype=T.dtype, device=T.device))
        return P, totals

    def beam_power(self, state: ParticleState, t: float, rows: torch.Tensor) -> torch.Tensor:
        """Power (W) each particle absorbs from all beams; only ``rows`` absorb or shadow
        (with an active set, the beams' footprints are in it: lit particles seed it)."""
        return embed(rows, self.beam_power_rows(state, t, rows), state.n)

    beam_rows = None  # per beam: the positions in ``rows`` that it can reach until the next build
    # the conduction window (numerics.conduction_window, 0: none; slow rows colder than slow_below), its start,
    # this step's factor (0-d, None: the slow pairs wait), closed in this step; :func:`integrated_rows`, and
    # its rows; this step's (:func:`start_step`); the next may take int_rows only; a checkpoint's fast rows
    window, slow_below, slow_mark, slow_now, closed = 0.0, math.inf, None, None, False
    int_rows = int_rows_for = step_rows = restored_fast = None
    partial_next = False
    refreeze_limit = 0.02  # share of G's rows re-solidified (not in G) at which G is made anew
    provisional = False  # steady set guessed (arrays not carried): G is made anew at the next build

    def beam_candidates(self, x_ref: torch.Tensor, reach: float | None, comm) -> list | None:
        """Per beam, the positions in ``rows`` it can reach before the next neighbour build
        (:func:`torchsph.beam.reachable`; each process over its own rows)."""
        if not self.beams or reach is None:
            return None
        return reachable(self.beams, x_ref.index_select(0, self.rows), reach)

    def beam_power_rows(self, state: ParticleState, t: float, rows: torch.Tensor) -> torch.Tensor:
        """:meth:`beam_power` on ``rows`` only (each beam traced on the rows it can reach)."""
        comm = getattr(self, "comm", None)
        if comm is not None and comm.size > 1:
            return beam_power_decomposed(self, state, t, rows, comm, self.beam_rows if rows is getattr(self, "rows", None) else None)
        return beams_power(self.beams, state.x, t, self.dx, plan=plan_beams(self, state, rows))

    def lit_mask(self, state: ParticleState, t: float) -> torch.Tensor | None:
        """Particles any beam lights at time t (all non-wall particles considered)."""
        if not self.beams:
            return None
        return self.beam_power(state, t, torch.nonzero(state.phase != Phase.WALL).squeeze(1)) > 0

    def add_particles(self, new: ParticleState):
        """Extend the per-particle arrays for particles appended to the state."""
        self.k = torch.cat([self.k, torch.full((new.n,), self.prm.conductivity, dtype=self.k.dtype,
                                               device=self.k.device)])
        self.T_set = torch.cat([self.T_set, new.T])
        if self.steady is not None:  # not in the conduction matrix: steady from its next making
            self.steady = torch.cat([self.steady, torch.zeros(new.n, dtype=torch.bool, device=self.steady.device)])
            self.x_op = torch.cat([self.x_op, new.x])
        for name in ("zeta_cache", "area_cache", "normal"):  # kept to length until the forced rebuild
            v = getattr(self, name, None)
            if v is not None:
                setattr(self, name, torch.cat([v, torch.zeros((new.n,) + v.shape[1:], dtype=v.dtype, device=v.device)]))
        if getattr(self, "lit", None) is not None:
            self.lit = torch.cat([self.lit, torch.zeros(new.n, dtype=torch.bool, device=self.lit.device)])

    def surface_area(self, state: ParticleState) -> torch.Tensor:
        """:func:`surface_area` of this model's rows (sets ``normal``)."""
        return surface_area(self, state)

    def to_enthalpy(self, T: torch.Tensor) -> torch.Tensor:
        return enthalpy(T, self.prm, 0.0)

    mushy_cap = 1 << 62  # rows :func:`banded_temperature` inverts by Newton (all until a selection sets it)
    def to_temperature_unchecked(self, H: torch.Tensor, guess: torch.Tensor) -> "Inversion":
        """T from the specific enthalpy (:func:`banded_temperature`: closed form off the mushy band, Newton
        from ``guess`` on it), the convergence not read: an :class:`Inversion` whose ``bad`` mask the step
        reads with its other decisions, and whose ``fixed()`` inverts the rows that did not converge."""
        if self.prm.latent_heat <= 0.0:  # exact: nothing to check
            return Inversion(self.to_temperature(H, guess), None, H, self.prm)
        T, bad = banded_temperature(H, self.prm, 0.0, guess, self.mushy_cap)  # (an empty H gets an empty mask: every process reads alike)
        return Inversion(T, bad, H, self.prm)

    def to_temperature(self, H: torch.Tensor, guess: torch.Tensor | None = None) -> torch.Tensor:
        return temperature_from_enthalpy(H, self.prm, 0.0, guess)

    def limit(self, state: ParticleState):
        """Thermal time-step limit 0.125 rho c_p h^2 / k (3.17, fixed), a 0-d float64 tensor
        (inf without conduction)."""
        kmax = self.k_summary()[0]
        lim = 0.125 * self.rho_min(state).double() * self.prm.specific_heat * self.h**2 / kmax
        return torch.where(kmax > 0, lim, torch.full_like(lim, math.inf))

    def k_summary(self) -> tuple[torch.Tensor, torch.Tensor | None]:
        """(the largest conductivity as a 0-d float64 tensor, the one conductivity where all are
        equal or None), made once per conductivity array: passes over every particle (and one
        host read) at the first use after k is set, not at every step."""
        memo = self.__dict__.get("_k_summary")
        if memo is None or memo[0] is not self.k:
            k = self.k
            kmax = k.max()
            memo = self._k_summary = (k, kmax.double(), k[0].clone() if bool(k.min() == kmax) else None)
        return memo[1], memo[2]

    def rho_min(self, state: ParticleState) -> torch.Tensor:
        """The smallest density of all particles, reading only the rows, the walls among them
        and, for the rest (cold solid left out, whose density does not change), the value
        taken at the pair selection."""
        r = self._rho_rest
        if self.rows.numel():
            r = torch.minimum(state.rho.index_select(0, self.rows).min(), r)
        return r if not self.rows_w.numel() else torch.minimum(r, state.rho.index_select(0, self.rows_w).min())


def slow_rows(th, state: ParticleState) -> torch.Tensor:
    """(R,) bool over the operator's rows: the rows whose pairs with each other wait for the
    window (:class:`~torchsph.heat_operator.SlowSplit`). Slow: steady solid of one rigid body
    with its neighbours (not next to melt: rigid), no moving pair, not lit by a beam, colder
    than ``slow_below``, and no row with one of these (one neighbour's width around the fast
    ones: the steep gradients at the hot zone's edge are summed every step)."""
    op = th.op
    n = state.n
    cand = th.rigid & th.steady & (state.T < th.slow_below)
    lit = getattr(th, "lit", None)
    if lit is not None and lit.shape[0] == n:
        cand = cand & ~lit
    slow = cand.index_select(0, op.rows)
    if op.n_dynamic:
        slow = slow.index_fill(0, op.d_row, False)
    fr = torch.nonzero(~slow).squeeze(1)
    e, _, _ = row_entries(op.crow, fr)
    near = op.row_of.index_select(0, op.g_j.index_select(0, e))
    return (~slow).index_fill(0, near[near >= 0], True)


def split_operator(th, state: ParticleState):
    """With a window (``numerics.conduction_window`` > 0, one process): G's fast and slow rows
    (:func:`slow_rows`), made after each build of G. A decomposed run sums every row at every
    step (its ghosts' rows are their owners')."""
    op = th.op
    comm = getattr(th, "comm", None)
    th.int_rows = th.int_rows_for = None  # (made anew after the surface rows: integrated_rows)
    fast, th.restored_fast = th.restored_fast, None
    if th.window <= 0 or op.at is not None or (comm is not None and comm.size > 1) or not op.n_static:
        op.split = None
        return
    prev = op.split  # (a split of this operator's G: its structure is the same, its values of an earlier build)
    if fast is not None and fast.shape[0] == state.n:  # a restart: the rows as the run had them
        fast = fast.index_select(0, op.rows)
    else:
        fast = slow_rows(th, state)
        if prev is not None and not bool((fast & ~prev.fast).any()):  # no row turns fast (a phase change
            # inside the hot zone): the split is kept, with the new values (rows fast before stay so until
            # the next change of the fast rows; a restart takes the split's rows: window_state)
            prev.revalue(op)
            return
    op.split = SlowSplit(op, fast)


def integrated_rows(th):
    """The rows a step between windows integrates (``int_rows``; None: all): every row but the
    *frozen* ones, slow rows whose heat between windows is zero (no pair with a fast row, no
    surface loss, no beam that can reach them): their enthalpy and temperature do not change
    until the window closes, so the step's passes over the rows (the half kicks, h(T) and its
    inversion, the phase test, the heating limit) skip them. Made after the split and the
    surface rows, at each selection's first evaluation."""
    sp = th.op.split if th.op is not None else None
    th.int_rows, th.int_rows_for = None, th.rows
    memo = th.surface_memo
    if (sp is None or (th.beams and (th.beam_rows is None or any(b is None for b in th.beam_rows)))  # (a beam
            # that may reach any row, e.g. a moving one: none frozen)
            or (th.losses.active and (memo is None or memo[0] is not th.rows))):
        return
    keep = sp.fast.index_fill(0, sp.b_row, True)
    if th.losses.active:
        keep = keep.index_fill(0, memo[2], True)
    for b in th.beam_rows or ():
        keep = keep.index_fill(0, b, True)
    th.int_rows = th.rows.index_select(0, torch.nonzero(keep).squeeze(1))


def start_step(th) -> torch.Tensor:
    """At a step's start: the rows its first half integrates (``step_rows``: ``int_rows`` where the
    last step allows, else None: every row). Returns the rows as the step begins."""
    th.step_rows = th.int_rows if th.partial_next and th.int_rows_for is th.rows else None
    return th.rows


def live_rows(th) -> torch.Tensor:
    """The rows whose dh/dt may be non-zero after this step: ``int_rows`` while they hold (no
    window closed in the step, no selection since they were made), else every row."""
    ok = (th.int_rows is not None and th.int_rows_for is th.rows and th.op is not None and th.op.built
          and not th.closed)
    return th.int_rows if ok else th.rows


def end_rows(th, rows0: torch.Tensor, rows_start: torch.Tensor) -> torch.Tensor:
    """The rows whose temperatures a step's end inverts: those its first half integrated
    (``rows0``) where the rest of the step heats no other row, else every row (``rows0`` and
    the rows of now, where a rebuild changed them since the step began: ``rows_start``)."""
    if th.rows is rows0:
        return rows0
    i = th.int_rows
    if (not th.closed and i is not None and th.int_rows_for is th.rows
            and (i is rows0 or (i.shape == rows0.shape and bool(torch.equal(i, rows0))))):
        return rows0  # (the read where a selection made them anew: at a rebuild, not per step)
    if th.rows is rows_start and rows0 is th.step_rows:  # rows0: a subset of the unchanged rows
        return th.rows
    return torch.unique(torch.cat([rows0, th.rows]))


def slow_factor(th, t: float, dt: float, limits: dict) -> float | None:
    """The slow rows' window (host numbers, no read): None while it is open, else its length
    over this step's dt, and the next window begins. A window closes at the step after which
    one more step would take it past ``window`` times the thermal limit (3.17)."""
    if th.window <= 0:
        return None
    if th.slow_mark is None:
        th.slow_mark = t
    elapsed = t + dt - th.slow_mark
    if elapsed + dt <= th.window * limits.get("thermal", math.inf):
        return None
    th.slow_mark = t + dt
    return elapsed / dt


def operator_rows(th) -> torch.Tensor:
    """The conduction operator's rows: those of ``th`` (:class:`Conduction`), or in a
    decomposed run the owned ones among them."""
    own = getattr(th, "owned", None)
    if own is None:
        return th.rows
    return th.rows.index_select(0, torch.nonzero(own.index_select(0, th.rows)).squeeze(1))


def owned_operator(th, table, state: ParticleState) -> ConductionOperator:
    """A new conduction operator on :func:`operator_rows` (``op.at``: their places in the
    rows of ``th``, in a decomposed run). No owned particle's rate in a step reads a ghost's
    conduction: a ghost's temperature and rate are its owner's, refreshed at every step's
    end, and the ghost rows keep only the per-row work (the extrapolated temperatures the
    owned rows' sums read)."""
    rows = operator_rows(th)
    return placed(th, ConductionOperator(rows, *table.gather(rows, within=True), th.x_op, th.steady, state.body,
                                         th.kernel, th.h, th.domain))


def placed(th, op: ConductionOperator) -> ConductionOperator:
    """``op`` with ``op.at``, its rows' places among the conducting rows of ``th`` (a
    decomposed run's: the operator holds the owned ones only)."""
    if getattr(th, "owned", None) is not None:
        op.at = torch.searchsorted(th.rows, op.rows)
    return op


def select_operator(th, table, state: ParticleState, x_ref: torch.Tensor, new_table: bool) -> ConductionOperator:
    """The conduction operator of a pair selection of ``th`` (:class:`Conduction`), and its
    steady set. Kept while the rows and the particle set stay (the particle set changing
    drops it: ``th.op = None``); following a new row set (the active set moved), carrying
    the rows that stay, unless enough of its rows froze again since it was made (solid, not
    steady: their pairs are evaluated every step) that it is worth making anew. A decomposed
    run decides that on the count over every process (the operators of all processes are
    then the single-process one's rows, split), and its ghosts' phases and steady flags are
    their owners' at a selection (refreshed before it)."""
    solid = state.phase == Phase.SOLID
    op = getattr(th, "op", None)
    n = state.n
    reuse = (op is not None and th.steady is not None and th.steady.shape[0] == n and th.x_op is not None
             and th.x_op.shape[0] == n and op.row_of.shape[0] == n and not th.provisional)
    rows = operator_rows(th)
    keep = reuse and op.same_rows(rows, n)
    comm = getattr(th, "comm", None)
    if new_table and comm is not None and comm.size > 1:  # every process decides alike (a collective)
        refrozen = float((solid & ~th.steady).index_select(0, rows).sum()) if reuse and not keep else 0.0
        refrozen, total, unfit = comm.sum([refrozen, float(rows.numel()), float(not reuse)])
        reuse = unfit == 0 and refrozen <= th.refreeze_limit * total
        keep = reuse and keep
    elif reuse and not keep and new_table:
        refrozen = int((solid & ~th.steady).index_select(0, rows).sum())
        reuse = refrozen <= th.refreeze_limit * rows.numel()
    if new_table and not reuse:  # G anew at this neighbour build's positions
        th.steady, th.x_op, th.provisional = solid, x_ref, False
    elif th.steady is None or th.steady.shape[0] != n or th.x_op is None or th.x_op.shape[0] != n:
        # arrays not carried (a checkpoint of an older version): the solid that has not
        # moved since the last build, until G is made anew at the next build
        th.steady, th.x_op = solid & (state.x == x_ref).all(1), x_ref
        th.provisional = True
    else:  # a phase change, or G kept: melt leaves it, what froze joins only when G is made anew
        th.steady = th.steady & solid
    if not reuse:
        th.op = owned_operator(th, table, state)
    elif not keep:
        th.op = op.follow(rows, lambda at: table.gather(rows[at], within=True), th.x_op, th.steady, state.body)
    # (also where it is kept: the operator's rows are the same, but the ghosts among the
    # conducting rows, and so the owned rows' places there, may have changed)
    return placed(th, th.op)


def rows_and_table(th, sub: torch.Tensor | None = None):
    """(rows, nb): the conducting rows of ``th`` (:class:`Conduction`), or their positions
    ``sub``, with their rows of the selection's neighbour table, read for those rows only."""
    rows = th.rows if sub is None else th.rows.index_select(0, sub)
    return rows, th.table.gather(rows, within=True)[0]


def surface_area(th, state: ParticleState) -> torch.Tensor:
    """Area (m^2) of free surface each particle of ``th`` (:class:`Conduction`) stands for: V_i |grad c_i| (the CSF
    surface delta) divided by its flat-lattice sum, so that a flat surface gets
    exactly its area. Particles with |grad c| h < 0.05 (the interior) get none.
    Also sets ``th.normal``, the outward unit normal of surface particles (0 inside)."""
    sub, prev = th._rows_to_compute("area")
    rows, nb = rows_and_table(th, sub)
    want, th.area_want = th.area_want, None
    if want is not None and want[0] is th.area_prev and want[1] is th.area_ok:  # the rows asked for
        g = th.colour.of(state, "area")
    else:
        g = colour_gradient_pairs(state.x, state.m, state.rho, rows, nb, th.kernel, th.h, th.domain)
    th.colour.want("area", None)  # (until the next selection)
    gn = g.norm(dim=-1)
    surface = gn * th.h > th.colour.threshold
    gn = torch.where(surface, gn, torch.zeros_like(gn))
    # outward unit normal n = -grad c / |grad c| on surface particles, 0 inside
    n_out = torch.where(surface.unsqueeze(-1), -g / gn.clamp_min(tiny(gn)).unsqueeze(-1), torch.zeros_like(g))
    a = (state.m / state.rho).index_select(0, rows) * gn / th.delta_norm
    normal_prev = th.normal_prev
    in_rows = th._computed("area", state.n)
    th.normal_prev = None
    if prev is not None and normal_prev is not None:  # as computed whole: 0 off the rows
        th.normal = torch.where(in_rows.unsqueeze(-1), normal_prev, 0.0).index_copy(0, rows, n_out)
        return torch.where(in_rows, prev, 0.0).index_copy(0, rows, a)
    th.normal = embed(rows, n_out, state.n)
    return embed(rows, a, state.n)


def surface_rows(th, state: ParticleState) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """The conducting rows with a surface area, the only ones the surface losses reach: their
    places in ``rows``, their particles and their areas. Made once per row set and area array
    (a selection's; :meth:`Conduction.prepare` makes them before the traced part of the step),
    so the losses' terms and limit cost what the surface has, not every conducting row (in the
    full scene at full activity, ~35 of 320 ms per step went to losses of interior rows, 0 W)."""
    if th.area_cache is None:
        th.area_cache = th.surface_area(state)
    m = th.surface_memo
    if m is None or m[0] is not th.rows or m[1] is not th.area_cache:
        a = th.area_cache.index_select(0, th.rows)
        at = torch.nonzero(a != 0).squeeze(1)
        th.surface_memo = m = (th.rows, th.area_cache, at, th.rows.index_select(0, at), a.index_select(0, at))
    return m[2], m[3], m[4]


def evaporation_limit(th, state: ParticleState):
    """Time-step limit of the evaporation loss, which is stiff near and above T_v:
    0.5 m c_p / (A dq/dT), q = m_v [h_v + h(T)], dm_v/dT = m_v (C_T / T^2 - 1 / (2 T)),
    so that a surface particle's loss changes little over a step (explicit
    integration of dT/dt = -lambda T is stable for lambda dt < 2; 0.5 keeps it accurate).
    A 0-d float64 tensor."""
    L = th.losses
    _, rows, area = surface_rows(th, state)  # the others have no surface area
    if not rows.numel():
        return math.inf
    T = state.T.index_select(0, rows)
    mdot = L.evaporation_flux(T)
    CT = L.evaporation_heat * L.molar_mass / R_GAS
    dq = (mdot * (CT / T**2 - 0.5 / T) * (L.evaporation_heat + enthalpy(T, th.prm, 0.0))
          + mdot * th.prm.specific_heat)
    lam = area * dq / (state.m.index_select(0, rows) * th.prm.specific_heat)
    lmax = lam.max().double()
    return torch.where(lmax > 0, 0.5 / lmax, torch.full_like(lmax, math.inf))


def zeta_rows(th, table, limit: int = 4 * ENTRY_BLOCK):
    """At a selection: the rows whose zeta the next evaluation makes, for the colour stage to
    make from the pairs it reads for the area anyway (kept as ``th.zeta_want``), or None: a
    whole zeta (a restart, new particles: made in blocks) or a compiled zeta is made apart."""
    sub, _ = th._rows_to_compute("zeta")
    th.zeta_want = None
    if sub is not None and th._zeta_fn is laplacian_norm and sub.numel() * table.k <= limit:
        th.zeta_want = th.rows.index_select(0, sub)
    return th.zeta_want


def zeta_of(th, state: ParticleState, rows: torch.Tensor) -> torch.Tensor:
    """zeta (unclipped) of ``rows`` of ``th`` (:class:`Conduction`): the colour stage's where it
    made them at this state (:func:`zeta_rows`), else in blocks of table rows."""
    want = getattr(th, "zeta_want", None)
    z = th.colour.norm(state, want) if want is not None else None
    if z is None or z.shape[0] != rows.numel():
        z = by_rows(lambda r, t: th._zeta_fn(state.x, state.m, state.rho, r, t, th.kernel, th.h, th.domain),
                    rows, th.table.gather(rows, within=True)[0])
    return z


def plan_beams(th, state: ParticleState, rows: torch.Tensor) -> BeamPlan | None:
    """The beams' tracing plan of ``rows`` for ``th`` (:class:`Conduction`), made once per row
    set (a selection's; :meth:`Conduction.prepare` makes it outside the traced part of the step),
    kept as ``th.beam_plan`` = (subsets, rows, plan). None without beams, or decomposed (traced apart)."""
    if not th.beams or getattr(getattr(th, "comm", None), "size", 1) > 1:
        return None
    subs = th.beam_rows if rows is getattr(th, "rows", None) else None
    memo = getattr(th, "beam_plan", None)
    if memo is None or memo[0] is not subs or memo[1] is not rows:
        plan = BeamPlan(th.beams, [None] * len(th.beams) if subs is None else subs, rows.numel(),
                        state.x.dtype, state.x.device, th.dx, rows=rows)
        th.beam_plan = memo = (subs, rows, plan)
    return memo[2]


def beam_power_decomposed(th, state: ParticleState, t: float, rows: torch.Tensor, comm, subs: list | None = None):
    """Shadowing is global: the candidates of all processes (their own particles inside
    a beam's cylinder) are gathered in particle-id order (the order of one process), the
    beams traced over them on every process, and each local row (owned or ghost) takes
    its particle's power by id. ``subs``: per beam, the positions in ``rows`` it can reach
    (:meth:`Conduction.beam_candidates`): only those are looked at (late in the full scene,
    2 ranks spent ~50 ms a step testing every row against the cylinders)."""
    if subs is not None and subs and all(s is not None for s in subs):
        memo = getattr(th, "beam_union", None)  # their union, once per selection
        if memo is None or memo[0] is not subs:
            th.beam_union = memo = (subs, torch.unique(torch.cat(subs)))
        pos = memo[1]
        P = torch.zeros(rows.numel(), dtype=state.x.dtype, device=state.x.device)
        return P.index_copy_(0, pos, beam_power_decomposed(th, state, t, rows.index_select(0, pos), comm))
    own = th.owned.index_select(0, rows)
    x, ids = state.x.index_select(0, rows), state.id.index_select(0, rows)
    cyl = torch.zeros_like(own)
    for b in th.beams:
        cyl = cyl | in_beam(x, b, t)
    sel = own & cyl
    g = comm.gather_rows({"x": x[sel], "id": ids[sel]})
    order = torch.argsort(g["id"])
    gx, gid = g["x"].index_select(0, order), g["id"].index_select(0, order)
    P_g = beams_power(th.beams, gx, t, th.dx)  # (all of them material)
    P = torch.zeros(rows.numel(), dtype=x.dtype, device=x.device)
    if gid.numel():
        pos = torch.searchsorted(gid, ids).clamp_max(gid.numel() - 1)
        hit = cyl & (gid.index_select(0, pos) == ids)
        P = torch.where(hit, P_g.index_select(0, pos), P)
    return P


def stored_energy(state: ParticleState, prm: ThermalParams, T_ref: float, owned=None) -> float:
    """Stored energy sum_i m_i h(T_i) (J) relative to T_ref, walls excluded (and, in a
    decomposed run, particles this process does not own)."""
    inside = state.phase != Phase.WALL
    if owned is not None:
        inside = inside & owned
    return float((state.m * enthalpy(state.T, prm, T_ref) * inside).sum())


__all__ = ["ThermalParams", "Conduction", "SurfaceLosses", "effective_heat_capacity", "enthalpy",
           "temperature_from_enthalpy", "liquid_fraction", "conduction_pairs"]
