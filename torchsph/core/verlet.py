"""The Verlet list: the neighbour table within the search radius plus a skin, rebuilt only when
some particle may have moved half the skin, partially for rigid bodies (their mutual pairs
kept); the work set's table (:func:`subset_table`)."""
from __future__ import annotations

import math

import torch

from torchsph.core.neighbors import Domain, NeighbourTable, build_table, row_counts
from torchsph.core.state import Array, Holder


class VerletList(Holder):
    """Neighbour table of pairs within ``radius + skin``, rebuilt only when the separation of
    some pair may have changed by more than ``skin`` since the last build (:meth:`due`). Pairs between ``radius`` and
    ``radius + skin`` are kept: compact kernels are exactly zero there.

    Partial rebuilds (``update(..., rigid=...)``): particles of one rigid body keep their mutual
    distances, so their mutual pairs are the ones the current table holds; a rebuild searches
    afresh only the rows of the other particles (melt, particles that joined the work since)
    and hands each body particle the new partners it gained among them. With several rigid
    groups (a substrate and a fed wire) each keeps its own mutual pairs; the pairs across two
    groups are found by searching each smaller group's rows among the other groups' particles
    only (the wire's 33 600 rows find candidates only at its tip). The
    result holds exactly the pairs a full build would (tests/test_neighbors.py), in another
    order within rows. The body set (``static``): a particle
    leaves it when it leaves the body (melts) or has moved otherwise than the body since the
    last full build (beyond rounding: 1e-8 skin in float64, 1e-3 skin in float32, far inside the
    skin's margin); a body particle searched afresh (one that joined the work set) joins it,
    its row now holding all its pairs; a full build starts it afresh. The table holds rows
    for the working particles only (:class:`NeighbourTable`), and a partial rebuild reads
    and writes only those. A full build is made when the searched rows exceed ``partial_limit`` of
    the working particles, or when particles were added or removed."""

    partial_limit = 0.5

    array_prefix = "nl"
    put_back_after_selection = False
    ARRAYS = {
        "x_ref": Array("positions at the last build (the rebuild test's reference)", "m", vector=True),
        "x_mig": Array("a decomposed run's positions at the last migration", "m", vector=True),
        "body_ref": Array("each particle's rigid body at the last build (-1: none)"),
        "static": Array("rows whose mutual pairs with their rigid group the table holds", travels=False),
        "x_full": Array("positions at the last full build", "m", travels=False, vector=True),
        "cross": Array("rows that may hold a partner of another body", travels=False),
    }

    def __init__(self, radius: float, skin: float, domain: Domain):
        self.radius = radius
        self.skin = skin
        self.domain = domain
        self.x_ref: torch.Tensor | None = None
        self.table: NeighbourTable | None = None
        self.n_builds = 0
        self.n_partial = 0  # of the builds, partial ones
        self.static: torch.Tensor | None = None  # rows whose mutual pairs with their rigid group the table holds
        self.x_full: torch.Tensor | None = None  # positions at the last full build
        self.x_mig: torch.Tensor | None = None  # a decomposed run's positions at the last migration
        self.body_ref: torch.Tensor | None = None  # each particle's rigid body at the last build (-1: none; set by the step)
        # after a partial rebuild, the particles whose row may hold a partner of another rigid group (the
        # rows searched afresh and both ends of the pairs found across groups); None: not known (a full build)
        self.cross: torch.Tensor | None = None

    @property
    def nb(self) -> torch.Tensor | None:
        """The (N, k) table of every particle, materialised (tests and tools; the solver reads
        :attr:`table`'s rows)."""
        return None if self.table is None else self.table.to_dense()[0]

    @property
    def mask(self) -> torch.Tensor | None:
        return None if self.table is None else self.table.to_dense()[1]

    def build(self, x: torch.Tensor, work: torch.Tensor | None = None):
        """A full build: the table of every particle, or of the ``work`` particles only."""
        r = self.radius + self.skin
        self.table = NeighbourTable.dense(*build_table(x, r, self.domain)) if work is None else \
            subset_table(x, work, r, self.domain)

    known = None  # (positions, their motion() read), read by the step with its other decisions

    def motion(self, x: torch.Tensor, rows: torch.Tensor | None = None) -> torch.Tensor | None:
        """What the rebuild test reads of the displacements d since the last build (of
        ``rows``; None: all), as a (7,) device tensor whose maximum over processes is theirs
        together: [2 max |d|, the largest d_k (>= 0), minus the smallest d_k (>= 0)], k = 1..3
        (fewer in 2-D). None when the particle set changed since the build (a rebuild is due)."""
        if self.x_ref is None or self.x_ref.shape != x.shape:
            return None
        if rows is None:
            d = self.domain.minimum_image(x - self.x_ref)
        else:
            d = self.domain.minimum_image(x.index_select(0, rows) - self.x_ref.index_select(0, rows))
        if d.shape[0] == 0:
            return torch.zeros(1 + 2 * x.shape[1], dtype=x.dtype, device=x.device)
        top = 2.0 * (d * d).sum(-1).amax().sqrt()
        return torch.cat([top.view(1), d.amax(0).clamp_min(0), -d.amin(0).clamp_max(0)])

    def due(self, m: list[float]) -> bool:
        """The rebuild test on the floats read of a :meth:`motion`.
        The table stays right while no pair's separation has changed by more than the skin:
        |d_i - d_j| is at most 2 max |d|, and at most the diagonal of the box that holds
        every displacement and 0 (the particles not checked are at rest or move as one of
        the checked). So one fast particle, or a blob of melt that moves as one past solid
        at rest, is rebuilt for once it has moved a skin, not half a skin; any one particle
        moves at most a skin between builds (:attr:`travel`)."""
        d = (len(m) - 1) // 2
        if self.skin <= 0:  # no skin: rebuild whenever anything moved
            return m[0] > 0
        return min(m[0], math.sqrt(sum((m[1 + k] + m[1 + d + k]) ** 2 for k in range(d)))) > self.skin

    @property
    def travel(self) -> float:
        """How far one particle can move between builds (:meth:`due`)."""
        return self.skin

    def needs_rebuild(self, x: torch.Tensor, rows: torch.Tensor | None = None, comm=None) -> bool:
        """Whether some pair's separation may have changed by more than the skin since the
        last build (:meth:`due`); ``comm``: over every process (the same answer on each);
        with ``rows``, only those are checked (the caller knows the others move with one of
        them). From the motion the step has read already for these very positions (``known``)."""
        if self.known is not None and self.known[0] is x:
            m = self.known[1]
        else:
            m = self.motion(x, rows)
            m = None if m is None else m.tolist()
        if comm is not None and comm.size > 1:  # (every process takes part, even one with a rebuild due)
            m = comm.reduce_max([math.inf] * (1 + 2 * x.shape[1]) if m is None else m)
        return True if m is None else self.due(m)

    def update(self, x: torch.Tensor, force: bool = False, subset=None, rigid=None, rows=None) -> bool:
        """Rebuild if needed; returns True when the pairs changed. ``subset`` (a callable
        returning a mask, evaluated only when rebuilding) restricts the search to those
        particles: the others get empty rows and appear in no row. ``rigid`` (a callable
        returning each particle's rigid group, -1 where it has none, or the mask of one rigid
        body; evaluated only when rebuilding) allows a partial rebuild (see the class). ``rows``: the particles
        whose displacement decides (:meth:`needs_rebuild`; None: all)."""
        if force or self.needs_rebuild(x, rows):
            work = subset() if subset is not None else None
            if work is not None and bool(work.all()):
                work = None
            group = rigid() if rigid is not None else None
            if group is not None and group.dtype == torch.bool:  # one rigid group, as a mask
                group = torch.where(group, 0, -1)
            if group is None or not self._partial(x, work, group):
                self.build(x, work)
                self.static = self.x_full = self.cross = None
                if group is not None:
                    self.static = group >= 0 if work is None else (group >= 0) & work
                    self.x_full = x.clone()
            self.x_ref = x.clone()
            self.n_builds += 1
            return True
        return False

    def _partial(self, x: torch.Tensor, work: torch.Tensor | None, group: torch.Tensor) -> bool:
        """Rebuild from the current table keeping each rigid group's mutual pairs; False
        (nothing done) where a full build is due. Only the working particles' rows are read
        and written (the table holds no others)."""
        N = x.shape[0]
        T = self.table
        if self.static is None or self.static.shape[0] != N or T is None or T.n != N:
            return False
        rigid = group >= 0
        st = self.static & rigid
        if work is not None:
            st &= work
        srows = torch.nonzero(st).squeeze(1)
        minor, main = [], None  # the static rows of each group but the largest (main)
        if srows.numel():  # moved with their group since the last full build (rounding aside)
            d = self.domain.minimum_image(x.index_select(0, srows) - self.x_full.index_select(0, srows))
            g = group.index_select(0, srows)
            ids = torch.unique(g).tolist()  # (the rigid groups: a few; one read at a rebuild)
            if len(ids) == 1:
                ref = d.median(dim=0).values
            else:
                ref = torch.empty_like(d)
                for gid in ids:
                    sel = torch.nonzero(g == gid).squeeze(1)
                    ref.index_copy_(0, sel, d.index_select(0, sel).median(dim=0).values.expand(sel.numel(), -1))
            keep_s = torch.nonzero((d - ref).abs().amax(1) <= self.skin * (1e-3 if x.dtype == torch.float32 else 1e-8)).squeeze(1)
            srows, g = srows.index_select(0, keep_s), g.index_select(0, keep_s)
            st = torch.zeros_like(st).index_fill_(0, srows, True)
            if len(ids) > 1:
                per = torch.bincount(g, minlength=max(ids) + 1).tolist()
                main = max(range(len(per)), key=lambda k: per[k])
                minor = [(gid, srows.index_select(0, torch.nonzero(g == gid).squeeze(1))) for gid in ids
                         if gid != main and per[gid]]
        alive = work if work is not None else torch.ones(N, dtype=torch.bool, device=x.device)
        q = torch.nonzero(alive & ~st).squeeze(1)  # rows searched afresh
        n_work = int(alive.sum())
        if q.numel() > self.partial_limit * n_work:
            return False
        dev = x.device
        rows = torch.nonzero(alive).squeeze(1)  # the new table's rows: body rows kept and rows searched
        # rows searched afresh, among the working particles
        if work is None:
            qnb, qmask = build_table(x, self.radius + self.skin, self.domain, rows=q)
        else:
            qnb, qmask = subset_table(x, work, self.radius + self.skin, self.domain, rows=q)
        # the body rows' new partners: the searched rows' pairs seen from the body side
        # (one pass over the searched rows' entries: their body partners, in row-major order)
        back = torch.nonzero(st.index_select(0, qnb.view(-1)).logical_and_(qmask.view(-1))).squeeze(1)
        gain_i = [qnb.view(-1).index_select(0, back)]  # row i gains j
        gain_j = [q.index_select(0, torch.div(back, max(qnb.shape[1], 1), rounding_mode="floor"))]
        # the pairs between static rows of two groups (which move apart): each smaller group's
        # rows searched among the other groups' static particles only; the largest group's rows
        # gain their partners found so (a smaller group's rows find their pairs with each other)
        for gid, mrows in minor:
            src = st & (group != gid)
            cnb, cmask = (build_table(x, self.radius + self.skin, self.domain, rows=mrows, sources=src) if work is None
                          else subset_table(x, work, self.radius + self.skin, self.domain, rows=mrows, sources=src))
            ci, cj = mrows.unsqueeze(1).expand_as(cnb)[cmask], cnb[cmask]
            big = torch.nonzero(group.index_select(0, cj) == main).squeeze(1)
            gain_i += [ci, cj.index_select(0, big)]
            gain_j += [cj, ci.index_select(0, big)]
        ti, tj = (torch.cat(t) for t in (gain_i, gain_j)) if minor else (gain_i[0], gain_j[0])
        cross = torch.zeros(N, dtype=torch.bool, device=dev).index_fill_(0, q, True)
        for t in gain_i[1:]:  # (the pairs found across groups: both ends)
            cross.index_fill_(0, t, True)
        perm = torch.sort(ti, stable=True).indices
        ti, tj = ti.index_select(0, perm), tj.index_select(0, perm)
        # the body rows that change: those with a partner that is not of the body (freed), that
        # left the work set, or that gain one. Every old partner was working (the table holds
        # the working particles' pairs only) and the table is symmetric, so a freed partner is a
        # searched row that had a row, or a row that left the work: the changing body rows are
        # those listed in these rows' old rows, and the gaining ones. The others stay as they
        # are and are not read (the table is copied whole once)
        same = rows.shape == T.rows.shape and bool(torch.equal(rows, T.rows))
        onb, omask = T.gather(q, within=same)  # (a row new to the work set has none: empty)
        touched = torch.zeros(N, dtype=torch.bool, device=dev)
        touched.index_fill_(0, onb[omask], True).index_fill_(0, ti, True)
        if not same:  # the rows that left the work set free their partners
            left = T.rows.index_select(0, torch.nonzero(~alive.index_select(0, T.rows)).squeeze(1))
            lnb, lmask = T.gather(left, within=True)
            touched.index_fill_(0, lnb[lmask], True)
        for _, mrows in minor:  # the smaller groups' rows and their old partners (pairs across groups freed)
            mnb, mmask = T.gather(mrows, within=True)
            touched.index_fill_(0, mnb[mmask], True).index_fill_(0, mrows, True)
        srows = torch.nonzero(touched & st).squeeze(1)
        # each group's mutual pairs stay where the table holds them; every other entry is freed
        nb, keep = T.gather(srows)
        k = T.k
        S = srows.numel()
        col = srows.unsqueeze(1)
        keep = keep & st.index_select(0, nb.reshape(-1)).view_as(nb)
        if minor:
            keep &= group.index_select(0, nb.reshape(-1)).view_as(nb) == group.index_select(0, srows).unsqueeze(1)
        ls = torch.searchsorted(srows, ti)  # ti's place among the body rows
        gain = torch.bincount(ls, minlength=S)
        grows = torch.nonzero(gain).squeeze(1)
        # width: the searched rows' longest, and room in every gaining row for its gain
        short = (gain.index_select(0, grows) - (~keep.index_select(0, grows)).sum(1)).clamp_(min=0)
        k2 = max(k + (int(short.max()) if grows.numel() else 0), qnb.shape[1])
        if k2 > k:
            keep = torch.cat([keep, torch.zeros((S, k2 - k), dtype=torch.bool, device=dev)], 1)
            nb = torch.cat([nb, col.expand(S, k2 - k)], 1)
        nb = torch.where(keep, nb, col)
        mask = keep
        flat_nb, flat_mask = nb.view(-1), mask.view(-1)
        if grows.numel():  # gained partners go to the first free slots of their rows
            free = torch.nonzero(~keep.index_select(0, grows).reshape(-1)).squeeze(1)
            r = torch.div(free, k2, rounding_mode="floor")
            per = torch.bincount(r, minlength=grows.numel())
            rank = torch.arange(free.numel(), device=dev) - (torch.cumsum(per, 0) - per).index_select(0, r)
            use = torch.nonzero(rank < gain.index_select(0, grows).index_select(0, r)).squeeze(1)
            slots = grows.index_select(0, r.index_select(0, use)) * k2 + free.index_select(0, use) % k2
            # slots are in (row, column) order, as the gained partners are (sorted by row)
            flat_nb.index_copy_(0, slots, tj)
            flat_mask.index_fill_(0, slots, True)
        # the new table: the working rows, i.e. the body rows kept and the rows searched afresh:
        # the old table, its changed rows written over (where the rows are the old ones, in
        # place: the table's arrays are read by no one else, selections gather copies); the
        # body rows kept are the old rows as they were (a row new to the work set is searched)
        W = rows.numel()
        old_at = None if same else T.slot.index_select(0, rows).clamp_(min=0)
        nb_new, mask_new = (T.nb, T.mask) if same else (T.nb.index_select(0, old_at), T.mask.index_select(0, old_at))
        if k2 > k:
            nb_new = torch.cat([nb_new, rows.unsqueeze(1).expand(W, k2 - k)], 1)
            mask_new = torch.cat([mask_new, torch.zeros((W, k2 - k), dtype=torch.bool, device=dev)], 1)
        if S:
            at = torch.searchsorted(rows, srows)
            nb_new.index_copy_(0, at, nb)
            mask_new.index_copy_(0, at, mask)
        if q.numel():  # the searched rows, as the search laid them out (from the left)
            at = torch.searchsorted(rows, q)
            w = qnb.shape[1]
            if w < k2:
                qnb = torch.cat([qnb, q.unsqueeze(1).expand(-1, k2 - w)], 1)
                qmask = torch.cat([qmask, torch.zeros((q.numel(), k2 - w), dtype=torch.bool, device=dev)], 1)
            nb_new.index_copy_(0, at, qnb)
            mask_new.index_copy_(0, at, qmask)
        counts = None
        if T.counts_made is not None:  # the rows' pair counts: the changed rows' anew
            at = torch.searchsorted(rows, torch.cat([srows, q]))
            counts = T.counts_made.clone() if same else T.counts_made.index_select(0, old_at)
            counts.index_copy_(0, at, row_counts(mask_new.index_select(0, at)))
        self.table = NeighbourTable(rows, nb_new, mask_new, N, slot=T.slot if same else None, counts=counts)
        # the body's rows searched now hold all their pairs with the working particles, so
        # they join the body set: the next partial rebuild keeps them instead of searching
        # them again (a particle that joins the work set is searched once)
        self.static = st.index_fill_(0, q, True) & rigid
        self.cross = cross
        self.n_partial += 1
        return True


def subset_table(x: torch.Tensor, work: torch.Tensor, radius: float, domain: Domain,
                 rows: torch.Tensor | None = None, sources: torch.Tensor | None = None):
    """:func:`build_table` over the particles ``work`` only, in the full numbering: a
    :class:`NeighbourTable` with the working particles' rows (the others have none). With
    ``rows`` (indices of working particles), ``(nb, mask)`` of those rows only, as
    :func:`build_table`'s ``rows``, and with ``sources`` (a mask over all particles, working
    ones only) the neighbours among those only: no pass over the particles outside the work
    (the full scene's cross-body search took 50 ms binning 733 600 particles for 53 000 working)."""
    idx = torch.nonzero(work).squeeze(1)
    if rows is not None:
        local = torch.full((x.shape[0],), -1, dtype=torch.long, device=x.device)
        local[idx] = torch.arange(idx.numel(), device=x.device)
        nb_w, mask_w = build_table(x.index_select(0, idx), radius, domain, rows=local.index_select(0, rows),
                                   sources=None if sources is None else sources.index_select(0, idx))
        return idx.index_select(0, nb_w.reshape(-1)).view_as(nb_w), mask_w
    nb_w, mask_w = build_table(x.index_select(0, idx), radius, domain)
    return NeighbourTable(idx, idx.index_select(0, nb_w.reshape(-1)).view_as(nb_w), mask_w, x.shape[0])
