"""The parts of a kick-drift-kick step that hold its arithmetic (SPEC §4), with no host read
in any: :func:`first_half` (1a-1e: the half kick, the extrapolations, the density and the
drift), then :func:`close_momentum` and :func:`close_energy` (2 and 3: the rates at the end
of the step and the closing half kicks; apart because the selection's cached conduction
values are made between them, once per selection, eagerly). Between the first half and the
rest the step reads the host once (the feed's contact, whether to rebuild, whether the
extrapolated temperatures converged: :func:`torchsph.step.bookkeeping.mid_step_read`), and after
the rest once more (the measures, the next limits, the phase changes:
:func:`torchsph.step.bookkeeping.finish_step`); particles enter and leave, and the pairs are
rebuilt, only at those reads.

On a step between rebuilds each part has fixed shapes and no data-dependent branch, so
``torch.compile(fullgraph=True)`` traces each whole (tests/test_compile.py): the condition
for capturing them as CUDA graphs."""
from __future__ import annotations

from typing import NamedTuple

import torch

from torchsph.core.state import Phase
from torchsph.physics.enthalpy import Inversion
from torchsph.physics.fluid import embed
from torchsph.step import rates
from torchsph.step.bookkeeping import EndTemperatures


class Half(NamedTuple):
    """What :func:`first_half` hands to the rest of the step."""
    v_half: torch.Tensor | None  # u_{n+1/2} (1a), whole; None: in place (vh_f; see first_half)
    v_tilde: torch.Tensor | None  # u_n + dt du/dt (1b), for the viscous term; None: the state's v now
    rows0: torch.Tensor | None  # the integrated rows of the energy equation
    H_half_r: torch.Tensor | None  # h_{n+1/2} on rows0 (1d)
    inv: Inversion | None  # the extrapolated temperatures on rows0 (unchecked)
    vh_f: torch.Tensor | None = None  # u_{n+1/2} on the fluid rows (the in-place step)
    vt_f: torch.Tensor | None = None  # u_n + dt du/dt on the fluid rows (the in-place step)


def renewed(a: torch.Tensor) -> torch.Tensor:
    """``a`` changed in place, as a new tensor object on the same memory: the caches that know
    a state's arrays by identity (the colour gradient's memo, the wire's contact probe) see new
    positions and densities as new, as they did when each step made new arrays."""
    return a.view_as(a)


def first_half(sim, dt: torch.Tensor) -> Half:
    """1a-1e: half kick, extrapolated velocity and enthalpy (the temperatures of the rate
    evaluation), density, drift (with shifting). Sets the state's T, rho and x. ``dt``: a
    0-d float64 tensor, so a traced part is not specialised to its value."""
    s = sim.state
    # Only the fluid accelerates (dvdt is zero elsewhere: walls and rigid bodies keep their
    # velocity), so the kicks are taken on the fluid's rows and written into copies of v;
    # the drift moves every particle (rigid bodies with their velocity, the fluid with
    # u_{n+1/2}). At full size a pass over every particle costs more than the physics of
    # the few that move: each whole-array update is one fused pass.
    half = 0.5 * dt
    fr = sim.fluid.fluid_rows if sim.fluid is not None else None
    vh_f = vt_f = None
    if fr is None:  # nothing accelerates
        v_half = v_tilde = s.v
    else:  # in place, on the fluid's rows of the state's own v: u_{n+1/2} now, u~ after the
        # density (a whole copy of v per half cost 2-3 ms of a full-scene step)
        v_f, a_f = s.v.index_select(0, fr), sim.dvdt.index_select(0, fr)
        vh_f = torch.addcmul(v_f, a_f, half)  # 1a (v + dt/2 a)
        vt_f = torch.addcmul(v_f, a_f, dt)  # 1b
        s.v.index_copy_(0, fr, vh_f)
        v_half = s.v
    rows0 = H_half_r = inv = None
    if sim.thermal is not None:  # the energy equation in specific enthalpy h(T)
        th = sim.thermal
        rows0 = th.rows if th.step_rows is None else th.step_rows  # integrated particles (not walls; only the
        # active set when skipping; between windows of the conduction window, not its frozen rows)
        T0, a_r = s.T, sim.dTdt.index_select(0, rows0)
        H_r = th.to_enthalpy(T0.index_select(0, rows0))
        H_half_r = H_r + 0.5 * dt * a_r  # 1d on the rows (dh/dt = 0 off them: H_half = h(T) there)
        # extrapolated for the evaluation at the end of the step; walls keep theirs
        inv = th.to_temperature_unchecked(H_r + dt * a_r, T0.index_select(0, rows0))  # checked at the mid read
        s.T = s.T.index_copy(0, rows0, inv.T)
    shift = None
    if sim.fluid is not None:
        sim.drhodt, shift = sim.fluid.continuity(  # at x_n, with u_{n+1/2}
            v_half, s.m, sim.dx if sim.fluid.prm.shifting > 0 else 0.0, rho=s.rho)
        fr_rho = sim.fluid.rows_f  # drho/dt is 0 off the fluid's rows: rho + dt drho/dt on those only
        s.rho = renewed(s.rho.index_add_(0, fr_rho, dt * sim.drhodt.index_select(0, fr_rho)))
    # the drift (continuity above read x_n through its cached pair geometry): every particle
    # with its u_{n+1/2}, in place (a new whole array per step cost ~1 ms of a full-scene step)
    s.x.addcmul_(v_half, dt)
    if shift is not None:
        if sim.surface is not None:
            shift = sim.surface.project_shift(shift, sim.fluid.rows_f)
        s.x.index_add_(0, sim.fluid.rows_f, shift)
    s.x = renewed(sim.domain.wrap(s.x))
    if fr is None:
        return Half(v_half, v_tilde, rows0, H_half_r, inv)
    s.v.index_copy_(0, fr, vt_f)  # the state's v holds u~ until the closing kick
    return Half(None, None, rows0, H_half_r, inv, vh_f, vt_f)


def whole_velocities(s, half: Half, fr, keep: torch.Tensor | None = None) -> tuple[torch.Tensor, torch.Tensor]:
    """(u_{n+1/2}, u~) as whole arrays of their own, where an in-place step (``half.vh_f``) adds
    or removes particles between its halves (the state's v holds u~ on the fluid rows ``fr``; with
    ``keep``, the mask of the rows the state kept of the step's, which it holds already)."""
    vh_f = half.vh_f
    if keep is not None:  # the kept fluid rows, renumbered
        kf = keep.index_select(0, fr)
        fr = (torch.cumsum(keep.long(), 0) - 1).index_select(0, fr)[kf]
        vh_f = vh_f[kf]
    return s.v.index_copy(0, fr, vh_f), s.v.clone()


def close_momentum(sim, dt: torch.Tensor, damping: torch.Tensor | None, v_half, v_tilde,
                   vh_f: torch.Tensor | None = None):
    """2 and 3c at the end of the step: the accelerations with the extrapolated velocity
    (``damping``: the settling drag's rate then, a 0-d tensor, or None) and the closing half
    kick. Either on whole arrays (``v_half``, this step's own, and ``v_tilde``) or in place
    (``vh_f``: u_{n+1/2} on the fluid rows, the state's v holding u~)."""
    s = sim.state
    if sim.fluid is not None:
        in_place = vh_f is not None
        if in_place:
            v_tilde = s.v
        sim.dvdt = sim.accelerations(v_tilde)  # 2
        if damping is not None:
            fm = sim.fluid_mask.unsqueeze(-1)
            sim.dvdt = sim.dvdt - damping * torch.where(fm, v_tilde, torch.zeros_like(v_tilde))
        fr = sim.fluid.fluid_rows
        if in_place:
            s.v.index_copy_(0, fr, torch.addcmul(vh_f, sim.dvdt.index_select(0, fr), 0.5 * dt))  # 3c
        else:  # (v_half: this step's own copy, so written in place)
            s.v = v_half.index_copy_(0, fr, torch.addcmul(v_half.index_select(0, fr), sim.dvdt.index_select(0, fr), 0.5 * dt))  # 3c
    else:
        s.v = v_half  # nothing accelerates
    if sim.new_body_velocity:  # a body's velocity was changed during the step (a feed starts)
        sim.new_body_velocity = False
        solid = (s.phase == Phase.SOLID).unsqueeze(-1)
        s.v = torch.where(solid, sim.body_velocity.index_select(0, s.body), s.v)


def close_energy(sim, dt: torch.Tensor, t_end: torch.Tensor, rows, H_half) -> EndTemperatures:
    """2 and 3b at t_end (a 0-d tensor, as ``dt``): the heat per particle, its energy booked
    (trapezoid), and the end's temperatures on ``rows`` from their half-step enthalpy ``H_half`` (put in unchecked: the
    end's read says whether Newton converged). After :func:`close_momentum` (the melt's
    walls take their densities there) and the selection's cached values
    (:meth:`~torchsph.physics.thermal.Conduction.prepare`)."""
    s, th = sim.state, sim.thermal
    P_r, heat = rates.heat_power(sim, s.T, t_end, rows_only=True)  # 2 (W per particle of the rows; 0 elsewhere)
    sim.dTdt = embed(th.rows, P_r / s.m.index_select(0, th.rows), s.n, sim.outs.get("dTdt"))  # (the rows of now: a rebuild may have changed them)
    for k, v in heat.items():  # accumulated on the device: no sync per step
        sim.energy[k] = sim.energy.get(k, 0.0) + 0.5 * dt * (sim.heat_totals[k] + v)
    sim.heat_totals = heat
    inv = th.to_temperature_unchecked(  # 3b
        H_half + 0.5 * dt * sim.dTdt.index_select(0, rows), s.T.index_select(0, rows))
    return EndTemperatures(s, rows, inv)
