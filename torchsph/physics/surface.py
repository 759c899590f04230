"""Free-surface forces (SPEC 2.4-2.6, 3.9-3.12): CSF surface tension, Marangoni, recoil.

All three act only on fluid particles on the free surface, through the CSF surface delta
|grad c| of the colour gradient (3.9) (c = 1 in all material, so a melt/solid contact is
not a surface):

- surface area a particle stands for, ``A_i = V_i |grad c_i| / D``, where D is the sum of
  V |grad c| over the layers of a flat lattice surface per unit area (computed once), so
  that a flat surface gets exactly its area;
- outward unit normal ``n_i = -grad c_i / |grad c_i|`` (grad c points into the material);
- curvature ``kappa_i = div n`` (the fix of the garbled 3.10; > 0 on a convex drop), the SPH
  divergence over surface neighbours with the first-order kernel-gradient correction
  (``grad n = G B^-1``, B = -sum_j V_j x_ij x_ij dW/dr / r): exact for a linear field even
  in the one-sided neighbourhood of a surface band, where the plain sum is not;
- surface tension (2.4/2.5): force ``-alpha(T) kappa n A`` (towards the centre of
  curvature: the pressure jump alpha kappa), alpha(T) = alpha0 + alpha' (T - T0), kept >= 0;
- Marangoni (3.11): ``alpha' (I - n n) grad T A`` with the corrected gradient of T;
- recoil (2.6/3.12): ``-p_v(T) n A`` (pushes the melt in, along -n).

The time-step limit of the capillary waves 0.25 sqrt(rho_min h^3 / (2 pi alpha_max)) (3.16,
fixed) is :meth:`SurfaceForces.limit`; recoil and Marangoni enter the acceleration limit.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import torch

from torchsph.core.kernels import Kernel
from torchsph.core.neighbors import Domain
from torchsph.core.state import Array, Holder, ParticleState, Phase
from torchsph.physics.fluid import dot, embed, gather_nb, outer_sum, pair_dwdr_r, pair_geometry, pair_sum, tiny
from torchsph.physics.free_surface import ColourGradient, SelectionArrays
from torchsph.physics.losses import flat_surface_layers
from torchsph.physics.wetting import ContactAngle


@dataclass
class SurfaceParams:
    tension: float = 0.0  # alpha0, N/m at T0
    dtension_dT: float = 0.0  # alpha' = d sigma / dT, N/(m K)
    reference_temperature: float = 300.0  # T0 of alpha(T), K
    marangoni: bool = True  # the tangential (I - n n) grad alpha force (when alpha' != 0)
    recoil: bool = False  # recoil pressure p_v(T) (needs a vapour-pressure law)
    threshold: float = 0.05  # |grad c| h above which a particle belongs to the surface
    zero_net_force: bool = False  # remove the discrete forces' net resultant (a free body only)
    contact_angle: float | None = None  # theta_eq between melt and solid, deg (None: no wetting model)
    wetting: bool = True  # False: contact_angle ignored
    band_curvature: str = "clear"  # the contact band's curvature: ("clear") of the surface particles beside
    # it with no solid in their support, or ("beside") of all of them


def gradient_moments(x, f, w, m, rho, rows, nb, kernel: Kernel, h: float, domain: Domain):
    """Pair sums of the corrected gradient (see :func:`corrected_gradient_pairs`): the
    moment matrix B_i = sum_j V_j w_j (x_j - x_i) (x) grad_i W_ij (R, d, d) and
    G_i = sum_j V_j w_j (f_j - f_i) (x) grad_i W_ij ((R, d) or (R, d, d))."""
    dx, r = pair_geometry(x, rows, nb, domain, h)
    dWr = pair_dwdr_r(r, kernel, h)
    Vw = gather_nb(m, nb) / gather_nb(rho, nb) * gather_nb(w, nb) * dWr  # (R, k)
    gW = Vw.unsqueeze(-1) * dx  # V_j w_j grad_i W_ij
    B = -outer_sum(dx, gW)  # (x_j - x_i) (x) grad W
    df = gather_nb(f, nb) - f.index_select(0, rows).unsqueeze(1)
    if f.dim() == 1:
        return B, pair_sum(df, gW)
    return B, outer_sum(df, gW)


def solve_gradient(B: torch.Tensor, G: torch.Tensor) -> torch.Tensor:
    """grad = G B^-1 (batched), with B regularised by 1e-6 tr(B) I so that a degenerate
    neighbourhood stays invertible."""
    d = B.shape[-1]
    eye = torch.eye(d, dtype=B.dtype, device=B.device)
    tr = torch.diagonal(B, dim1=-2, dim2=-1).sum(-1).clamp_min(1e-30)
    Bt = (B + (1e-6 * tr).view(-1, 1, 1) * eye).transpose(-1, -2)
    if G.dim() == 2:
        return torch.linalg.solve(Bt, G.unsqueeze(-1)).squeeze(-1)
    # grad = G B^-1  <=>  B^T grad^T = G^T
    return torch.linalg.solve(Bt, G.transpose(-1, -2)).transpose(-1, -2)


def corrected_gradient_pairs(x, f, w, m, rho, rows, nb, kernel: Kernel, h: float, domain: Domain):
    """Corrected SPH gradient of the field ``f`` ((N,) or (N, d)) at ``rows``, over the
    neighbours with weight ``w`` (N,) (0 = excluded):
    grad f_i = [sum_j V_j w_j (f_j - f_i) (x) grad_i W_ij] B_i^-1,
    B_i = sum_j V_j w_j (x_j - x_i) (x) grad_i W_ij, exact for linear f.
    Returns (rows, d) for a scalar field, (rows, d, d) (grad[a, b] = d f_a / d x_b) for a vector."""
    return solve_gradient(*gradient_moments(x, f, w, m, rho, rows, nb, kernel, h, domain))


def smoothed_pairs(x, f, w, m, rho, rows, nb, mask, kernel: Kernel, h: float, domain: Domain):
    """Kernel (Shepard) average of ``f`` over the neighbours with weight ``w``, self included
    (``mask`` marks the real neighbours of the padded table)."""
    dx, r = pair_geometry(x, rows, nb, domain, h)
    if nb.numel() < m.shape[0]:  # few rows (a small pool in a large scene): V w on their entries only
        Vw_nb = gather_nb(m, nb) / gather_nb(rho, nb) * gather_nb(w, nb)
        Vw_r = m.index_select(0, rows) / rho.index_select(0, rows) * w.index_select(0, rows)
    else:  # (the same values, per particle first)
        Vw = m / rho * w
        Vw_nb, Vw_r = gather_nb(Vw, nb), Vw.index_select(0, rows)
    Wk = kernel.w(r, h) * Vw_nb * mask
    self_w = Vw_r * kernel.w(torch.zeros((), dtype=x.dtype), h)
    num = pair_sum(Wk, gather_nb(f, nb)) + f.index_select(0, rows) * self_w.unsqueeze(-1)
    return num / (Wk.sum(1) + self_w).clamp_min(tiny(Wk)).unsqueeze(-1)


class SurfaceForces(Holder):
    """CSF surface tension, Marangoni and recoil forces on the free-surface fluid particles."""

    array_prefix = "sf"
    ARRAYS = {"normal": Array("outward surface normal of the last evaluation (0 off the surface)",
                              output="surface_normal", lazy=True, vector=True),
              "kappa": Array("curvature of the last evaluation (0 off the surface)", "1/m", output="curvature",
                             lazy=True)}

    def __init__(self, params: SurfaceParams, kernel: Kernel, h: float, domain: Domain,
                 h_over_dx: float, vapour_pressure=None, compile: bool = False,
                 colour: ColourGradient | None = None):
        if params.recoil and vapour_pressure is None:
            raise ValueError("SurfaceForces: recoil needs a vapour-pressure law")
        self.prm = params
        self.kernel = kernel
        self.h = h
        self.domain = domain
        self.vapour_pressure = vapour_pressure
        # a sum over the particles owned, over all processes (a decomposed run's is set by the step)
        self.sum_owned = lambda rows, values: values.sum(0)
        layers = flat_surface_layers(kernel, h_over_dx)
        self.delta_norm = sum(w for _, w in layers)
        # |grad c|-weighted mean depth of the surface band below the surface (m): the band's
        # curvature 1/(R - s) is turned into the surface's 1/R (kappa / (1 + s kappa / (d - 1)))
        self.band_depth = sum(z * w for z, w in layers) / self.delta_norm * (h / h_over_dx)
        self.normal = None  # outward normal (N, d) of the last evaluation, 0 off the surface
        self.kappa = None  # curvature (N,) of the last evaluation, 0 off the surface
        self.n_surface = 0
        # the colour gradient, shared with the surface losses when both exist (one per step)
        self.colour = colour if colour is not None else ColourGradient(kernel, h, domain, params.threshold, compile)
        self.bufs = SelectionArrays()  # the per-particle fields of an evaluation (see accelerations)
        self.wetting = None if params.contact_angle is None or not params.wetting else ContactAngle(
            params.contact_angle, kernel, h, domain, params.threshold, clear=params.band_curvature == "clear")
        self._fns = {"moments": gradient_moments, "smooth": smoothed_pairs}
        if compile:  # the pair sums fuse; the batched d x d solves stay eager
            self._fns = {k: torch.compile(f, dynamic=True) for k, f in self._fns.items()}

    @property
    def marangoni_on(self) -> bool:
        return self.prm.marangoni and self.prm.dtension_dT != 0.0

    def select_pairs(self, state: ParticleState, table):
        """The fluid particles' rows of the neighbour table (a :class:`~torchsph.core.neighbors.NeighbourTable`)."""
        fluid = state.phase == Phase.FLUID
        self.rows_f = torch.nonzero(fluid).squeeze(1)
        self.nb_f, self.mask_f = table.gather(self.rows_f, within=True, trim=True)
        self.fluid = fluid
        self.colour.want("surface", self.rows_f, table, self.nb_f)
        self.bufs.reset()  # the evaluation's whole-length arrays, made at its first evaluation
        if self.wetting is not None:
            self.wetting.select(state, self.nb_f, self.mask_f, table)

    def share_pairs(self, rows: torch.Tensor, nb: torch.Tensor, table):
        """At a selection: where the momentum's rows ``rows`` (and their table ``nb``) are the
        surface's (every fluid row: one process), read those same tensors, so that an
        evaluation makes their pair geometry once (:class:`torchsph.physics.fluid.GeometryMemo`);
        a decomposition's momentum rows (its own and the near ghosts) are not, and stay apart."""
        if rows.shape == self.rows_f.shape and nb.shape == self.nb_f.shape and torch.equal(rows, self.rows_f):
            self.rows_f, self.nb_f = rows, nb
            self.colour.want("surface", rows, table, nb)

    def tension(self, T: torch.Tensor) -> torch.Tensor:
        prm = self.prm
        return (prm.tension + prm.dtension_dT * (T - prm.reference_temperature)).clamp_min(0.0)

    def accelerations(self, state: ParticleState, terms: bool = False, rows_only: bool = False):
        """Accelerations (N, d) from the surface forces at ``state``; with ``terms`` also a
        dict by force; with ``rows_only`` (rows, accelerations of those rows) instead (the
        others are zero). Sets ``normal``, ``kappa`` and ``n_surface``."""
        prm, n, d = self.prm, state.n, state.dim
        x, m, rho = state.x, state.m, state.rho
        g = self.colour.of(state, "surface")
        gn = g.norm(dim=-1)
        # every fluid row is evaluated and the ones off the surface masked out: fixed shapes,
        # no read of the host (the surface rows' values are those of a surface-only sum)
        on = gn * self.h > self.colour.threshold
        rows, nb, onv = self.rows_f, self.nb_f, on.unsqueeze(-1)
        onf = onv.to(rho.dtype)  # (a product with it: every factor it masks is finite)
        self.n_surface = on.sum()  # (a tensor: the plan statistics sum it without a read)
        # The fields the pair sums read by particle (normals, flags, curvature) are
        # whole-length arrays that only the rows ever write: made zero once per selection
        # (the rows are fixed until the next) and written in place at each evaluation, not
        # made and zeroed at every step (at full size, passes over every particle).
        buf = self.bufs
        self.normal, self.kappa = buf.zeros("normal", x), buf.zeros("kappa", rho)  # (zero off the surface rows)
        parts = {}
        gns = torch.where(on, gn, torch.ones_like(gn))
        n_out = -g / gns.unsqueeze(-1) * onf
        band = None
        if self.wetting is not None:  # the contact band: the melt's surface next to the solid
            band = self.wetting.contact_band(state, rows, g, on)
        self.normal.index_copy_(0, rows, n_out)
        flag = buf.whole("flag", rho, rows, on.to(rho.dtype))  # surface fluid particles
        # force per unit mass = (force per area) x A_i / m_i = (force per area) |grad c| / (rho D)
        per_area = (gns / (rho.index_select(0, rows) * self.delta_norm)).unsqueeze(-1) * onf
        a = torch.zeros_like(n_out)
        if prm.tension > 0 or prm.dtension_dT != 0.0:
            # kernel-smoothed normals: on a lattice staircase the raw ones turn at the
            # corners and overstate kappa there by 30-90 % (10-40 % once smoothed)
            flag_s = flag
            if band is not None:  # the band's normals blend in the solid's: not smoothed into
                # the surface beside it, whose normals read the contact angle
                flag_s = buf.whole("flag_s", rho, rows, (on & ~band).to(rho.dtype))
            nsm = self._fns["smooth"](x, self.normal, flag_s, m, rho, rows, nb, self.mask_f.to(rho.dtype),
                                      self.kernel, self.h, self.domain)
            nsm = nsm / nsm.norm(dim=-1, keepdim=True).clamp_min(1e-30) * onf
            nfield = buf.whole("nfield", x, rows, nsm)  # (read at surface rows only)
            gradn = solve_gradient(*self._fns["moments"](x, nfield, flag, m, rho, rows, nb, self.kernel,
                                                         self.h, self.domain))
            kappa = torch.diagonal(gradn, dim1=-2, dim2=-1).sum(-1)
            kappa = kappa / (1.0 + self.band_depth * kappa / (d - 1)).clamp_min(0.5)
            kappa = torch.where(on, kappa, torch.zeros_like(kappa))
            self.kappa.index_copy_(0, rows, kappa)
            alpha = self.tension(state.T.index_select(0, rows))
            n_f = n_out
            if band is not None:
                surf = buf.whole("surf", self.fluid, rows, on)
                F = self.wetting.force(state, rows, nfield, self.kappa, surf, alpha)
                parts["contact_line"] = F / m.index_select(0, rows).unsqueeze(-1)
                a = a + parts["contact_line"]
                # the band's own normals blend in the solid's, and its curvature is no
                # surface's: it carries the tension of the surface beside it (the Laplace
                # balance down to the solid), with that surface's curvature and normal
                kappa = torch.where(band, self.wetting.k_band, kappa)
                n_f = torch.where(band.unsqueeze(-1), self.wetting.n_band, n_out)
                self.kappa.index_copy_(0, rows, kappa)
            parts["surface_tension"] = -(alpha * kappa).unsqueeze(-1) * n_f * per_area
            a = a + parts["surface_tension"]
        if self.marangoni_on:
            if getattr(self, "_material", (None,))[0] is not state.phase:  # once per phase array
                self._material = (state.phase, (state.phase != Phase.WALL).to(rho.dtype))
            material = self._material[1]
            gT = solve_gradient(*self._fns["moments"](x, state.T, material, m, rho, rows, nb,
                                                      self.kernel, self.h, self.domain))
            gT_t = gT - dot(gT, n_out).unsqueeze(-1) * n_out
            T = state.T.index_select(0, rows)
            live = (self.tension(T) > 0).to(rho.dtype).unsqueeze(-1)  # alpha clamped at 0: no gradient
            parts["marangoni"] = torch.where(onv, prm.dtension_dT * gT_t * per_area * live, torch.zeros_like(gT_t))
            a = a + parts["marangoni"]
        if prm.recoil:
            pv = self.vapour_pressure(state.T.index_select(0, rows))
            parts["recoil"] = -pv.unsqueeze(-1) * n_out * per_area
            a = a + parts["recoil"]
        if prm.zero_net_force:
            # on a closed surface the continuum forces (tension with alpha(T) and Marangoni)
            # have no resultant; the discrete ones keep a few per cent of the tangential total,
            # which would accelerate a free drop as a whole: remove it as a uniform traction
            # (over the particles of every process: a decomposed run's ghosts are not counted)
            mr = m.index_select(0, rows).unsqueeze(-1)
            F = self.sum_owned(rows, mr * a)
            parts["zero_net_force"] = -(F / self.sum_owned(rows, mr * per_area).clamp_min(tiny(F))) * per_area
            a = a + parts["zero_net_force"]
        if rows_only:
            return rows, a
        out = embed(rows, a, n)
        if not terms:
            return out
        return out, {k: embed(rows, v, n) for k, v in parts.items()}

    def limit(self, state: ParticleState):
        """Capillary time-step limit 0.25 sqrt(rho_min h^3 / (2 pi alpha_max)) (3.16, fixed),
        a 0-d float64 tensor (read with the other limits at once), or inf without fluid."""
        if self.rows_f.numel() == 0:
            return math.inf
        T = state.T.index_select(0, self.rows_f)
        amax = self.tension(T).max().double()
        rho_min = state.rho.index_select(0, self.rows_f).min().double()
        lim = 0.25 * torch.sqrt(rho_min * self.h**3 / (2.0 * math.pi * amax))
        return torch.where(amax > 0, lim, torch.full_like(lim, math.inf))

    def project_shift(self, shift: torch.Tensor, rows: torch.Tensor) -> torch.Tensor:
        """Particle shifting on the free surface only along it: (I - n n) dr (Lind et al. 2012),
        so that shifting does not push surface particles out of the fluid (``shift``: of the
        particles ``rows``)."""
        if self.normal is None:
            return shift
        nrm = self.normal.index_select(0, rows)
        return shift - dot(shift, nrm).unsqueeze(-1) * nrm


__all__ = ["SurfaceParams", "SurfaceForces", "corrected_gradient_pairs"]
