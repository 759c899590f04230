"""The conduction's multi-rate window: the operator's slow rows (steady cold solid of one body,
far from the melt and the beams) summed once per window, the fast rows at every step."""
from __future__ import annotations

import math

import torch

from torchsph.core.state import ParticleState
from torchsph.physics.heat_operator import SlowSplit, row_entries


def slow_rows(th, state: ParticleState) -> torch.Tensor:
    """(R,) bool over the operator's rows: the rows whose pairs with each other wait for the
    window (:class:`~torchsph.physics.heat_operator.SlowSplit`). Slow: steady solid of one rigid body
    with its neighbours (not next to melt: rigid), no moving pair, not lit by a beam, colder
    than ``slow_below``, and no row with one of these (one neighbour's width around the fast
    ones: the steep gradients at the hot zone's edge are summed every step)."""
    op = th.op
    n = state.n
    cand = th.rigid & th.steady & (state.T < th.slow_below)
    lit = getattr(th, "lit", None)
    if lit is not None and lit.shape[0] == n:
        cand = cand & ~lit
    slow = cand.index_select(0, op.rows)
    if op.n_dynamic:
        slow = slow.index_fill(0, op.d_row, False)
    fr = torch.nonzero(~slow).squeeze(1)
    e, _, _ = row_entries(op.crow, fr)
    near = op.row_of.index_select(0, op.g_j.index_select(0, e))
    return (~slow).index_fill(0, near[near >= 0], True)


def split_operator(th, state: ParticleState):
    """With a window (``numerics.conduction_window`` > 0, one process): G's fast and slow rows
    (:func:`slow_rows`), made after each build of G. A decomposed run sums every row at every
    step (its ghosts' rows are their owners')."""
    op = th.op
    comm = getattr(th, "comm", None)
    th.int_rows = th.int_rows_for = None  # (made anew after the surface rows: integrated_rows)
    fast, th.restored_fast = th.restored_fast, None
    if th.window <= 0 or op.at is not None or (comm is not None and comm.size > 1) or not op.n_static:
        op.split = None
        return
    prev = op.split  # (a split of this operator's G: its structure is the same, its values of an earlier build)
    if fast is not None and fast.shape[0] == state.n:  # a restart: the rows as the run had them
        fast = fast.index_select(0, op.rows)
    else:
        fast = slow_rows(th, state)
        if prev is not None and not bool((fast & ~prev.fast).any()):  # no row turns fast (a phase change
            # inside the hot zone): the split is kept, with the new values (rows fast before stay so until
            # the next change of the fast rows; a restart takes the split's rows: window_state)
            prev.revalue(op)
            return
    op.split = SlowSplit(op, fast)


def integrated_rows(th):
    """The rows a step between windows integrates (``int_rows``; None: all): every row but the
    *frozen* ones, slow rows whose heat between windows is zero (no pair with a fast row, no
    surface loss, no beam that can reach them): their enthalpy and temperature do not change
    until the window closes, so the step's passes over the rows (the half kicks, h(T) and its
    inversion, the phase test, the heating limit) skip them. Made after the split and the
    surface rows, at each selection's first evaluation."""
    sp = th.op.split if th.op is not None else None
    th.int_rows, th.int_rows_for = None, th.rows
    memo = th.surface_memo
    if (sp is None or (th.beams and (th.beam_rows is None or any(b is None for b in th.beam_rows)))  # (a beam
            # that may reach any row, e.g. a moving one: none frozen)
            or (th.losses.active and (memo is None or memo[0] is not th.rows))):
        return
    keep = sp.fast.index_fill(0, sp.b_row, True)
    if th.losses.active:
        keep = keep.index_fill(0, memo[2], True)
    for b in th.beam_rows or ():
        keep = keep.index_fill(0, b, True)
    th.int_rows = th.rows.index_select(0, torch.nonzero(keep).squeeze(1))


def start_step(th) -> torch.Tensor:
    """At a step's start: the rows its first half integrates (``step_rows``: ``int_rows`` where the
    last step allows, else None: every row). Returns the rows as the step begins."""
    th.step_rows = th.int_rows if th.partial_next and th.int_rows_for is th.rows else None
    return th.rows


def live_rows(th) -> torch.Tensor:
    """The rows whose dh/dt may be non-zero after this step: ``int_rows`` while they hold (no
    window closed in the step, no selection since they were made), else every row."""
    ok = (th.int_rows is not None and th.int_rows_for is th.rows and th.op is not None and th.op.built
          and not th.closed)
    return th.int_rows if ok else th.rows


def end_rows(th, rows0: torch.Tensor, rows_start: torch.Tensor) -> torch.Tensor:
    """The rows whose temperatures a step's end inverts: those its first half integrated
    (``rows0``) where the rest of the step heats no other row, else every row (``rows0`` and
    the rows of now, where a rebuild changed them since the step began: ``rows_start``)."""
    if th.rows is rows0:
        return rows0
    i = th.int_rows
    if (not th.closed and i is not None and th.int_rows_for is th.rows
            and (i is rows0 or (i.shape == rows0.shape and bool(torch.equal(i, rows0))))):
        return rows0  # (the read where a selection made them anew: at a rebuild, not per step)
    if th.rows is rows_start and rows0 is th.step_rows:  # rows0: a subset of the unchanged rows
        return th.rows
    return torch.unique(torch.cat([rows0, th.rows]))


def slow_factor(th, t: float, dt: float, limits: dict) -> float | None:
    """The slow rows' window (host numbers, no read): None while it is open, else its length
    over this step's dt, and the next window begins. A window closes at the step after which
    one more step would take it past ``window`` times the thermal limit (3.17)."""
    if th.window <= 0:
        return None
    if th.slow_mark is None:
        th.slow_mark = t
    elapsed = t + dt - th.slow_mark
    if elapsed + dt <= th.window * limits.get("thermal", math.inf):
        return None
    th.slow_mark = t + dt
    return elapsed / dt
