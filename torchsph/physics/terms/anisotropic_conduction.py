"""Extra conduction along the axes, from the temperature gradient field: a material whose
conductivity is k (the [thermal] section's, isotropic) plus K = diag(k_x, k_y[, k_z]), e.g. a
layered or columnar build whose heat runs faster along one direction. Its heat flux is
q = -K grad T, and its power per particle the divergence of that flux in the symmetric form

    P_i = V_i sum_j V_j (K grad T_i + K grad T_j) . grad_i W_ij,

two stages: ``grad_T`` made on every row by [temperature_gradient], then this sum, which reads
it on the neighbours. Each pair's two contributions cancel (grad_j W_ji = -grad_i W_ij), so the
term moves heat without making or losing any, to round-off, where no wall takes part; a wall
neighbour (fixed temperature) exchanges heat as the conduction's walls do, and the energy
balance books it under ``anisotropic_conduction_J``. Time-step limit: the conduction's,
0.125 rho c_p h^2 / (k + max K)."""
from __future__ import annotations

import torch

from torchsph.core.schema import CaseError, Key
from torchsph.physics.fluid import dot, gather_nb, pair_geometry
from torchsph.physics.terms.base import Term, TermContext, register


@register
class AnisotropicConduction(Term):
    section = "anisotropic_conduction"
    doc = "extra conductivity along the axes, q = -diag(k_x, k_y, k_z) grad T (reads grad_T on neighbours)"
    schema = {"extra_conductivity_W_mK": Key("vec", doc="k_x, k_y[, k_z] added to [thermal] conductivity_W_mK "
                                                        "along each axis (>= 0)")}
    needs = ("thermal", "temperature_gradient")
    reads = ("x", "m", "rho", "grad_T")
    writes = ("heat",)
    limit_formulas = {"anisotropic_conduction": "0.125 rho c_p h^2 / (k + max K)"}

    def __init__(self, K, kernel, h: float, k_iso: float, cp: float):
        self.K, self.kernel, self.h = K, kernel, h
        self.k_max, self.cp = k_iso + max(float(k) for k in K), cp  # (host numbers: the limit reads none)

    @classmethod
    def check(cls, cfg: dict) -> None:
        K = cfg["anisotropic_conduction"]["extra_conductivity_W_mK"]
        if any(k < 0 for k in K):
            raise CaseError(f"[anisotropic_conduction] extra_conductivity_W_mK = {list(K)}: each must be >= 0")

    @classmethod
    def from_case(cls, cfg: dict, ctx: TermContext) -> "AnisotropicConduction":
        K = torch.tensor(cfg["anisotropic_conduction"]["extra_conductivity_W_mK"], dtype=ctx.dtype, device=ctx.device)
        th = cfg["thermal"]
        return cls(K, ctx.kernel, ctx.h, th["conductivity_W_mK"], th["specific_heat_J_kgK"])

    def heat(self, sim, t, rows: torch.Tensor) -> torch.Tensor:
        s = sim.state
        g = sim.fields["grad_T"]
        nb, mask = sim.nl.table.gather(rows, within=True)
        dx, r = pair_geometry(s.x, rows, nb, sim.domain, self.h)
        V = s.m / s.rho
        dw = self.kernel.dwdr(r, self.h) / r * mask * gather_nb(V, nb)
        flux = (g.index_select(0, rows).unsqueeze(1) + gather_nb(g, nb)) * self.K  # K grad T_i + K grad T_j
        return V.index_select(0, rows) * (dw * dot(flux, dx)).sum(1)

    def limits(self, sim) -> dict:
        rho = sim.state.rho.min()
        return {"anisotropic_conduction": 0.125 * rho * self.cp * self.h**2 / self.k_max}

    def plan(self) -> str:
        return f"K = {[round(float(k), 6) for k in self.K]} W/(m K)"
