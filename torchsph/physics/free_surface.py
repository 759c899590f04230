"""The free-surface stage: the colour gradient (3.9) once per evaluation point, for every
term that reads it (the surface forces on the melt's surface, the surface losses' area on
all material), with one threshold |grad c| h > ``threshold`` for "on the surface"."""
from __future__ import annotations

import torch

from torchsph.core.kernels import Kernel
from torchsph.core.neighbors import Domain
from torchsph.physics.fluid import gather_nb, pair_dwdr_r, pair_geometry, pair_sum


def colour_pair_weights(m, rho, rows, nb, r, kernel: Kernel, h: float):
    """The pair weights of the colour gradient (3.9), (V_i^2 + V_j^2) rho_i / (rho_i + rho_j)
    dW/dr / (r V_i) (rows, k), so that grad c_i = sum_j w_ij (x_i - x_j); and V_j (rows, k)."""
    rho_i = rho.index_select(0, rows).unsqueeze(1)
    rho_j = gather_nb(rho, nb)
    Vi = m.index_select(0, rows).unsqueeze(1) / rho_i
    Vj = gather_nb(m, nb) / rho_j
    return (Vi * Vi + Vj * Vj) * rho_i / (rho_i + rho_j) * pair_dwdr_r(r, kernel, h) / Vi, Vj


def colour_and_norm_pairs(x, m, rho, rows, nb, kernel: Kernel, h: float, domain: Domain):
    """:func:`colour_gradient_pairs` and, from the same pair geometry, the Laplacian
    normalisation zeta_i = -(1/d) sum_j V_j r_ij dW/dr (:func:`torchsph.physics.thermal.laplacian_norm`,
    the same operations in the same order: the same bits)."""
    dx, r = pair_geometry(x, rows, nb, domain, h)
    w, Vj = colour_pair_weights(m, rho, rows, nb, r, kernel, h)
    return pair_sum(w, dx), -(Vj * r * kernel.dwdr(r, h)).sum(1) / x.shape[1]


def colour_gradient_pairs(x, m, rho, rows, nb, kernel: Kernel, h: float, domain: Domain):
    """grad c_i = (1/V_i) sum_j (V_i^2 + V_j^2) rho_i / (rho_i + rho_j) dW/dr e_ij (3.9) over
    all material neighbours (c = 1 in all material): nonzero only where the kernel is
    truncated, i.e. at a free surface. Points into the material."""
    dx, r = pair_geometry(x, rows, nb, domain, h)
    w, _ = colour_pair_weights(m, rho, rows, nb, r, kernel, h)
    return pair_sum(w, dx)


class SelectionArrays:
    """Whole-length work arrays of one pair selection, by name: made zero at first use and
    then written in place on the selection's rows only (fixed until the next selection), so
    they stay zero elsewhere without being made and zeroed whole at every evaluation.
    :meth:`reset` at each selection."""

    def __init__(self):
        self.arrays: dict[str, torch.Tensor] = {}

    def reset(self):
        self.arrays = {}

    def zeros(self, name: str, like: torch.Tensor) -> torch.Tensor:
        b = self.arrays.get(name)
        if b is None or b.shape != like.shape or b.dtype != like.dtype or b.device != like.device:
            b = self.arrays[name] = torch.zeros_like(like)
        return b

    def whole(self, name: str, like: torch.Tensor, rows: torch.Tensor, vals: torch.Tensor) -> torch.Tensor:
        """``vals`` at ``rows`` (the selection's), zero elsewhere."""
        return self.zeros(name, like).index_copy_(0, rows, vals)

    def accumulator(self, name: str, like: torch.Tensor, *places: torch.Tensor) -> torch.Tensor:
        """A zero array to sum into at ``places`` (the selection's entries; zeroed there only)."""
        b = self.zeros(name, like)
        for p in places:
            b.index_fill_(0, p.reshape(-1), 0)
        return b


class ColourGradient:
    """The colour gradient of the particles the terms ask for, evaluated once per state.

    At a pair selection each term says which rows it will read (:meth:`want`); the first
    :meth:`of` at a state computes the gradient over the union of those rows in one pair sum
    and every term takes its rows from it. A new state (positions or densities replaced by
    the step) or a new selection starts afresh."""

    def __init__(self, kernel: Kernel, h: float, domain: Domain, threshold: float = 0.05, compile: bool = False):
        self.kernel, self.h, self.domain, self.threshold = kernel, h, domain, threshold
        self.fn = torch.compile(colour_gradient_pairs, dynamic=True) if compile else colour_gradient_pairs
        self.wanted: dict[str, torch.Tensor] = {}
        self.nbs: dict[str, torch.Tensor | None] = {}  # the rows' gathered table, where a term gave it
        self.table = None
        self.memo = None  # (x, rho, {name: gradient of its rows})
        self.norm_rows = None  # rows whose Laplacian normalisation the next evaluation also makes (want_norm)
        self.norm_memo = None  # (x, rho, norm_rows, their normalisation)

    def want_norm(self, rows: torch.Tensor | None):
        """At a selection: the next evaluation also makes the Laplacian normalisation of
        ``rows`` (among the rows asked for), from the pairs it reads anyway (None: not)."""
        self.norm_rows, self.norm_memo = rows, None

    def norm(self, state, rows: torch.Tensor) -> torch.Tensor | None:
        """The normalisation of ``rows`` made by the evaluation at ``state``, if it made it."""
        m = self.norm_memo
        if m is not None and m[0] is state.x and m[1] is state.rho and m[2] is rows:
            return m[3]
        return None

    def want(self, name: str, rows: torch.Tensor | None, table=None, nb: torch.Tensor | None = None):
        """Term ``name`` reads the rows ``rows`` of the neighbour table ``table`` (None: nothing);
        ``nb``: those rows of the table, gathered already (a term's own, whose pair geometry an
        evaluation then shares: :class:`torchsph.physics.fluid.GeometryMemo`)."""
        if rows is None:
            self.wanted.pop(name, None)
            self.nbs.pop(name, None)
        else:
            self.wanted[name] = rows
            self.nbs[name] = nb
            self.table = table
        self.memo = None

    def of(self, state, name: str) -> torch.Tensor:
        """(rows, d): the colour gradient of term ``name``'s rows at ``state``."""
        memo = self.memo
        if memo is None or memo[0] is not state.x or memo[1] is not state.rho or name not in memo[2]:
            self.memo = memo = (state.x, state.rho, self._evaluate(state))
        return memo[2][name]

    def _evaluate(self, state) -> dict[str, torch.Tensor]:
        sets = list(self.wanted.items())
        # zeta's rows join the union (at a selection they are the area's); not in a traced step,
        # which then makes zeta apart and has no variant for it
        nr = None if torch.compiler.is_compiling() else self.norm_rows
        if len(sets) == 1 and nr is None:
            name, rows = sets[0]
            nb = self.nbs.get(name)
            if nb is None:
                nb = self.table.gather(rows, within=True)[0]
            return {name: self.fn(state.x, state.m, state.rho, rows, nb, self.kernel, self.h, self.domain)}
        mark = torch.zeros(state.n, dtype=torch.bool, device=state.x.device)
        for rows in [r for _, r in sets] + ([nr] if nr is not None else []):
            mark.index_fill_(0, rows, True)
        union = torch.nonzero(mark).squeeze(1)  # (at a selection's first evaluation only)
        slot = torch.cumsum(mark, 0) - 1
        nb = self.table.gather(union, within=True)[0]
        if nr is not None:  # zeta from the same pairs (a selection's)
            g, zn = colour_and_norm_pairs(state.x, state.m, state.rho, union, nb, self.kernel, self.h, self.domain)
            self.norm_memo = (state.x, state.rho, nr, zn.index_select(0, slot.index_select(0, nr)))
            self.norm_rows = None  # (once: the next evaluations have the surface rows alone)
        else:
            g = self.fn(state.x, state.m, state.rho, union, nb, self.kernel, self.h, self.domain)
        return {name: g.index_select(0, slot.index_select(0, rows)) for name, rows in sets}
