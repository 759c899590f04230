"""Steps in a loop: to an end time (the last step shortened to land on it) or for a number of
steps, with the counts of binding limits; the time step a run can expect."""
from __future__ import annotations

import collections
import math

from torchsph.step.simulation import Simulation


class RunStats:
    """Counts of binding limits, extreme dt and Mach over a run."""

    def __init__(self):
        self.limits = collections.Counter()
        self.dt_min = math.inf
        self.dt_max = 0.0
        self.vmax = 0.0

    def add(self, info):
        self.limits[info.limit] += 1
        self.dt_min = min(self.dt_min, info.dt)
        self.dt_max = max(self.dt_max, info.dt)
        self.vmax = max(self.vmax, info.vmax)


def run_steps(sim: Simulation, t_end: float | None = None, steps: int | None = None,
              callback=None, stats: RunStats | None = None):
    """Advance to ``t_end`` (the last step is shortened to land on it) or by ``steps``."""
    n0 = sim.step
    while True:
        if steps is not None and sim.step - n0 >= steps:
            break
        if t_end is not None and sim.t >= t_end * (1 - 1e-12):
            break
        dt, limit = sim.choose_dt()
        if t_end is not None and sim.t + dt > t_end:
            dt = t_end - sim.t
        info = sim.advance(dt, limit)
        if stats is not None:
            stats.add(info)
        if callback is not None:
            callback(sim, info)


def expected_dt(sim: Simulation) -> tuple[float, str]:
    """The step the run is expected to take once under way: the time-step limits at the
    current state, and where the scene has a fluid model (melt to come) the acoustic,
    viscous and capillary limits of the melt at rest, with 10 % Mach for the flow."""
    now = sim.limits()
    lim = dict(now)
    fm = sim.fluid_model
    if fm is not None and sim.dt_fixed is None:
        prm, h = fm.prm, sim.h
        lim.setdefault("acoustic", sim.cfl * h / (1.1 * prm.c0))
        if prm.eta > 0:
            lim.setdefault("viscous", 0.125 * h * h * prm.rho0 / prm.eta)
        sf = sim.surface_model
        if sf is not None and sf.prm.tension > 0:
            lim.setdefault("capillary", 0.25 * math.sqrt(prm.rho0 * h**3 / (2 * math.pi * sf.prm.tension)))
    if sim.dt_fixed is not None:
        return sim.dt_fixed, "fixed"
    name = min(lim, key=lim.get)
    return lim[name], name + " limit" + ("" if name in now else ", once melt flows")
