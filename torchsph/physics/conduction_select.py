"""Which pairs the conduction operator holds, per pair selection: the rigid pairs (both ends of
one body, steady), the operator kept, followed or made anew, and a decomposed run's owned rows."""
from __future__ import annotations

import torch

from torchsph.core.state import ParticleState, Phase
from torchsph.physics.fluid import gather_nb
from torchsph.physics.heat_operator import ConductionOperator


def rigid_marks_direct(state: ParticleState, table, work=None) -> torch.Tensor:
    """:func:`rigid_marks` from every working row's own neighbours."""
    fluid = state.phase == Phase.FLUID
    solid = state.phase == Phase.SOLID
    w = None if work is None else torch.nonzero(work & table.has_row()).squeeze(1)  # (decomposed: outer ghosts have no row)
    nbw, mw = table.gather(torch.arange(state.n, device=state.x.device) if w is None else w, within=True)
    # solid next to melt is the melt's wall: its density follows the melt's pressure
    firm_w = (solid if w is None else solid.index_select(0, w)) & ~(gather_nb(fluid, nbw) & mw).any(1)
    firm = firm_w if w is None else solid.index_copy(0, w, firm_w)
    body_w = state.body if w is None else state.body.index_select(0, w)
    same = (gather_nb(firm, nbw) & (gather_nb(state.body, nbw) == body_w.unsqueeze(1))) | ~mw
    rigid_w = firm_w & same.all(1)
    return rigid_w if w is None else firm.index_copy(0, w, rigid_w)


def rigid_marks(state: ParticleState, table, work=None, cross=None) -> torch.Tensor:
    """Per particle: solid, not next to melt (solid next to melt is the melt's wall: its
    density follows the melt's pressure), and so are all its neighbours, of its body. Only
    the rows of the table's ``work`` set (None: all) are read: the others have no neighbours
    (a solid one is rigid).

    Read from the few rows that can make a particle not rigid: the table is symmetric, so
    a particle next to melt is a partner of a melt row, and a particle of the largest body
    is not rigid exactly when a partner is not firm or of another body, i.e. a partner
    whose own row is one of those few (not firm, or not of that body), which marks it. Only
    the rows of the particles outside that body, or not firm, are read, not the body's
    bulk. Where a working particle has no row (a decomposed run's outer ghosts) its
    partners cannot be marked from it: :func:`rigid_marks_direct` reads every row.

    With ``cross`` (the particles whose row may hold a partner of another body:
    :func:`~torchsph.step.bookkeeping.cross_rows`) only the rows not firm or in ``cross`` are read,
    of any body (a fed wire's rows too, but for its tip): a firm particle outside them is not
    rigid exactly when one of them lists it and is not firm or of another body."""
    n, dev = state.n, state.x.device
    has = table.has_row()
    if work is not None and not bool((work & ~has).any()):
        work = None  # every working particle has a row
    if work is not None or table.rows.numel() == 0:
        return rigid_marks_direct(state, table, work)
    solid = state.phase == Phase.SOLID
    fluid = torch.nonzero((state.phase == Phase.FLUID) & has).squeeze(1)
    fnb, fm = table.gather(fluid, within=True)
    near_melt = torch.zeros(n, dtype=torch.bool, device=dev).index_fill_(0, fnb[fm], True)
    firm = solid & ~near_melt
    if cross is None:
        fr = state.body.index_select(0, table.rows)[firm.index_select(0, table.rows)]
        main = int(torch.bincount(fr).argmax()) if fr.numel() else -1
        # the rows that can unmake a neighbour's rigidity, or whose own rigidity is read directly
        few = torch.nonzero(has & (~firm | (state.body != main))).squeeze(1)
    else:
        few = torch.nonzero(has & (~firm | cross)).squeeze(1)
    nb, m = table.gather(few, within=True)
    body_f = state.body.index_select(0, few)
    same_body = gather_nb(state.body, nb) == body_f.unsqueeze(1)
    if cross is None:
        marked = torch.zeros(n, dtype=torch.bool, device=dev).index_fill_(0, nb[m], True)
        rigid = firm & ~(marked & (state.body == main))  # the body's particles: no such partner
    else:  # marked by a listing row that is not firm or of another body
        bad = m & (~same_body | ~firm.index_select(0, few).unsqueeze(1))
        rigid = firm & ~torch.zeros(n, dtype=torch.bool, device=dev).index_fill_(0, nb[bad], True)
    # the other rows, each from its own neighbours
    same = (gather_nb(firm, nb) & same_body) | ~m
    return rigid.index_copy(0, few, firm.index_select(0, few) & same.all(1))


def operator_rows(th) -> torch.Tensor:
    """The conduction operator's rows: those of ``th`` (:class:`Conduction`), or in a
    decomposed run the owned ones among them."""
    own = getattr(th, "owned", None)
    if own is None:
        return th.rows
    return th.rows.index_select(0, torch.nonzero(own.index_select(0, th.rows)).squeeze(1))


def owned_operator(th, table, state: ParticleState) -> ConductionOperator:
    """A new conduction operator on :func:`operator_rows` (``op.at``: their places in the
    rows of ``th``, in a decomposed run). No owned particle's rate in a step reads a ghost's
    conduction: a ghost's temperature and rate are its owner's, refreshed at every step's
    end, and the ghost rows keep only the per-row work (the extrapolated temperatures the
    owned rows' sums read)."""
    rows = operator_rows(th)
    return placed(th, ConductionOperator(rows, *table.gather(rows, within=True), th.x_op, th.steady, state.body,
                                         th.kernel, th.h, th.domain))


def placed(th, op: ConductionOperator) -> ConductionOperator:
    """``op`` with ``op.at``, its rows' places among the conducting rows of ``th`` (a
    decomposed run's: the operator holds the owned ones only)."""
    if getattr(th, "owned", None) is not None:
        op.at = torch.searchsorted(th.rows, op.rows)
    return op


def select_operator(th, table, state: ParticleState, x_ref: torch.Tensor, new_table: bool) -> ConductionOperator:
    """The conduction operator of a pair selection of ``th`` (:class:`Conduction`), and its
    steady set. Kept while the rows and the particle set stay (the particle set changing
    drops it: ``th.op = None``); following a new row set (the active set moved), carrying
    the rows that stay, unless enough of its rows froze again since it was made (solid, not
    steady: their pairs are evaluated every step) that it is worth making anew. A decomposed
    run decides that on the count over every process (the operators of all processes are
    then the single-process one's rows, split), and its ghosts' phases and steady flags are
    their owners' at a selection (refreshed before it)."""
    solid = state.phase == Phase.SOLID
    op = getattr(th, "op", None)
    n = state.n
    reuse = (op is not None and th.steady is not None and th.steady.shape[0] == n and th.x_op is not None
             and th.x_op.shape[0] == n and op.row_of.shape[0] == n and not th.provisional)
    rows = operator_rows(th)
    keep = reuse and op.same_rows(rows, n)
    comm = getattr(th, "comm", None)
    if new_table and comm is not None and comm.size > 1:  # every process decides alike (a collective)
        refrozen = float((solid & ~th.steady).index_select(0, rows).sum()) if reuse and not keep else 0.0
        refrozen, total, unfit = comm.sum([refrozen, float(rows.numel()), float(not reuse)])
        reuse = unfit == 0 and refrozen <= th.refreeze_limit * total
        keep = reuse and keep
    elif reuse and not keep and new_table:
        refrozen = int((solid & ~th.steady).index_select(0, rows).sum())
        reuse = refrozen <= th.refreeze_limit * rows.numel()
    if new_table and not reuse:  # G anew at this neighbour build's positions
        th.steady, th.x_op, th.provisional = solid, x_ref, False
    elif th.steady is None or th.steady.shape[0] != n or th.x_op is None or th.x_op.shape[0] != n:
        # arrays not carried (a checkpoint of an older version): the solid that has not
        # moved since the last build, until G is made anew at the next build
        th.steady, th.x_op = solid & (state.x == x_ref).all(1), x_ref
        th.provisional = True
    else:  # a phase change, or G kept: melt leaves it, what froze joins only when G is made anew
        th.steady = th.steady & solid
    if not reuse:
        th.op = owned_operator(th, table, state)
    elif not keep:
        th.op = op.follow(rows, lambda at: table.gather(rows[at], within=True), th.x_op, th.steady, state.body)
    # (also where it is kept: the operator's rows are the same, but the ghosts among the
    # conducting rows, and so the owned rows' places there, may have changed)
    return placed(th, th.op)
