"""Neighbour search: sorted cell lists producing pair tensors, plus a Verlet list.

The search is fully vectorised: particles are binned into cells of edge >= radius,
sorted by linear cell index with ``argsort``, and for each of the 3^d stencil
offsets (a loop over at most 27 offsets, never over particles or cells) the
candidate pairs of every particle are produced at once with ``searchsorted`` and
``repeat_interleave``, then filtered by distance; for a few rows (a partial rebuild's)
the offsets are searched together, in one such pass (``PASS_ROWS``). Periodic axes use the minimum
image convention; they must span at least two search radii so that a pair has one
image at most within the radius.
"""
from __future__ import annotations

import itertools
import math
from dataclasses import dataclass, field

import torch


@dataclass
class Domain:
    """The simulation box. Only periodic axes need bounds; ``lo``/``hi`` of open axes
    are informative (the cell grid of an open axis follows the particles)."""

    lo: list[float]
    hi: list[float]
    periodic: list[bool] = field(default_factory=list)

    def __post_init__(self):
        self.dim = len(self.lo)
        if not self.periodic:
            self.periodic = [False] * self.dim
        if len(self.hi) != self.dim or len(self.periodic) != self.dim:
            raise ValueError("Domain: lo, hi and periodic must have the same length")
        self.length = [h - l for l, h in zip(self.lo, self.hi)]
        for a in range(self.dim):
            if self.periodic[a] and self.length[a] <= 0:
                raise ValueError(f"Domain: periodic axis {a} has non-positive length")

    @property
    def any_periodic(self) -> bool:
        return any(self.periodic)

    def displacement(self, xi: torch.Tensor, xj: torch.Tensor) -> torch.Tensor:
        """x_i - x_j with the minimum image on periodic axes."""
        d = xi - xj
        return self.minimum_image(d)

    def minimum_image(self, d: torch.Tensor) -> torch.Tensor:
        if not self.any_periodic:
            return d
        cols = []
        for a in range(self.dim):
            c = d[..., a]
            if self.periodic[a]:
                L = self.length[a]
                c = c - L * torch.round(c * (1.0 / L))
            cols.append(c)
        return torch.stack(cols, dim=-1)

    def wrap(self, x: torch.Tensor) -> torch.Tensor:
        """Map positions on periodic axes back into [lo, hi)."""
        if not self.any_periodic:
            return x
        cols = []
        for a in range(self.dim):
            c = x[:, a]
            if self.periodic[a]:
                c = self.lo[a] + torch.remainder(c - self.lo[a], self.length[a])
            cols.append(c)
        return torch.stack(cols, dim=-1)


# Cells per search radius along each axis: cells of edge radius / 2 and a 5-cell stencil
# test (2.5 r)^3 of candidates per particle instead of (3 r)^3 (42 % fewer distances).
CELLS_PER_RADIUS = 2


def _cell_grid(x: torch.Tensor, radius: float, domain: Domain, m: int = 1):
    """Integer cell coordinates (N, d) for cells of edge >= radius / m, cells per axis, and
    the stencil offsets per axis (-m..m, or each cell once on a short periodic axis)."""
    coords, ncell, offsets = [], [], []
    edge = radius / m
    for a in range(domain.dim):
        xa = x[:, a]
        if domain.periodic[a]:
            L = domain.length[a]
            if L < 2.0 * radius:
                raise ValueError(
                    f"periodic axis {a} has length {L:g} < 2 x search radius {radius:g}: "
                    "enlarge the box or reduce the smoothing length")
            n = max(int(L // edge), 1)
            cs = L / n
            c = torch.floor((xa - domain.lo[a]) / cs).long().remainder(n)
            offsets.append(list(range(-m, m + 1)) if n >= 2 * m + 1 else list(range(n)))
        else:
            lo = float(xa.min())
            n = int((float(xa.max()) - lo) // edge) + 1
            c = torch.floor((xa - lo) / edge).long().clamp_(0, n - 1)
            offsets.append(list(range(-m, m + 1)))
        coords.append(c)
        ncell.append(n)
    return torch.stack(coords, dim=1), ncell, offsets


# Rows x stencil passes searched at once by build_table: a group of passes holds at most this
# many; more rows go one pass at a time. Measured on the CPU, grouping pays only where the
# per-pass kernels' launches cost more than their work (a few thousand rows or fewer).
PASS_ROWS = 1 << 13


class CellStarts:
    """The sorted particles' cell ids as each cell's first place in them (``starts[c]``, and
    ``starts[C]`` the end): a cell's run is two reads instead of two binary searches of the
    sorted ids (the full scene's partial rebuild spent ~20 ms in them). Made where the grid
    has at most :data:`DENSE_CELLS` cells per particle binned (else the searches are kept)."""

    def __init__(self, sorted_cid: torch.Tensor, n_cells: int):
        counts = torch.bincount(sorted_cid, minlength=n_cells)
        self.starts = torch.zeros(n_cells + 1, dtype=torch.long, device=sorted_cid.device)
        torch.cumsum(counts, 0, out=self.starts[1:])
        self.top = n_cells


# grid cells per binned particle up to which :class:`CellStarts` is made
DENSE_CELLS = 16


def cell_range(cells, first: torch.Tensor, last: torch.Tensor):
    """The places [start, end) of the sorted particles in the cells ``first`` .. ``last`` (ids;
    one run of the numbering). ``cells``: the sorted ids, or their :class:`CellStarts`. Ids off
    the grid (an outer offset past its edge, masked by the caller) read any run."""
    if isinstance(cells, CellStarts):
        return (cells.starts.index_select(0, first.clamp(0, cells.top)),
                cells.starts.index_select(0, (last + 1).clamp_(0, cells.top)))
    return torch.searchsorted(cells, first, right=False), torch.searchsorted(cells, last, right=True)


def _search_passes(off, reach, c, xcol, xscol, sorted_cid, order, me, base, all_rows: bool, outer, inner, mult,
                   ncell, domain: Domain, r2max: float):
    """One group of :func:`build_table`'s stencil passes for all its query rows at once: the
    pairs (row, slot, j) found, each row's pairs after those already in it (``base``, which is
    advanced), pass after pass, in cell order within a pass (the order of one pass at a time);
    None where the group finds none. ``off``: the passes' outer offsets (P, outer axes);
    ``reach``: their inner runs' cells on each side (P, 1)."""
    dev = c.device
    Q, P = c.shape[0], off.shape[0]
    valid = torch.ones((P, Q), dtype=torch.bool, device=dev)
    ncid = torch.zeros((P, Q), dtype=torch.long, device=dev)
    for k, a in enumerate(outer):
        na = c[:, a].unsqueeze(0) + off[:, k:k + 1]
        if domain.periodic[a]:
            na = na.remainder(ncell[a])
        else:
            valid &= (na >= 0) & (na < ncell[a])
        ncid += na * mult[a]
    if inner is None:
        first, last = ncid.view(-1), ncid.view(-1)
    else:  # the run of cells along the inner axis, clipped to the grid
        ci = c[:, inner].unsqueeze(0)
        first = (ncid + (ci - reach).clamp_(min=0)).view(-1)
        last = (ncid + (ci + reach).clamp_(max=ncell[inner] - 1)).view(-1)
    start, end = cell_range(sorted_cid, first, last)
    cnt = torch.where(valid.view(-1), end - start, torch.zeros_like(start))  # per (pass, row), pass-major
    total = int(cnt.sum())
    if total == 0:
        return None
    grp = torch.repeat_interleave(torch.arange(P * Q, device=dev), cnt, output_size=total)  # sorted
    pos = torch.arange(total, device=dev) + (start - (torch.cumsum(cnt, 0) - cnt)).index_select(0, grp)
    # each candidate's row (integer division by Q is the slow way on the CPU)
    i = torch.repeat_interleave(torch.arange(Q, device=dev).repeat(P), cnt, output_size=total) if P > 1 else grp
    dim = len(xcol)
    r2 = None
    for a in range(dim):
        da = xcol[a].index_select(0, i) - xscol[a].index_select(0, pos)
        if domain.periodic[a]:
            L = domain.length[a]
            da -= L * torch.round(da * (1.0 / L))
        r2 = da * da if r2 is None else r2.addcmul_(da, da)
    keep = torch.nonzero(r2 < r2max).squeeze(1)
    i, j = i.index_select(0, keep), order.index_select(0, pos.index_select(0, keep))
    grp = grp.index_select(0, keep) if P > 1 else i
    keep = torch.nonzero((i if all_rows else me.index_select(0, i)) != j).squeeze(1)
    i, j = i.index_select(0, keep), j.index_select(0, keep)
    grp = grp.index_select(0, keep) if P > 1 else i
    kept = torch.bincount(grp, minlength=P * Q)  # per (pass, row)
    per_pass = kept.view(P, Q)
    # a pair's slot: its place among the kept, less its (pass, row)'s first place there, plus
    # the row's slots filled before that pass
    shift = (torch.cumsum(per_pass, 0) - per_pass + base.unsqueeze(0)).view(-1) - (torch.cumsum(kept, 0) - kept)
    slot = torch.arange(grp.numel(), device=dev) + shift.index_select(0, grp)
    base += per_pass.sum(0)
    return i, slot, j


def build_table(x: torch.Tensor, radius: float, domain: Domain, cells_per_radius: int | None = None,
                rows: torch.Tensor | None = None, sources: torch.Tensor | None = None):
    """Neighbour table of every particle: all j != i with |x_i - x_j| < radius
    (minimum image on periodic axes). With ``rows`` (indices into ``x``), the table of those
    particles only (row r lists the neighbours of ``rows[r]`` among all of ``x``). With
    ``sources`` (a mask of ``x``), the neighbours are taken among those particles only (only
    they are binned: a row far from every source costs its stencil's range searches alone).

    Returns ``(nb, mask)`` of shape (N, k), k the largest neighbour count: row i lists
    the neighbours of i, padded with i itself (``mask`` False there). Padding with the
    particle itself makes every gradient term vanish (dx = 0, dW/dr(0) = 0), so most
    sums need no mask. Rows are filled stencil pass by stencil pass, so no sort of the
    pairs is needed. Cells are numbered with an open axis varying fastest, so the stencil's
    cells along it are one run of the sorted order: one ``searchsorted`` range per pass
    covers them (5^2 passes for cells of edge radius / 2 in 3-d, not 5^3).
    """
    N = x.shape[0]
    dev = x.device
    if N == 0 or (rows is not None and rows.numel() == 0):
        n = 0 if rows is None else rows.numel()
        return (torch.zeros((n, 1), dtype=torch.long, device=dev) if rows is None else rows.unsqueeze(1).clone(),
                torch.zeros((n, 1), dtype=torch.bool, device=dev))
    m = CELLS_PER_RADIUS if cells_per_radius is None else int(cells_per_radius)
    x = domain.wrap(x)
    c, ncell, offsets = _cell_grid(x, radius, domain, m)
    dim = domain.dim
    # the fastest-varying axis of the numbering: an open one where there is one (its stencil
    # cells are contiguous in the sorted order; a periodic axis wraps)
    inner = next((a for a in reversed(range(dim)) if not domain.periodic[a]), None)
    axes = [a for a in range(dim) if a != inner] + ([inner] if inner is not None else [])
    mult = [1] * dim
    for k in range(dim - 2, -1, -1):
        mult[axes[k]] = mult[axes[k + 1]] * ncell[axes[k + 1]]
    cid = sum(c[:, a] * mult[a] for a in range(dim))
    if sources is None:
        order = torch.argsort(cid)
    else:
        src = torch.nonzero(sources).squeeze(1)
        order = src.index_select(0, torch.argsort(cid.index_select(0, src)))
    sorted_cid = cid[order]
    n_cells = math.prod(ncell)
    if n_cells <= DENSE_CELLS * max(order.numel(), 1):
        sorted_cid = CellStarts(sorted_cid, n_cells)
    # coordinates one axis at a time (1-d gathers are the fast ones), the j side in cell
    # order: a pass reads runs of it
    xcol = [x[:, a].contiguous() for a in range(dim)]
    xscol = [xa.index_select(0, order) for xa in xcol]
    if rows is not None:  # the query side: those rows only
        c = c.index_select(0, rows)
        xcol = [xa.index_select(0, rows) for xa in xcol]
    Q = N if rows is None else rows.numel()
    ar = torch.arange(Q, device=dev)
    me = ar if rows is None else rows  # the particle of each row
    r2max = radius * radius
    outer = [a for a in range(dim) if a != inner]
    edge = radius / m
    # the stencil is trimmed to the cells that can hold a neighbour: an outer offset whose
    # cells are a distance >= radius away is skipped, and the run along the inner axis is
    # as long as the rest of the radius needs (offsets are true offsets only where the axis
    # is not a short periodic one, which lists each of its cells once)
    trim = all(offsets[a] == list(range(-m, m + 1)) for a in outer)
    passes = []  # (outer offsets, cells of the inner run on each side)
    for off in itertools.product(*(offsets[a] for a in outer)):
        reach = m
        if trim:
            gap2 = sum(max(abs(o) - 1, 0) ** 2 for o in off) * edge * edge
            if gap2 >= r2max:
                continue
            reach = min(m, math.ceil(math.sqrt(r2max - gap2) / edge))
        passes.append((off, reach))
    base = torch.zeros(Q, dtype=torch.long, device=dev)  # neighbours found so far per row
    found = []
    # the passes go in groups, one vectorised search per group: a partial rebuild's few rows
    # take every pass at once (a few dozen kernels instead of a few hundred); a full build's
    # take one or a few at a time (its candidates' memory bounded as a single pass bounds it)
    group = max(1, PASS_ROWS // max(Q, 1))
    off = torch.tensor([list(o) for o, _ in passes], dtype=torch.long).view(len(passes), len(outer)).to(dev)
    reach = torch.tensor([r for _, r in passes], dtype=torch.long).unsqueeze(1).to(dev)
    for g0 in range(0, len(passes), group):
        found.append(_search_passes(off[g0:g0 + group], reach[g0:g0 + group], c, xcol, xscol, sorted_cid, order, me,
                                    base, rows is None, outer, inner, mult, ncell, domain, r2max))
    found = [f for f in found if f is not None]
    k = max(int(base.max()), 1)
    nb = me.unsqueeze(1).repeat(1, k)
    mask = torch.zeros((Q, k), dtype=torch.bool, device=dev)
    if found:
        i, slot, j = (torch.cat(t) for t in zip(*found))
        flat = i * k + slot
        nb.view(-1).index_copy_(0, flat, j)
        mask.view(-1).index_fill_(0, flat, True)
    return nb, mask


def build_pairs(x: torch.Tensor, radius: float, domain: Domain, cells_per_radius: int | None = None):
    """All ordered pairs (i, j), i != j, with |x_i - x_j| < radius, sorted by (i, j)."""
    nb, mask = build_table(x, radius, domain, cells_per_radius)
    i = torch.arange(x.shape[0], device=x.device).unsqueeze(1).expand_as(nb)[mask]
    j = nb[mask]
    perm = torch.argsort(i * max(x.shape[0], 1) + j)
    return i[perm], j[perm]


def brute_force_pairs(x: torch.Tensor, radius: float, domain: Domain):
    """O(N^2) reference for tests: same convention as :func:`build_pairs`."""
    N = x.shape[0]
    x = domain.wrap(x)
    ii, jj = torch.meshgrid(torch.arange(N), torch.arange(N), indexing="ij")
    ii, jj = ii.reshape(-1).to(x.device), jj.reshape(-1).to(x.device)
    d = domain.displacement(x[ii], x[jj])
    r2 = d[:, 0] * d[:, 0]  # summed in the same order as build_table, so ties agree bit for bit
    for a in range(1, domain.dim):
        r2 = r2 + d[:, a] * d[:, a]
    keep = (r2 < radius * radius) & (ii != jj)
    return ii[keep], jj[keep]


def row_counts(mask: torch.Tensor) -> torch.Tensor:
    """True entries per row of a boolean (R, k) mask, as int64 (summed as bytes: a bool sum
    converts every entry to int64 first, twice as slow)."""
    return mask.view(torch.uint8).sum(1, dtype=torch.int32).long()


class NeighbourTable:
    """The neighbour lists of some particles (``rows``, sorted; the others have none), as a
    (R, k) table in the particles' numbering: row r lists the neighbours of ``rows[r]``,
    padded with ``rows[r]`` itself (``mask`` False there). With an active set only its work
    particles have rows, so the table's size follows them, not all N particles.
    :meth:`gather` reads the rows of any particles (an empty row for one without)."""

    def __init__(self, rows: torch.Tensor, nb: torch.Tensor, mask: torch.Tensor, n: int,
                 slot: torch.Tensor | None = None, counts: torch.Tensor | None = None):
        """``slot``, ``counts``: the row of each particle and each row's pair count, where the
        caller has them (else made here, the counts when first asked for)."""
        self.rows, self.nb, self.mask, self.n = rows, nb, mask, n
        self.slot = slot if slot is not None else torch.full((n,), -1, dtype=torch.long, device=nb.device).index_copy_(
            0, rows, torch.arange(rows.numel(), device=nb.device))
        self._counts = counts

    @property
    def counts(self) -> torch.Tensor:
        """Pairs per row (R,)."""
        if self._counts is None:
            self._counts = row_counts(self.mask)
        return self._counts

    @property
    def counts_made(self) -> torch.Tensor | None:
        """The pairs per row if they were made (or given), else None (not made here)."""
        return self._counts

    @classmethod
    def dense(cls, nb: torch.Tensor, mask: torch.Tensor) -> "NeighbourTable":
        """A table with a row for every particle (an (N, k) table as :func:`build_table` makes)."""
        return cls(torch.arange(nb.shape[0], device=nb.device), nb, mask, nb.shape[0])

    @property
    def k(self) -> int:
        return self.nb.shape[1]

    def has_row(self) -> torch.Tensor:
        """Mask of the particles with a row."""
        return self.slot >= 0

    def gather(self, idx: torch.Tensor, within: bool = False, trim: bool = False) -> tuple[torch.Tensor, torch.Tensor]:
        """(nb, mask) of the particles ``idx``, shape (len(idx), k); a particle without a row
        gets an empty one (itself, mask False). ``within``: the caller knows every one has a
        row (the working particles' subsets): read straight (a particle without one raises).
        ``trim``: drop the trailing columns that are padding in every one of these rows where
        that leaves at most 3/4 of the table's width (one read of the host: at a selection), so a
        term's pair sums follow its own rows' widths, not the widest row of the table (solid
        packed under a deposit: 434 columns where the melt's rows use 200; the 0.2 mm
        perpendicular rung's step 73-75 -> 50-52 ms with the shared geometry). A smaller
        saving keeps the table's width: each new width is a new shape for a traced step."""
        if self.rows.numel() == 0:
            return idx.unsqueeze(1).clone(), torch.zeros((idx.numel(), 1), dtype=torch.bool, device=idx.device)
        s = self.slot.index_select(0, idx)
        if within:
            nb, mask = self.nb.index_select(0, s), self.mask.index_select(0, s)
        else:
            has = (s >= 0).unsqueeze(1)
            s = s.clamp_min(0)
            nb = torch.where(has, self.nb.index_select(0, s), idx.unsqueeze(1))
            mask = self.mask.index_select(0, s) & has
        if trim and nb.shape[0] and nb.shape[1] > 1:
            used = torch.nonzero(mask.any(0)).flatten()
            width = max(int(used[-1]) + 1 if used.numel() else 1, 1)
            width = min(-(-width // 8) * 8, nb.shape[1])  # (a multiple of 8: fewer distinct shapes)
            if width <= 0.75 * nb.shape[1]:
                nb, mask = nb[:, :width].contiguous(), mask[:, :width].contiguous()
        return nb, mask

    def to_dense(self) -> tuple[torch.Tensor, torch.Tensor]:
        """The (N, k) table of every particle (for tests and tools: its size follows N)."""
        nb = torch.arange(self.n, device=self.nb.device).unsqueeze(1).repeat(1, max(self.k, 1))
        mask = torch.zeros(nb.shape, dtype=torch.bool, device=nb.device)
        if self.rows.numel():
            nb.index_copy_(0, self.rows, self.nb)
            mask.index_copy_(0, self.rows, self.mask)
        return nb, mask

    def n_pairs(self) -> int:
        return int(self.counts.sum())

    def state_dict(self) -> dict:
        return {"rows": self.rows, "nb": self.nb, "mask": self.mask, "n": self.n}

    @classmethod
    def from_state(cls, d: dict, device=None) -> "NeighbourTable":
        to = lambda t: t.to(device) if device is not None else t  # noqa: E731
        if "rows" not in d:  # a dense (N, k) table (checkpoints before compact tables)
            return cls.dense(to(d["nb"]), to(d["mask"]))
        return cls(to(d["rows"]), to(d["nb"]), to(d["mask"]), int(d["n"]))
