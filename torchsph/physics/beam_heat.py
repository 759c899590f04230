"""The beams' heat on the conducting rows: the shadowing plan for the rows, and a decomposed
run's beam power (the beams are traced over every process's particles)."""
from __future__ import annotations

import torch

from torchsph.core.state import ParticleState
from torchsph.physics.beam import BeamPlan, beams_power, in_beam


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
