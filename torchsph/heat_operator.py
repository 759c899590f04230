"""The Cleary-Monaghan conduction sum (3.13) as a cached sparse operator.

(div k grad T)_i = sum_j w_ij V_j (T_i - T_j), with V_j = m_j / rho_j and the pair factor

    g_ij = 4 k_i k_j / (k_i + k_j) * 2 / (zeta_i + zeta_j) * (1/r) dW/dr

(per-particle conductivity k, the Laplacian normalisation zeta of
:func:`torchsph.thermal.laplacian_norm`, fixed per pair selection). Between two solid
particles of one rigid body the distance does not change, so g_ij is a constant of the
selection (their volumes may still change: solid next to melt is the melt's wall, its
density set by the melt's pressure). Those pairs form a sparse matrix G (CSR), built once
per selection, and their sum is one product of G with the two columns [V, V T]:

    sum_j g_ij V_j (T_i - T_j) = T_i (G V)_i - (G (V T))_i.

The other pairs (any pair with melt or a wall, two bodies moving past each other) are a
flat pair list whose factors are evaluated every step. No padded neighbour table is read
per step.

The constant factors are computed from the positions at the last neighbour build
(``x_ref``, a per-particle array a checkpoint and a migration carry): a rigid pair's
distance is constant, so the value is the one any later build of the operator (after a
restart, on another rank) computes, bit for bit.
"""
from __future__ import annotations

import warnings

import torch

from .fluid import dot
from .kernels import Kernel
from .neighbors import Domain


def pair_factor(x_i, x_j, k_i, k_j, z_i, z_j, kernel: Kernel, h: float, domain: Domain):
    """g_ij on flat pair arrays (one entry per pair); dW/dr < 0, so g_ij < 0 and
    sum_j g_ij V_j (T_i - T_j) moves heat from hot to cold."""
    return material_factor(k_i, k_j, z_i, z_j) * kernel_factor(x_i, x_j, kernel, h, domain)


def kernel_factor(x_i, x_j, kernel: Kernel, h: float, domain: Domain):
    """(1/r) dW/dr on flat pair arrays."""
    d = domain.minimum_image(x_i - x_j)
    r = torch.sqrt(dot(d, d)).clamp_min(1e-12 * h)  # (a per-component sum: .sum(-1) over 3 is slow)
    return kernel.dwdr(r, h) / r


def material_factor(k_i, k_j, z_i, z_j):
    """4 k_i k_j / (k_i + k_j) * 2 / (zeta_i + zeta_j)."""
    return 4.0 * k_i * k_j / (k_i + k_j) * (2.0 / (z_i + z_j))


class ConductionOperator:
    """Conduction over the rows ``rows`` of a neighbour table. Per table, the pairs as a flat
    list (row-major), and among them the rigid ones: both particles *steady* (solid, with no
    phase change since the table was built, so at the build's distance from each other) and
    of one body, inside the kernel's support (a rigid pair beyond it never contributes),
    with their kernel factor at the build's positions. Per pair selection (a build, a phase
    change) the rigid pairs whose particles are both still steady form a constant sparse
    matrix (:meth:`build`, once zeta is known); every other pair is evaluated every step.
    ``apply`` returns (div k grad T) on ``rows`` (W/m^3)."""

    def __init__(self, rows: torch.Tensor, nb: torch.Tensor, mask: torch.Tensor, x_ref: torch.Tensor,
                 steady: torch.Tensor, body: torch.Tensor, kernel: Kernel, h: float, domain: Domain):
        """``nb``, ``mask``: the table of ``rows``; ``x_ref``: the positions it was built at;
        ``steady`` (N,): solid particles that have not changed phase since then; ``body`` (N,)."""
        self.rows, self.kernel, self.h, self.domain = rows, kernel, h, domain
        self.table = None  # the whole neighbour table the rows came from (compared by identity)
        R, kk = nb.shape
        at = torch.nonzero((mask & (nb != rows.unsqueeze(1))).reshape(-1)).squeeze(1)  # row-major
        self.ri = torch.div(at, kk, rounding_mode="floor")
        self.j = nb.reshape(-1).index_select(0, at)
        self.i = rows.index_select(0, self.ri)
        i, j = self.i, self.j
        rigid = steady.index_select(0, i) & steady.index_select(0, j) & (body.index_select(0, i) == body.index_select(0, j))
        c = torch.nonzero(rigid).squeeze(1)
        d = domain.minimum_image(x_ref.index_select(0, i.index_select(0, c)) - x_ref.index_select(0, j.index_select(0, c)))
        r2 = dot(d, d)
        near = r2 < kernel.radius(h) ** 2
        inside, outside = torch.nonzero(near).squeeze(1), torch.nonzero(~near).squeeze(1)
        r = torch.sqrt(r2.index_select(0, inside)).clamp_min(1e-12 * h)
        self.rigid, self.f_ref = c.index_select(0, inside), kernel.dwdr(r, h) / r  # positions in the list
        self.beyond = c.index_select(0, outside)  # rigid pairs outside the support: never evaluated while rigid
        self.G = None
        self.n_static = self.n_dynamic = 0

    def same_table(self, rows: torch.Tensor, nb: torch.Tensor) -> bool:
        return nb is self.table and rows.shape == self.rows.shape and bool(torch.equal(rows, self.rows))

    def select(self, steady: torch.Tensor):
        """The split for the current phases: rigid pairs with both particles still steady
        -> the matrix; every other pair (rigid ones beyond the support excepted, while both
        stay steady) -> evaluated every step."""
        keep = steady.index_select(0, self.i.index_select(0, self.rigid)) & steady.index_select(
            0, self.j.index_select(0, self.rigid))
        self.s = torch.nonzero(keep).squeeze(1)  # positions in self.rigid
        skip = torch.zeros(self.i.numel(), dtype=torch.bool, device=self.i.device)
        skip.index_fill_(0, self.rigid.index_select(0, self.s), True)
        far = self.beyond
        if far.numel():
            still = steady.index_select(0, self.i.index_select(0, far)) & steady.index_select(0, self.j.index_select(0, far))
            skip.index_fill_(0, far[still], True)
        m = torch.nonzero(~skip).squeeze(1)
        self.d_row, self.d_i, self.d_j = self.ri.index_select(0, m), self.i.index_select(0, m), self.j.index_select(0, m)
        self.n_static, self.n_dynamic = int(self.s.numel()), int(m.numel())
        self.G = None
        self.built = False

    def build(self, k, zeta):
        """G: row r holds g_ij at column j for the rigid pairs of row r."""
        p = self.rigid.index_select(0, self.s)
        i, j = self.i.index_select(0, p), self.j.index_select(0, p)
        g = material_factor(k.index_select(0, i), k.index_select(0, j), zeta.index_select(0, i),
                            zeta.index_select(0, j)) * self.f_ref.index_select(0, self.s)
        R = self.rows.numel()
        crow = torch.zeros(R + 1, dtype=torch.long, device=g.device)
        crow[1:] = torch.cumsum(torch.bincount(self.ri.index_select(0, p), minlength=R), 0)
        with warnings.catch_warnings():  # "sparse CSR support is in beta": mv on CSR is what we use of it
            warnings.simplefilter("ignore", UserWarning)
            self.G = torch.sparse_csr_tensor(crow, j, g, size=(R, k.shape[0]), check_invariants=False)
        self.built = True
    def apply(self, x, T, k, V, zeta) -> torch.Tensor:
        """(div k grad T) on ``rows``: the matrix product plus the moving pairs' sum."""
        if self.n_static:
            u = self.G @ torch.stack([V, V * T], 1)
            q = T.index_select(0, self.rows) * u[:, 0] - u[:, 1]
        else:
            q = torch.zeros(self.rows.numel(), dtype=T.dtype, device=T.device)
        if self.n_dynamic:
            i, j = self.d_i, self.d_j
            g = pair_factor(x.index_select(0, i), x.index_select(0, j), k.index_select(0, i), k.index_select(0, j),
                            zeta.index_select(0, i), zeta.index_select(0, j), self.kernel, self.h, self.domain)
            q = q.index_add(0, self.d_row, g * V.index_select(0, j) * (T.index_select(0, i) - T.index_select(0, j)))
        return q

    @property
    def pairs(self) -> int:
        return self.n_static + self.n_dynamic
