"""A uniform volumetric heat source, q''' (W/m^3) in a box for a time window: induction
pre-heating of the substrate, which the thesis's conclusion names as a way to a wider,
shallower bead. In the energy equation (SPEC (2.11)) it is one more source,

    rho dh/dt = div(k grad T) + q'''   (inside the box, t_start <= t < t_end),

so a particle of volume V_i = m_i / rho_i gains P_i = q''' V_i (W). With no conduction
across the box's faces (the whole body heated, or an insulated body) the temperature rises
as dh/dt = q''' / rho: T(t) = T0 + q''' t / (rho c_p) without latent heat.

The source is evaluated at the ends of each step (the step's trapezoid), so a switch time
that falls inside a step is resolved to that step: the energy booked (``heating_J``) is
what was integrated, to round-off, and differs from q V (t_end - t_start) by up to half a
step's heating at each switch."""
from __future__ import annotations

import math

import torch

from torchsph.core.schema import CaseError, Key
from torchsph.core.state import Phase
from torchsph.physics.terms.base import Term, TermContext, register


@register
class VolumetricHeating(Term):
    section = "heating"
    doc = "uniform volumetric heat source q''' (W/m^3) in a box, e.g. induction pre-heating"
    schema = {
        "power_density_W_m3": Key("float", gt=0, doc="q''', heat per unit volume and time"),
        "box_min_m": Key("vec", default=(), doc="lower corner of the heated box (omit: no bound)"),
        "box_max_m": Key("vec", default=(), doc="upper corner of the heated box (omit: no bound)"),
        "t_start_s": Key("float", default=0.0, ge=0, doc="the source is on from this time"),
        "t_end_s": Key("float", default=None, gt=0, doc="the source is off from this time (omit: never)"),
    }
    needs = ("thermal",)
    reads = ("x", "m", "rho", "T", "phase")
    writes = ("heat",)
    limit_formulas = {"volumetric_heating": "0.1 c_p T_min rho_min / q''': at most 10 % temperature rise per step"}

    def __init__(self, q: float, lo, hi, t_start: float = 0.0, t_end: float = math.inf):
        self.q = q
        self.lo, self.hi = lo, hi  # (dim,) tensors, +-inf where unbounded
        self.t_start, self.t_end = t_start, t_end
        self.cp = None  # the material's c_p (from the thermal model, at the first selection)

    @classmethod
    def check(cls, cfg: dict) -> None:
        hs = cfg["heating"]
        lo, hi = hs["box_min_m"], hs["box_max_m"]
        if lo and hi and not all(a < b for a, b in zip(lo, hi)):
            raise CaseError(f"[heating] box_max_m = {list(hi)}: must exceed box_min_m = {list(lo)} in every component")
        if hs["t_end_s"] is not None and not hs["t_end_s"] > hs["t_start_s"]:
            raise CaseError(f"[heating] t_end_s = {hs['t_end_s']}: must be > t_start_s = {hs['t_start_s']}")

    @classmethod
    def from_case(cls, cfg: dict, ctx: TermContext) -> "VolumetricHeating":
        hs = cfg["heating"]

        def corner(v, fill):
            return torch.tensor(list(v) if v else [fill] * ctx.dim, dtype=ctx.dtype, device=ctx.device)
        return cls(hs["power_density_W_m3"], corner(hs["box_min_m"], -math.inf), corner(hs["box_max_m"], math.inf),
                   hs["t_start_s"], math.inf if hs["t_end_s"] is None else hs["t_end_s"])

    def on(self, t: float) -> bool:
        return self.t_start <= t < self.t_end

    def inside(self, x: torch.Tensor) -> torch.Tensor:
        return ((x >= self.lo) & (x <= self.hi)).all(-1)

    def select(self, sim) -> None:
        self.cp = sim.thermal.prm.specific_heat

    def heat(self, sim, t: float | torch.Tensor, rows: torch.Tensor) -> torch.Tensor:
        s = sim.state
        V = s.m.index_select(0, rows) / s.rho.index_select(0, rows)
        on = (t >= self.t_start) & (t < self.t_end)  # (t a 0-d tensor in the step: no branch on it)
        return torch.where(self.inside(s.x.index_select(0, rows)) & on, self.q * V, torch.zeros_like(V))

    def seeds(self, sim, t: float) -> torch.Tensor | None:
        s = sim.state
        if not self.on(t):
            return None
        return self.inside(s.x) & (s.phase != Phase.WALL)

    def limits(self, sim) -> dict:
        rows = sim.thermal.rows
        if not rows.numel() or self.cp is None or not self.on(sim.t):
            return {}
        s = sim.state
        T, rho = s.T.index_select(0, rows), s.rho.index_select(0, rows)
        return {"volumetric_heating": 0.1 * self.cp * T.min().clamp_min(1.0) * rho.min() / self.q}

    def plan(self) -> str:
        return f"{self.q:g} W/m^3"
