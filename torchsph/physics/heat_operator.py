"""The Cleary-Monaghan conduction sum (3.13) as a cached sparse operator.

(div k grad T)_i = sum_j w_ij V_j (T_i - T_j), with V_j = m_j / rho_j and the pair factor

    g_ij = 4 k_i k_j / (k_i + k_j) * 2 / (zeta_i + zeta_j) * (1/r) dW/dr

(per-particle conductivity k, the Laplacian normalisation zeta of
:func:`torchsph.physics.thermal.laplacian_norm`, fixed per pair selection). Between two solid
particles of one rigid body the distance does not change, so the kernel factor is a
constant (their volumes may still change: solid next to melt is the melt's wall, its
density set by the melt's pressure). Those pairs form a sparse matrix G (CSR) and their
sum is one product of G with the two columns [V, V T]:

    sum_j g_ij V_j (T_i - T_j) = T_i (G V)_i - (G (V T))_i.

The other pairs (any pair with melt or a wall, two bodies moving past each other) are a
flat pair list whose factors are evaluated every step. No padded neighbour table is read
per step. How long G lives and what makes it reproducible: :class:`ConductionOperator`.
"""
from __future__ import annotations

import warnings

import torch

from torchsph.core.kernels import Kernel
from torchsph.core.neighbors import Domain
from torchsph.physics.fluid import dot


def pair_factor(x_i, x_j, k_i, k_j, z_i, z_j, kernel: Kernel, h: float, domain: Domain):
    """g_ij on flat pair arrays (one entry per pair); dW/dr < 0, so g_ij < 0 and
    sum_j g_ij V_j (T_i - T_j) moves heat from hot to cold."""
    return material_factor(k_i, k_j, z_i, z_j) * kernel_factor(x_i, x_j, kernel, h, domain)


def kernel_factor(x_i, x_j, kernel: Kernel, h: float, domain: Domain):
    """(1/r) dW/dr on flat pair arrays."""
    return dwdr_over_r(squared_distance(x_i, x_j, domain), kernel, h)


def squared_distance(x_i, x_j, domain: Domain):
    """|x_i - x_j|^2 (minimum image) on flat pair arrays (a per-component sum: .sum(-1)
    over an axis of 3 is slow)."""
    d = domain.minimum_image(x_i - x_j)
    return dot(d, d)


def dwdr_over_r(r2, kernel: Kernel, h: float):
    r = torch.sqrt(r2).clamp_min(1e-12 * h)
    return kernel.dwdr(r, h) / r


def material_factor(k_i, k_j, z_i, z_j):
    """4 k_i k_j / (k_i + k_j) * 2 / (zeta_i + zeta_j)."""
    return 4.0 * k_i * k_j / (k_i + k_j) * (2.0 / (z_i + z_j))


def entry_material(k: torch.Tensor, zeta: torch.Tensor, i: torch.Tensor, j: torch.Tensor,
                   k1: torch.Tensor | None = None) -> torch.Tensor:
    """:func:`material_factor` of the entries (i, j). ``k1``: the one conductivity of a scene
    of one material (a 0-d tensor), whose part is then one number made by the same operations:
    the same values without the two gathers and three passes over the entries (a full build of
    the full scene's operator, 3.9 M entries, spent 35-85 ms in them)."""
    k_i, k_j = (k1, k1) if k1 is not None else (k.index_select(0, i), k.index_select(0, j))
    return material_factor(k_i, k_j, zeta.index_select(0, i), zeta.index_select(0, j))


def rows_of(x: torch.Tensor, i: torch.Tensor) -> torch.Tensor:
    """``x.index_select(0, i)`` for a 2-D ``x``, as a gather: 4x faster than index_select
    for a million rows of a large array on one CPU thread (measured), the same values."""
    return torch.gather(x, 0, i.unsqueeze(1).expand(-1, x.shape[1]))


# table entries (rows x width) a pass over table rows takes at once (:func:`by_rows`): the
# conduction matrix's rigid entries have temporaries of ~40 bytes an entry (positions of both
# ends, distances, indices), so a whole build of the full scene once every particle works (734 k
# rows x 180) peaked at ~20 GB; in blocks of rows it is bounded. Smaller blocks are faster on the
# CPU too (their temporaries stay in cache): the full scene's first refresh 575 -> 550 ms with
# 2^18 instead of 2^23, and its whole zeta (38 700 rows x 178) 0.66-1.5 s -> 0.12 s
ENTRY_BLOCK = 1 << 18


def by_rows(fn, *arrays: torch.Tensor):
    """``fn(*arrays)`` for arrays of table rows (the same rows first; the last an (R, k) table),
    taken in blocks of rows of at most :data:`ENTRY_BLOCK` table entries and joined: the same
    result (each row's is its own, and a block's rows come after the previous block's), with
    each block's pair temporaries small. ``fn`` returns a tensor or a tuple of them."""
    R, kk = arrays[-1].shape[0], max(arrays[-1].shape[1], 1)
    step = max(ENTRY_BLOCK // kk, 1)
    if R <= step:
        return fn(*arrays)
    parts = [fn(*(t[a:a + step] for t in arrays)) for a in range(0, R, step)]
    return torch.cat(parts) if isinstance(parts[0], torch.Tensor) else tuple(torch.cat(t) for t in zip(*parts))


def rigid_entries(ri, rows, nb, mask, x_op, steady, body, kernel: Kernel, h: float, domain: Domain):
    """The rigid pairs of the table rows ``nb``, ``mask`` (of the particles ``rows``, whose
    places in the operator are ``ri``, ascending): both steady, of one body, inside the
    kernel's support at ``x_op``. Returns (row, i, j, (1/r) dW/dr) in (row, column) order,
    taken :func:`by_rows`."""
    return by_rows(lambda *t: rigid_block(*t, x_op, steady, body, kernel, h, domain), ri, rows, nb, mask)


def rigid_block(ri, rows, nb, mask, x_op, steady, body, kernel: Kernel, h: float, domain: Domain):
    n, kk = steady.shape[0], nb.shape[1]
    at = torch.nonzero((mask & (nb != rows.unsqueeze(1))).reshape(-1)).squeeze(1)  # row-major
    r = torch.div(at, kk, rounding_mode="floor")
    j = nb.reshape(-1).index_select(0, at)
    i = rows.index_select(0, r)
    rigid = steady.index_select(0, i) & steady.index_select(0, j) & (body.index_select(0, i) == body.index_select(0, j))
    c = torch.nonzero(rigid).squeeze(1)
    r, i, j = r.index_select(0, c), i.index_select(0, c), j.index_select(0, c)
    r2 = squared_distance(rows_of(x_op, i), rows_of(x_op, j), domain)
    inside = torch.nonzero(r2 < kernel.radius(h) ** 2).squeeze(1)
    order = torch.argsort(r.index_select(0, inside) * n + j.index_select(0, inside))  # canonical
    keep = inside.index_select(0, order)
    return (ri.index_select(0, r.index_select(0, keep)), i.index_select(0, keep), j.index_select(0, keep),
            dwdr_over_r(r2.index_select(0, keep), kernel, h))


def sparse_sum(G, row, g, jl, cols, rows, T, m, rho) -> torch.Tensor:
    """sum_j g_ij V_j (T_i - T_j) on ``rows`` (the particle of each of G's rows) by one product
    of the CSR matrix ``G`` (columns: the particles ``cols``) with [V, V T]. In a traced step
    (no sparse tensors there) G's entries (``row``, ``jl``, ``g``) are summed instead."""
    V_c = m.index_select(0, cols) / rho.index_select(0, cols)
    X = torch.stack([V_c, V_c * T.index_select(0, cols)], 1)
    if torch.compiler.is_compiling():
        u = torch.zeros(rows.numel(), 2, dtype=T.dtype, device=T.device).index_add_(
            0, row, g.unsqueeze(1) * X.index_select(0, jl))
    else:
        u = G @ X
    return T.index_select(0, rows) * u[:, 0] - u[:, 1]


def local_csr(crow: torch.Tensor, j: torch.Tensor, n: int):
    """A CSR matrix's columns in a local numbering: (the particles it reads, ascending; each
    entry's column among them; the (crow, column) index pair for torch.sparse_csr_tensor). A
    product then reads [V, V T] of those particles only, not of every particle; the index arrays
    are in 32 bits where they fit (the CPU's sparse product converted 64-bit ones at every
    product: 6 of 16 ms of the full scene's product at t = 10 ms, 6.5 M entries)."""
    used = torch.zeros(n, dtype=torch.bool, device=j.device).index_fill_(0, j, True)
    cols = torch.nonzero(used).squeeze(1)
    jl = (torch.cumsum(used, 0) - 1).index_select(0, j)
    small = max(j.numel(), cols.numel()) < 2**31 - 1
    return cols, jl, ((crow.int(), jl.int()) if small else (crow, jl))


def row_entries(crow: torch.Tensor, rows: torch.Tensor):
    """The entries of the CSR rows ``rows`` (places), in G's order: (entry, its place in ``rows``,
    the entries per row), at a cost that follows those entries."""
    start = crow.index_select(0, rows)
    cnt = crow.index_select(0, rows + 1) - start
    total = int(cnt.sum())
    e_row = torch.repeat_interleave(torch.arange(rows.numel(), device=rows.device), cnt, output_size=total)
    run0 = torch.cumsum(cnt, 0) - cnt  # row r's run of entries starts at crow[r]
    e = torch.arange(total, device=rows.device) - run0.index_select(0, e_row) + start.index_select(0, e_row)
    return e, e_row, cnt


def csr_find(crow: torch.Tensor, jl: torch.Tensor, rows: torch.Tensor, c: torch.Tensor) -> torch.Tensor:
    """The first entry of each CSR row ``rows`` whose column (``jl``, ascending within a row) is not
    below ``c`` (the row's end where none is): a binary search of all rows' brackets at once, in as
    many rounds as the longest bracket needs (one host read, not one a round; each round halves
    every bracket). Its cost follows the rows searched (~5 ms for the preview's 61 000 at a
    rebuild; one search of all entries' row * C + column keys instead took 4.5 ms: 20 levels of
    random reads), hence :data:`WHOLE_PASS_SHARE`."""
    lo, hi = crow.index_select(0, rows), crow.index_select(0, rows + 1)
    if rows.numel() == 0:
        return lo
    top = max(jl.numel() - 1, 0)
    for _ in range(int((hi - lo).max()).bit_length()):
        mid = torch.div(lo + hi, 2, rounding_mode="floor")
        act = lo < hi
        less = jl.index_select(0, mid.clamp_max(top)) < c
        lo, hi = torch.where(act & less, mid + 1, lo), torch.where(act & ~less, mid, hi)
    return lo


# changed_entries takes the whole pass over G's entries where the changed rows hold more than this
# share of them: the preview's rebuilds (61 000 of 606 000 entries) spent 9 ms finding them by rows
# (their partners' entries by a binary search each), ~2 ms in the whole pass
WHOLE_PASS_SHARE = 20


def changed_entries(op: "ConductionOperator", ch: torch.Tensor) -> torch.Tensor:
    """G's entries (ascending) with a particle in ``ch`` (per particle), as the whole pass
    ``ch[i] | ch[j]`` over the entries finds them, at a cost that follows the changed particles:
    the entries of their rows, and, G being symmetric in its rows, their partners' entries in
    their columns (found by :func:`csr_find`). A changed particle that is a column without a
    row (or an entry not found), or rows holding more than 1 / :data:`WHOLE_PASS_SHARE` of the
    entries, take the whole pass."""
    p = torch.nonzero(ch).squeeze(1)
    whole = lambda: torch.nonzero(ch.index_select(0, op.g_i) | ch.index_select(0, op.g_j)).squeeze(1)  # noqa: E731
    if p.numel() == 0:
        return p
    C = op.cols.numel()
    r = op.row_of.index_select(0, p)
    col = torch.searchsorted(op.cols, p).clamp_max(max(C - 1, 0))
    is_col = (op.cols.index_select(0, col) == p) if C else torch.zeros_like(r, dtype=torch.bool)
    if bool((is_col & (r < 0)).any()):
        return whole()
    has = torch.nonzero(r >= 0).squeeze(1)
    e1, e_row, _ = row_entries(op.crow, r.index_select(0, has))
    if WHOLE_PASS_SHARE * e1.numel() > op.g_j.numel():  # the rows' search would cost more than the pass
        return whole()
    partner = op.row_of.index_select(0, op.g_j.index_select(0, e1))
    q = torch.nonzero(partner >= 0).squeeze(1)
    c = col.index_select(0, has).index_select(0, e_row.index_select(0, q))
    e2 = csr_find(op.crow, op.g_jl, partner.index_select(0, q), c)
    found = e2 < op.crow.index_select(0, partner.index_select(0, q) + 1)
    if not bool(found.all()) or not bool((op.g_jl.index_select(0, e2) == c).all()):
        return whole()
    return torch.unique(torch.cat([e1, e2]))


class SlowSplit:
    """G's rows in two sets: the *fast* rows, whose whole rows are summed at every step, and
    the *slow* ones (steady solid far from the melt, the beams and the hot zone: chosen by
    :func:`torchsph.physics.conduction_window.slow_rows`), whose pairs with each other are summed once per
    window of steps, their sum times the window's length over the step's dt (the step books
    that rate over the step as any other, so the window's heat enters once). A slow row's
    pairs with fast rows are summed at every step, each from the fast row's own entry (G is
    symmetric: g_ij = g_ji), so that every pair's heat leaves one particle as it enters the
    other, whatever the window: the energy is conserved to round-off.

    Per step: one product of the fast rows' CSR matrix (its own rows and columns) and the
    boundary entries (fast row, slow column) as a pair list. Once per window: the whole G's
    product, whose slow rows less the boundary entries' sum are the slow pairs'. Made per
    build of G, at a cost that follows the fast rows' entries (not G's)."""

    def __init__(self, op: "ConductionOperator", fast: torch.Tensor):
        """``fast``: (R,) bool over ``op.rows``."""
        dev = op.rows.device
        R = op.rows.numel()
        self.fast = fast
        self.slow_f = (~fast).to(op.g.dtype)  # 1 on slow rows, 0 on fast ones
        fr = torch.nonzero(fast).squeeze(1)
        self.f_at = fr  # the fast rows' places in rows
        self.rows_f = op.rows.index_select(0, fr)  # their particles
        e, e_row, cnt = row_entries(op.crow, fr)
        self.e_row = e_row
        gj = op.g_j.index_select(0, e)
        crow = torch.zeros(fr.numel() + 1, dtype=torch.long, device=dev)
        crow[1:] = torch.cumsum(cnt, 0)
        self.cols, self.jl, csr_index = local_csr(crow, gj, op.row_of.shape[0])
        # the boundary: a fast row's entries whose column is a slow row
        rj = op.row_of.index_select(0, gj)
        b = torch.nonzero((rj >= 0) & ~fast.index_select(0, rj.clamp_min(0))).squeeze(1)
        self.b_i = self.rows_f.index_select(0, e_row.index_select(0, b))  # the fast particle
        self.b_j = gj.index_select(0, b)  # the slow particle
        self.b_row = rj.index_select(0, b)  # its place in rows
        self.R = R
        self.e, self.b, self.csr_index = e, b, csr_index
        self.revalue(op)

    def revalue(self, op: "ConductionOperator"):
        """The values of G's latest build (its structure and these fast rows unchanged): the
        split a new one of the same fast rows would be, at the cost of a gather of their entries."""
        self.g = op.g.index_select(0, self.e)
        self.g_b = self.g.index_select(0, self.b)
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", UserWarning)
            self.G = torch.sparse_csr_tensor(*self.csr_index, self.g, size=(self.f_at.numel(), self.cols.numel()),
                                             check_invariants=False)

    def apply(self, op: "ConductionOperator", T, m, rho, slow: torch.Tensor | None) -> torch.Tensor:
        q_f = sparse_sum(self.G, self.e_row, self.g, self.jl, self.cols, self.rows_f, T, m, rho)
        q = torch.zeros(self.R, dtype=T.dtype, device=T.device).index_copy_(0, self.f_at, q_f)
        i, j = self.b_i, self.b_j  # the slow row's side of each boundary pair: g_ji V_i (T_j - T_i)
        flow_b = self.g_b * (m.index_select(0, i) / rho.index_select(0, i)) * (T.index_select(0, j) - T.index_select(0, i))
        q_b = torch.zeros_like(q).index_add_(0, self.b_row, flow_b)
        q = q + q_b
        if slow is not None:  # the window's slow pairs: the slow rows' whole sums less their boundary pairs
            q_all = sparse_sum(op.G, op.g_row, op.g, op.g_jl, op.cols, op.rows, T, m, rho)
            q = q + slow * (self.slow_f * q_all - q_b)
        return q


class ConductionOperator:
    """Conduction over the rows ``rows`` (positions of the conducting particles).

    The matrix G holds the *rigid* pairs: both particles steady (solid with no phase change
    since G was built, so at the distance they had then: ``x_op``, the positions at G's
    build) and of one body, inside the kernel's support (a rigid pair beyond it never
    contributes). Its entries are sorted by (row, column), so any later build from the same
    positions (after a restart, from another neighbour table) is the same matrix bit for
    bit. G lives as long as the rows do: a neighbour rebuild that keeps the active set keeps
    it, and only re-lists the other pairs (:meth:`select`); a particle that melts leaves it
    (its entries are zeroed when the values are next made, :meth:`build`, with the current
    zeta) and its pairs are evaluated every step from then on."""

    at = None  # the rows' places among the conducting rows, where they are some of them (a decomposed run's owned)

    def __init__(self, rows: torch.Tensor, nb: torch.Tensor, mask: torch.Tensor, x_op: torch.Tensor,
                 steady: torch.Tensor, body: torch.Tensor, kernel: Kernel, h: float, domain: Domain):
        """``nb``, ``mask``: the table of ``rows``; ``x_op``, ``steady``: see the class."""
        self.rows, self.kernel, self.h, self.domain = rows, kernel, h, domain
        n, dev = steady.shape[0], rows.device
        R = rows.numel()
        self.g_row, _, self.g_j, self.g_f = rigid_entries(
            torch.arange(R, device=dev), rows, nb, mask, x_op, steady, body, kernel, h, domain)
        self._finish(R, n, steady, body)

    def _finish(self, R: int, n: int, steady: torch.Tensor, body: torch.Tensor):
        dev = self.rows.device
        self.crow = torch.zeros(R + 1, dtype=torch.long, device=dev)
        self.crow[1:] = torch.cumsum(torch.bincount(self.g_row, minlength=R), 0)
        self.row_of = torch.full((n,), -1, dtype=torch.long, device=dev).index_copy_(
            0, self.rows, torch.arange(R, device=dev))
        # the body most rigid rows belong to: its steady particles' pairs with each other are
        # all in G, so only the other particles' table rows are read for the moving pairs
        counts = torch.bincount(body.index_select(0, self.rows)[steady.index_select(0, self.rows)])
        self.main_body = int(counts.argmax()) if counts.numel() else -1
        self.cols, self.g_jl, self.csr_index = local_csr(self.crow, self.g_j, n)
        self.n_static = int(self.g_row.numel())
        self.n_dynamic = 0
        self.G = None
        self.built = False

    def follow(self, rows: torch.Tensor, table_of, x_op: torch.Tensor,
               steady: torch.Tensor, body: torch.Tensor) -> "ConductionOperator":
        """The operator of another row set (same particles, same ``x_op``): the entries of
        the rows that stay are carried (less those of particles no longer steady), only the
        new rows' entries are made (``table_of(positions)``: (nb, mask), the table rows of
        ``rows[positions]``, read for the new rows only), the left rows' are dropped. Every
        entry is a function of ``x_op`` and its pair alone and the order
        is the canonical (row, column) one, so the result is bit for bit the operator
        :meth:`__init__` makes of the same arguments, at the cost of the new rows only."""
        n, dev = steady.shape[0], rows.device
        R = rows.numel()
        row_new = torch.full((n,), -1, dtype=torch.long, device=dev).index_copy_(
            0, rows, torch.arange(R, device=dev))
        # carried: row still there, both particles still steady (rows are sorted particle
        # indices in both sets, so the carried entries stay in (row, column) order); read
        # per old row first, then per entry (one gather over the entries each)
        r_old = row_new.index_select(0, self.rows)
        r_old = torch.where(steady.index_select(0, self.rows), r_old, torch.full_like(r_old, -1))
        k_row = r_old.index_select(0, self.g_row)
        live = (k_row >= 0) & steady.index_select(0, self.g_j)
        if bool(live.all()):  # (a rebuild's read) the common case: nothing to drop, nothing copied
            k_j, k_f = self.g_j, self.g_f
        else:
            c = torch.nonzero(live).squeeze(1)
            k_row, k_j, k_f = (t.index_select(0, c) for t in (k_row, self.g_j, self.g_f))
        # made: the rows that are new
        fresh = torch.nonzero(self.row_of.index_select(0, rows) < 0).squeeze(1)
        n_row, _, n_j, n_f = rigid_entries(fresh, rows.index_select(0, fresh), *table_of(fresh), x_op, steady, body,
                                           self.kernel, self.h, self.domain)
        # merged in (row, column) order: the rows are disjoint, each part is in order, so an
        # entry's place is its own place in its part plus the other part's entries in the
        # rows before its own
        cnt_k = torch.bincount(k_row, minlength=R)
        cnt_n = torch.bincount(n_row, minlength=R)
        out = ConductionOperator.__new__(ConductionOperator)
        out.rows, out.kernel, out.h, out.domain = rows, self.kernel, self.h, self.domain
        total = int(k_row.numel() + n_row.numel())
        out.g_row = torch.empty(total, dtype=torch.long, device=dev)
        out.g_j = torch.empty_like(out.g_row)
        out.g_f = torch.empty(total, dtype=self.g_f.dtype, device=dev)
        for row, j, f, other in ((k_row, k_j, k_f, cnt_n), (n_row, n_j, n_f, cnt_k)):
            shift = torch.cumsum(other, 0) - other  # the other part's entries in the rows before
            dest = shift.index_select(0, row).add_(torch.arange(row.numel(), device=dev))
            out.g_row.scatter_(0, dest, row)  # (scatter_: 3x faster than index_copy_ here, measured)
            out.g_j.scatter_(0, dest, j)
            out.g_f.scatter_(0, dest, f)
        out._finish(R, n, steady, body)
        return out

    def same_rows(self, rows: torch.Tensor, n: int) -> bool:
        return (rows.shape == self.rows.shape and self.row_of.shape[0] == n
                and bool(torch.equal(rows, self.rows)))

    def select(self, table, steady: torch.Tensor, body: torch.Tensor, work: torch.Tensor | None,
               cross: torch.Tensor | None = None):
        """The pairs evaluated every step, from the neighbour table (a
        :class:`~torchsph.core.neighbors.NeighbourTable`): every pair
        with a particle that is not steady, or of two bodies. They are found from the table
        rows of the particles outside the main body or not steady (in the work set), each
        pair once, as it is or transposed (the table is symmetric); G's values are made
        again at the next evaluation (zeta and the steady set may have changed)."""
        # (``cross``: the particles whose row may hold a partner of another body; the steady
        # particles outside it have only partners of their own body: their rigid pairs are in G)
        cand = ~steady | (body != self.main_body if cross is None else cross)
        if work is not None:
            cand = cand & work & table.has_row()  # (a decomposed work set's outer ghosts have no row)
        cidx = torch.nonzero(cand).squeeze(1)
        nbc, mc = table.gather(cidx, within=True)
        kk = nbc.shape[1]
        mc = mc & (nbc != cidx.unsqueeze(1))
        ent = torch.nonzero(mc.reshape(-1)).squeeze(1)
        ci = cidx.index_select(0, torch.div(ent, kk, rounding_mode="floor"))
        cj = nbc.reshape(-1).index_select(0, ent)
        rigid = steady.index_select(0, ci) & steady.index_select(0, cj) & (body.index_select(0, ci) == body.index_select(0, cj))
        mv = torch.nonzero(~rigid).squeeze(1)
        ci, cj = ci.index_select(0, mv), cj.index_select(0, mv)
        r_direct, r_trans = self.row_of.index_select(0, ci), self.row_of.index_select(0, cj)
        a = torch.nonzero(r_direct >= 0).squeeze(1)
        b = torch.nonzero((r_trans >= 0) & ~cand.index_select(0, cj)).squeeze(1)
        self.d_row = torch.cat([r_direct.index_select(0, a), r_trans.index_select(0, b)])
        self.d_i = torch.cat([ci.index_select(0, a), cj.index_select(0, b)])
        self.d_j = torch.cat([cj.index_select(0, a), ci.index_select(0, b)])
        self.n_dynamic = int(self.d_row.numel())
        self.steady = steady
        self.built = False

    built_from = None  # (k, zeta, steady) of this operator's last build

    def build(self, k, zeta, k1: torch.Tensor | None = None):
        """G's values: g_ij for the rigid pairs whose particles are both still steady, 0 for
        the others (their pairs are among the moving ones now). A build after the first
        makes only the entries with a particle whose k, zeta or steady flag changed (the
        others' values are functions of unchanged inputs: the same bits). ``k1``: k's one
        value where all are equal (:func:`entry_material`)."""
        prev = self.built_from
        if prev is not None and prev[1].shape == zeta.shape and prev[0].shape == k.shape:
            k0, z0, s0 = prev
            ch = (zeta != z0) | (self.steady != s0)
            if k is not k0:
                ch = ch | (k != k0)
            redo = changed_entries(self, ch)
            ri = self.rows.index_select(0, self.g_row.index_select(0, redo))
            rj = self.g_j.index_select(0, redo)
            live = self.steady.index_select(0, ri) & self.steady.index_select(0, rj)
            gr = entry_material(k, zeta, ri, rj, k1) * self.g_f.index_select(0, redo)
            g = self.g.index_copy_(0, redo, torch.where(live, gr, torch.zeros_like(gr)))  # (G is made anew from it below)
        else:
            i, j = self.g_i, self.g_j
            live = self.steady.index_select(0, i) & self.steady.index_select(0, j)
            g = entry_material(k, zeta, i, j, k1) * self.g_f
            g = torch.where(live, g, torch.zeros_like(g))
        self.g = g
        self.built_from = (k, zeta, self.steady)
        with warnings.catch_warnings():  # "sparse CSR support is in beta": mv on CSR is what we use of it
            warnings.simplefilter("ignore", UserWarning)
            self.G = torch.sparse_csr_tensor(*self.csr_index, g, size=(self.rows.numel(), self.cols.numel()),
                                             check_invariants=False)
        self.built = True

    split = None  # a :class:`SlowSplit` of G's rows, made after each build (numerics.conduction_window)

    def apply(self, x, T, k, m, rho, zeta, slow: torch.Tensor | None = None) -> torch.Tensor:
        """(div k grad T) on ``rows``: the matrix product plus the moving pairs' sum (the
        volumes V = m / rho of the particles read only). With a :attr:`split`, G's product on
        its fast rows and their pairs with slow rows, and with ``slow`` (a 0-d factor: the
        window's length over this step's dt) the slow rows' pairs with each other, that factor
        times (:class:`SlowSplit`)."""
        if self.split is not None and self.n_static:
            q = self.split.apply(self, T, m, rho, slow)
        elif self.n_static:
            q = sparse_sum(self.G, self.g_row, self.g, self.g_jl, self.cols, self.rows, T, m, rho)
        else:
            q = torch.zeros(self.rows.numel(), dtype=T.dtype, device=T.device)
        if self.n_dynamic:
            i, j = self.d_i, self.d_j
            g = pair_factor(x.index_select(0, i), x.index_select(0, j), k.index_select(0, i), k.index_select(0, j),
                            zeta.index_select(0, i), zeta.index_select(0, j), self.kernel, self.h, self.domain)
            V_j = m.index_select(0, j) / rho.index_select(0, j)
            q = q.index_add(0, self.d_row, g * V_j * (T.index_select(0, i) - T.index_select(0, j)))
        return q

    @property
    def g_i(self) -> torch.Tensor:
        """The particle of each entry's row (made when read: not stored, not carried)."""
        return self.rows.index_select(0, self.g_row)

    @property
    def pairs(self) -> int:
        return self.n_static + self.n_dynamic
