"""Blow-up diagnosis: after a step whose state is not finite (or whose compression exceeds
the weakly compressible limit), name the particle, the largest term acting on it, the time
step used and the limits it exceeded, and raise :class:`~torchsph.step.limits.SimulationError`."""
from __future__ import annotations

import math

import torch

from torchsph.step.limits import SimulationError, binding


def _over(dt: float, lim: dict[str, float]) -> str:
    over = sorted(((dt / v, n) for n, v in lim.items() if dt > v), reverse=True)
    return "; dt exceeded " + ", ".join(f"{n} x{f:.3g}" for f, n in over) if over else ""


def check_finite(sim, v_eval, dt: float = 0.0, limit: str = "-", T_ok: float | None = None):
    """Raise a diagnosis if the step just taken broke the state; ``v_eval`` the velocity
    the forces were evaluated with, ``dt`` and ``limit`` the step used and why; ``T_ok``:
    whether every temperature is finite, if the step has read it already."""
    if sim.fluid is None:
        if (bool(torch.isfinite(sim.state.T).all()) if T_ok is None else T_ok):
            return
        lim = sim.pre_limits or sim.limits()  # of the last good state
        bname, bval = binding(lim)
        k = int(torch.nonzero(~torch.isfinite(sim.state.T))[0])
        # the heat terms at the particle, from the last good temperatures
        _, parts = sim.thermal.power(sim.state, sim.T_prev, sim.t, per_particle=True)
        mags = {n: abs(float(torch.nan_to_num(v[k], nan=float("inf")))) for n, v in parts.items()}
        term = max(mags, key=mags.get)
        raise SimulationError(
            f"blow-up at step {sim.step}, t = {sim.t:.6g} s: non-finite temperature at "
            f"particle id {int(sim.state.id[k])}; largest term there: {term} "
            f"({mags[term]:.3g} W); dt used {dt:.3g} s ({limit}), binding dt limit before the "
            f"step: {bname} = {bval:.3g} s" + _over(dt, lim))
    m = sim.info
    bad_nan = not (math.isfinite(m["vmax"]) and math.isfinite(m["amax"]))
    if not (bad_nan or m["compression"] > sim.max_compression):
        return
    s = sim.state
    if callable(v_eval):  # made only now (the step keeps u~ on the fluid rows)
        v_eval = v_eval()
    sim.state = s.clone()
    try:
        _, parts = sim.accelerations(v_eval, terms=True)
    finally:
        sim.state = s
    if bad_nan:
        score = ~torch.isfinite(sim.dvdt).all(-1) | ~torch.isfinite(s.v).all(-1)
        k = int(torch.nonzero(score)[0]) if bool(score.any()) else 0
        what = "non-finite velocity or acceleration"
    else:
        comp = (s.rho / sim.fluid.prm.rho0 - 1.0).abs() * sim.fluid_mask
        k = int(comp.argmax())
        what = (f"density {float(s.rho[k]):.4g} is {float(comp[k]) * 100:.0f} % off rho0 "
                f"(limit {sim.max_compression * 100:.0f} %): the weakly compressible model broke")
    mags = {name: float(torch.nan_to_num(t[k], nan=float("inf")).norm()) for name, t in parts.items()}
    term = max(mags, key=mags.get)
    lim = sim.pre_limits or sim.limits()
    bname, bval = binding(lim)
    lim_txt = f"binding dt limit before the step: {bname} = {bval:.3g} s" + (_over(dt, lim) if dt > bval else "")
    pos = ", ".join(f"{c:.4g}" for c in s.x[k].tolist())
    raise SimulationError(
        f"blow-up at step {sim.step}, t = {sim.t:.6g} s: {what} at particle id "
        f"{int(s.id[k])} (x = [{pos}]); largest term there: {term} "
        f"(|a| = {mags[term]:.3g} m/s^2); dt used {dt:.3g} s ({limit}), {lim_txt}")
