"""Time-step control (SPEC §4): the measures of the state the limits read (largest speed
and acceleration, smallest density, compression), every stability limit that applies to a
scene, the choice of dt, the refusal of a fixed dt above a limit, and the settling drag.
Functions of a :class:`~torchsph.step.simulation.Simulation` (its public attributes only)."""
from __future__ import annotations

import math
from dataclasses import dataclass

import torch

from torchsph.physics.conduction_window import live_rows
from torchsph.physics.losses import evaporation_limit


class SimulationError(RuntimeError):
    """A run that cannot go on (blow-up, unstable time step); the message is a diagnosis."""


class UnstableStepError(SimulationError):
    """A fixed time step (``numerics.dt_s``) above a stability limit: bad input, refused
    before the first step."""


LIMIT_FORMULAS = {
    "acoustic": "cfl h / (c0 + |u|max)",
    "viscous": "0.125 h^2 rho_min / eta",
    "force": "0.25 sqrt(h / |a|max)",
    "thermal": "0.125 rho c_p h^2 / k",
    "capillary": "0.25 sqrt(rho_min h^3 / (2 pi alpha_max))",
    "evaporation": "0.5 m c_p / (A d q_evap/dT), the stiffness of the evaporation loss",
    "heating": "0.1 c_p T / |dh/dt| (with evaporation)",
}


@dataclass
class StepInfo:
    dt: float
    limit: str  # binding limit name, or "fixed"
    vmax: float
    amax: float


MEASURES = ("vmax", "amax", "rho_min", "compression")


def measure_tensor(sim) -> torch.Tensor:
    """(4,) float64 device tensor: the largest speed and acceleration, the smallest density
    and the largest compression |rho / rho0 - 1| of the fluid this process owns (not read)."""
    own = sim.comm.owned(sim)
    st = sim.state
    if sim.fluid is None:
        rho = st.rho if own is None else torch.where(own, st.rho, torch.full_like(st.rho, math.inf))
        z = torch.zeros((), dtype=torch.float64, device=rho.device)
        r = rho.min().double() if rho.numel() else torch.full_like(z, math.inf)
        return torch.stack([z, z, r, z])
    rows = sim.fluid.rows_f  # every fluid particle (and, decomposed, ghosts: masked)
    mine = None if own is None else own.index_select(0, rows)
    v, a = st.v.index_select(0, rows), sim.dvdt.index_select(0, rows)
    rho = st.rho.index_select(0, rows)
    comp = (rho / sim.fluid.prm.rho0 - 1.0).abs()
    v2, a2 = (v * v).sum(-1), (a * a).sum(-1)
    if mine is not None:
        v2, a2 = torch.where(mine, v2, torch.zeros_like(v2)), torch.where(mine, a2, torch.zeros_like(a2))
        rho = torch.where(mine, rho, torch.full_like(rho, float("inf")))
        comp = torch.where(mine, comp, torch.zeros_like(comp))
    z = torch.zeros((1,), dtype=rho.dtype, device=rho.device)  # (a process may own no fluid)
    inf = torch.full((1,), float("inf"), dtype=rho.dtype, device=rho.device)
    return torch.stack([torch.cat([v2, z]).max().sqrt(), torch.cat([a2, z]).max().sqrt(),
                        torch.cat([rho, inf]).min(), torch.cat([comp, z]).max()]).double()


def measure(sim) -> dict[str, float]:
    """:func:`measure_tensor`, read and reduced over processes (one read)."""
    return dict(zip(MEASURES, sim.comm.reduce_measure(measure_tensor(sim).tolist())))


def device_limits(sim) -> dict:
    """The limits computed from the particles (0-d device tensors, or numbers): capillary,
    thermal, evaporation, heating, and the composed terms'."""
    lim = {}
    if sim.surface is not None:
        lim["capillary"] = sim.surface.limit(sim.state)
    if sim.thermal is not None:
        lim["thermal"] = sim.thermal.limit(sim.state)
        if sim.thermal.losses.evaporation:
            lim["evaporation"] = evaporation_limit(sim.thermal, sim.state)
            lim["heating"] = heating_limit(sim)
    for term in sim.terms:  # the composable terms' own limits
        lim.update(term.limits(sim))
    return lim


def finish_limits(sim, m: dict[str, float], dev: dict[str, float]) -> dict[str, float]:
    """Every limit, from the measures ``m`` and the read ``dev`` values, over processes."""
    h = sim.h
    lim = {}
    if sim.fluid is not None:
        prm = sim.fluid.prm
        lim["acoustic"] = sim.cfl * h / (prm.c0 + m["vmax"])
        if prm.eta > 0:
            lim["viscous"] = 0.125 * h * h * m["rho_min"] / prm.eta
        if m["amax"] > 0 and math.isfinite(m["amax"]):
            lim["force"] = 0.25 * math.sqrt(h / m["amax"])
    lim.update(dev)
    lim = sim.comm.merge_limits({k: v for k, v in lim.items() if math.isfinite(v)})
    return lim or {"none": math.inf}


def read_all(sim, dev: dict, *extra: torch.Tensor) -> tuple[dict, list[float]]:
    """Read the device ``dev`` limits and the ``extra`` 0-d tensors in one go: (dev with
    numbers, the extras' values)."""
    keys = [k for k, v in dev.items() if isinstance(v, torch.Tensor)]
    ts = [dev[k].reshape(()).double() for k in keys] + [e.reshape(()).double() for e in extra]
    vals = torch.stack(ts).tolist() if ts else []
    return {**dev, **dict(zip(keys, vals))}, vals[len(keys):]


def limits(sim) -> dict[str, float]:
    """Every time-step limit of SPEC §4 that applies to the scene (seconds)."""
    dev, _ = read_all(sim, device_limits(sim))
    return finish_limits(sim, sim.info, dev)


def end_of_step(sim, **flags: torch.Tensor) -> dict[str, float]:
    """The step's one read: the measures, every limit of the next step (kept in
    ``sim.lim_cache``: the state does not change until then) and the ``flags`` (0-d
    tensors: the decisions the host needs) together. Sets ``sim.info``; returns the flags'
    values (process-local: the caller reduces what it must)."""
    dev = device_limits(sim)
    dev, vals = read_all(sim, dev, *measure_tensor(sim).unbind(), *flags.values())
    sim.info = dict(zip(MEASURES, sim.comm.reduce_measure(vals[:4])))
    sim.lim_cache = (sim.step, sim.state.n, finish_limits(sim, sim.info, dev))
    return dict(zip(flags, vals[4:]))


def heating_limit(sim):
    """0.1 c_p T / |dh/dt| over the non-wall particles: at most a 10 % temperature change
    per step. With evaporation on, a step that heats a surface particle far past T_v in
    one go meets a loss that is exponentially stiff there (a 1 200 W beam on the cube
    produced a non-finite temperature on the second step at the thermal limit). A 0-d
    float64 tensor."""
    th = sim.thermal  # dh/dt is 0 off the rows (walls and the cold solid left out; frozen rows between windows)
    rows = live_rows(th)
    if not rows.numel():
        return math.inf
    rate = sim.dTdt.index_select(0, rows).abs()
    r = (rate / (th.prm.specific_heat * sim.state.T.index_select(0, rows).clamp_min(1.0))).max().double()
    return torch.where(r > 0, 0.1 / r, torch.full_like(r, math.inf))


def binding(lim: dict[str, float]) -> tuple[str, float]:
    name = min(lim, key=lim.get)
    return name, lim[name]


def check_fixed_dt(dt_fixed: float, lim: dict[str, float], allow_unstable: bool, formulas: dict | None = None):
    """Refuse a fixed dt above any stability limit unless the case allows it (``formulas``:
    the terms' limits' formulas, beside :data:`LIMIT_FORMULAS`)."""
    formulas = {**LIMIT_FORMULAS, **(formulas or {})}
    for name, val in sorted(lim.items(), key=lambda kv: kv[1]):
        if dt_fixed > val and not allow_unstable:
            raise UnstableStepError(
                f"numerics.dt_s = {dt_fixed:g} s exceeds the {name} limit {val:.4g} s "
                f"({formulas.get(name, name)}); lower dt_s, remove it for the automatic step, "
                "or set numerics.allow_unstable_dt = true")


def damping_rate(damping_time: float, t: float) -> float:
    """Settling drag -zeta(t) u: zeta = (10 / T) (1 + cos(pi t / T)) / 2, ramped to zero
    at t = T (numerics.damping_time_s), so a scene starting from a lattice can relax to
    equilibrium (e.g. a hydrostatic tank) before it is measured."""
    T = damping_time
    return 10.0 / T * 0.5 * (1.0 + math.cos(math.pi * t / T))
