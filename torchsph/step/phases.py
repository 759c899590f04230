"""Melting and freezing (SPEC 2.2, 3.13): solid above T_L joins the melt and leaves its body;
melt below T_S joins the rigid body it rests on and takes its velocity; melt in the mushy
zone is dragged towards the local solid velocity (Carman-Kozeny)."""
from __future__ import annotations

from dataclasses import dataclass

import torch

from torchsph.core.state import Phase
from torchsph.physics.fluid import embed, gather_nb, neighbour_average
from torchsph.step.particles import fluid_set


@dataclass
class PhaseChange:
    """Solid particles above T_L join the fluid (and leave their body); fluid particles
    below T_S join the rigid body they rest on (the one with the largest kernel weight
    among their solid neighbours) and take its velocity; fluid in the mushy zone is
    dragged towards the local solid velocity with the Carman-Kozeny rate
    C (1 - phi)^2 / (phi^3 + 1e-3), integrated exactly (u - u_s decays as exp(-rate dt)),
    so any C is stable. Carman-Kozeny rather than a viscosity ramp: the harmonic mean of
    (3.8) lets the low melt viscosity dominate a pair, so a viscosity ramp barely damps.
    The step calls :meth:`decide`, :meth:`change` (where a phase changed) and :meth:`drag`
    (:func:`torchsph.step.bookkeeping.finish_step`)."""

    T_S: float  # solidus (K): melt below it freezes
    T_L: float  # liquidus (K): solid above it melts
    C: float  # mushy-zone drag (1/s)

    def decide(self, sim, rows=None):
        """(the particles that melt, those that freeze, as masks over the conducting rows,
        their counts as a device tensor). Only the rows' temperatures change in a step, so
        only they are read (``rows``: the rows whose temperatures the step's end set, default
        every conducting row; a decomposition's ghosts take their owners' decisions)."""
        s = sim.state
        rows = sim.thermal.rows if rows is None else rows
        phase, T = s.phase.index_select(0, rows), s.T.index_select(0, rows)
        melt = (phase == Phase.SOLID) & (T > self.T_L)
        freeze = (phase == Phase.FLUID) & (T < self.T_S)
        own = getattr(sim.thermal, "owned", None)
        if own is not None:  # a ghost's temperature is its owner's only after the step's refresh
            own = own.index_select(0, rows)
            melt, freeze = melt & own, freeze & own
        return (rows, melt), (rows, freeze), torch.stack([melt.sum(), freeze.sum()])

    def change(self, sim, melt, freeze, n_melt: int, n_freeze: int, total):
        """Apply :meth:`decide`'s decision (``melt``, ``freeze``: (rows, mask over them);
        ``n_melt``, ``n_freeze``: this process's counts; ``total``: the counts over every
        process, which all re-select together)."""
        s = sim.state
        g_melt, g_freeze = total
        melt, freeze = embed(*melt, s.n), embed(*freeze, s.n)
        if n_freeze:  # join the body it rests on and take that body's velocity
            rows = torch.nonzero(freeze).squeeze(1)
            b = resting_body(sim, rows)
            v_b = sim.body_velocity.index_select(0, b)
            s.v = s.v.index_copy(0, rows, torch.where((b > 0).unsqueeze(-1), v_b, s.v.index_select(0, rows)))
            s.body = s.body.index_copy(0, rows, b)
            s.phase = torch.where(freeze, torch.full_like(s.phase, int(Phase.SOLID)), s.phase)
        if n_melt:  # melt leaves its body
            s.phase = torch.where(melt, torch.full_like(s.phase, int(Phase.FLUID)), s.phase)
            s.body = torch.where(melt, torch.zeros_like(s.body), s.body)
        if g_melt or g_freeze:  # the pair subsets, rates and accelerations of the new fluid set
            # decomposed: a ghost's phase is its owner's decision (its own rows lack neighbours
            # beyond the halo): ghosts take their owners' values before the selection
            sim.comm.end_step(sim)
            s = sim.state
            fluid_set(sim)
            sim.select_pairs()
            sim.dvdt = torch.zeros_like(s.v)
            sim.drhodt = torch.zeros_like(s.rho)
            if sim.fluid is not None:
                sim.dvdt = sim.accelerations(s.v)

    def drag(self, sim, dt: float):
        """The mushy-zone drag of the step (see the class), in place on the fluid rows of the
        state's v; returns what undoes it (:func:`undo_drag`), or None where nothing was done."""
        T_S, T_L, C = self.T_S, self.T_L, self.C
        s = sim.state
        if sim.fluid is None or C <= 0:
            return None
        rows = sim.fluid_model.rows_f
        T = s.T.index_select(0, rows)
        phi = ((T - T_S) / (T_L - T_S)).clamp(0.0, 1.0)
        rate = C * (1.0 - phi) ** 2 / (phi**3 + 1e-3)
        v_s, near = solid_velocity(sim, rows)
        v = s.v.index_select(0, rows)
        decay = torch.where(near, torch.exp(-rate * dt), torch.ones_like(rate)).unsqueeze(-1)
        s.v.index_copy_(0, rows, v_s + (v - v_s) * decay)
        return rows, v


def undo_drag(sim, undo):
    """Put back the velocities a :meth:`PhaseChange.drag` changed (``undo``: its return)."""
    if undo is not None:
        sim.state.v.index_copy_(0, *undo)


def resting_body(sim, rows: torch.Tensor) -> torch.Tensor:
    """For each of ``rows``: the rigid body with the largest kernel weight among its
    solid neighbours (0 where no solid is near)."""
    s = sim.state
    nb = sim.nl.table.gather(rows)[0]
    m = sim.fluid_model
    solid = (s.phase == Phase.SOLID).to(s.dtype)
    best = torch.zeros(rows.numel(), dtype=torch.long, device=s.device)
    best_w = torch.zeros(rows.numel(), dtype=s.dtype, device=s.device)
    for b in range(1, sim.body_velocity.shape[0]):  # a loop over bodies (a handful)
        w = solid * (s.body == b).to(s.dtype)
        _, sW = neighbour_average(s.x, s.v, rows, nb, w, m.kernel, m.h, sim.domain)
        take = sW > best_w
        best = torch.where(take, torch.full_like(best, b), best)
        best_w = torch.where(take, sW, best_w)
    return best


def solid_velocity(sim, rows: torch.Tensor):
    """Shepard average of the rigid-solid neighbours' velocity around ``rows`` (the
    velocity of the body a particle rests on) and whether any solid is near."""
    s = sim.state
    nb = sim.nl.table.gather(rows)[0]
    solid = (gather_nb(s.phase, nb) == Phase.SOLID).to(s.dtype)  # on the rows' neighbours only
    m = sim.fluid_model
    avg, sW = neighbour_average(s.x, s.v, rows, nb, solid, m.kernel, m.h, sim.domain)
    return avg, sW > 0
