"""Surface losses (SPEC §2.8-2.10): radiation, convection and evaporation through the free
surface's area (the colour gradient's), the flat-surface normalisation, and their time-step limit."""
from __future__ import annotations

import math
from dataclasses import dataclass

import torch

from torchsph.core.kernels import Kernel
from torchsph.core.state import ParticleState
from torchsph.physics.enthalpy import enthalpy
from torchsph.physics.fluid import embed, tiny
from torchsph.physics.free_surface import colour_gradient_pairs

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
    sub, prev = th.rows_to_compute("area")
    rows, nb = rows_and_table(th, sub)
    want, th.area_want = th.area_want, None
    g = None
    if want is not None and want[0] is th.area_prev and want[1] is th.area_ok:  # the rows asked for
        g = th.colour.of(state, "area")
        if g.shape[0] != rows.numel():  # asked for other rows (a decomposed run re-armed since): not these
            g = None
    if g is None:
        g = colour_gradient_pairs(state.x, state.m, state.rho, rows, nb, th.kernel, th.h, th.domain)
    th.colour.want("area", None)  # (until the next selection)
    gn = g.norm(dim=-1)
    surface = gn * th.h > th.colour.threshold
    gn = torch.where(surface, gn, torch.zeros_like(gn))
    # outward unit normal n = -grad c / |grad c| on surface particles, 0 inside
    n_out = torch.where(surface.unsqueeze(-1), -g / gn.clamp_min(tiny(gn)).unsqueeze(-1), torch.zeros_like(g))
    a = (state.m / state.rho).index_select(0, rows) * gn / th.delta_norm
    normal_prev = th.normal_prev
    in_rows = th.computed("area", state.n)
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
