"""The rates of one step, summed over the physics a scene declares: the momentum
equation's accelerations (the fluid, the free-surface forces, the force terms) and the
energy equation's heat per particle (conduction, beams and losses, the heat terms), and
the particles a heat source reaches (which the active set keeps in the work). The step
(:class:`torchsph.step.simulation.Simulation`) calls these at fixed points; a term enters them
by what it ``writes`` (:mod:`torchsph.physics.terms`), without the step naming it."""
from __future__ import annotations

import torch

from torchsph.physics.fluid import GEOMETRY
from torchsph.physics.terms import owned_sum


def accelerations(sim, v_eval, terms: bool = False):
    """Fluid (pressure, viscous, body), free-surface and the force terms' accelerations at
    the state (``terms``: also each one by name, for a diagnosis). The terms that read the
    same pairs share their geometry (:class:`torchsph.physics.fluid.GeometryMemo`)."""
    if torch.compiler.is_compiling():  # (a traced step fuses the geometry into each pair sum)
        return _accelerations(sim, v_eval, terms)
    with GEOMETRY:
        return _accelerations(sim, v_eval, terms)


def _accelerations(sim, v_eval, terms: bool):
    out = sim.fluid.momentum(sim.state, v_eval, terms=terms)
    for term in sim.force_terms:
        rows, a = term.acceleration(sim, v_eval)
        if terms:
            out = (out[0].index_add(0, rows, a),
                   {**out[1], term.section: torch.zeros_like(out[0]).index_add_(0, rows, a)})
        else:
            out = out.index_add_(0, rows, a)
            mark(sim, out, rows)
    if sim.surface is None:
        return out
    if not terms:  # the surface particles' accelerations added into the fluid's array
        rows, a_s = sim.surface.accelerations(sim.state, rows_only=True)
        mark(sim, out, rows)
        return out.index_add_(0, rows, a_s)
    a_s, parts_s = sim.surface.accelerations(sim.state, terms=True)
    return out[0] + a_s, {**out[1], **parts_s}


def mark(sim, out: torch.Tensor, rows: torch.Tensor):
    """``rows`` of the accelerations ``out`` were added into (the reused array zeroes them next time)."""
    e = sim.outs.get("dvdt")
    if e is not None:
        e.mark(out, rows)


def heat_power(sim, T: torch.Tensor, t: float, rows_only: bool = False):
    """Heat per particle (W) and the totals by kind (W, booked over the owned particles):
    conduction, beams and losses (:meth:`torchsph.physics.thermal.Conduction.power`) and every
    heat term, on the conducting rows (``rows_only``: P of those rows only, in their order;
    else of every particle, 0 off them)."""
    P, totals = sim.thermal.power(sim.state, T, t, rows_only=rows_only)
    rows = sim.thermal.rows
    for term in sim.heat_terms:
        p = term.heat(sim, t, rows)
        P = P + p if rows_only else P.index_add(0, rows, p)
        totals[term.section] = owned_sum(sim, rows, p)
    return P, totals


def source_mask(sim) -> torch.Tensor | None:
    """The particles a heat source reaches now: the beams' lit ones and the heat terms' seeds."""
    lit = getattr(sim.thermal, "lit", None)
    for term in sim.heat_terms:
        m = term.seeds(sim, sim.t)
        lit = m if lit is None else (lit if m is None else lit | m)
    return lit
