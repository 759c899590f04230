"""Wetting: the equilibrium contact angle between the melt and the solid (SPEC 3b).

The model is a contact-line force (after Huber, Keller, Säckel, Hirschler, Kunz, Hassanizadeh
& Nieken 2016, J. Comput. Phys. 310): Young's unbalanced force, per unit length of contact
line,

    f = alpha (cos(theta_eq) - cos(theta)) t,

acts on the melt at the contact line, where theta is the angle at which the melt's surface
meets the solid there and t the unit vector in the solid's tangent plane that points out of
the melt. It vanishes when the melt meets the solid at theta_eq, whatever its discrete
magnitude, so the equilibrium angle does not hang on how the line's length is shared out.

- The contact band: the melt's surface particles (colour over all material, 3.9) with solid
  in their kernel support. There the colour's normal blends the melt's surface with the
  solid's and its curvature is no surface's: the band's CSF force takes the curvature and
  normal of the surface beside it (the Laplace balance carried down to the solid), and
  Young's force is added. (With no CSF force on the band the band bulged and the caps below
  90 deg settled 5-7 deg steep; with the band's own normals the contact foot broke up.)
- n_w, the solid's outward normal: minus the solid neighbours' part of the colour gradient;
  t: the melt-only colour gradient, reversed and projected on the solid's tangent plane.
- theta: from the kernel average of the smoothed surface normals of the surface particles
  beside the band (within a support, not in it; smoothed without the band's blended
  normals, which set the 30 deg cap 5 deg steep), carried down to the band particle's height
  with their curvature: cos(theta) = n . n_w - z kappa / (d - 1) for the average point
  beside, a height z above the band particle (exact on a circle or sphere). Without that, the
  angle would be read a few spacings up the surface, and a cap settle steeper than theta_eq
  by about z / R rad.
- The band's curvature (``surface.band_curvature``): by default (``"clear"``) the curvature of
  the surface particles beside the band that have no solid in their support (those just above
  the band's own layer; where there are none, all the beside particles'). With all the surface
  particles beside it (``"beside"``, the model before stop 51) a 3-D cap drawing in from 105 deg
  to 120 stopped at 107 deg (R/8) to 114 deg (R/16): near a steep foot those particles are the
  flank below the bulge, curved less than the cap, and the pressure, which balances the cap's
  curvature, pushed the foot out against Young's pull; with ``"clear"`` that cap reaches
  122-123 deg at R/8. Where the solid turns within the support (an edge: the spread of Gibbs's
  angles above :data:`EDGE_SPREAD`) all the beside particles' is taken: there the particles
  clear of the solid are the neck below a wire's edge, and with them a pendant drop fell whole,
  25 % light.
- Edges (Gibbs's criterion, Gibbs 1878; Oliver, Huh & Mason 1977): where the solid's
  surface turns within the support, e.g. a wire's end face meeting its side, the line's
  angle is measured against every outward normal of the solid's surface there (the solid's
  own colour gradient at its surface particles that face the melt particle), and the line
  holds, with no force, while theta_eq lies between those angles: at a 90 deg edge a drop
  stays put from theta_eq on the face to theta_eq + 90 deg. Outside that range the drive is
  the nearest angle's. On a flat face the normals agree and it is the plain force. (With
  the blended normal alone a drop under a wire crept round its edge and up its side, and a
  drop on a pillar ran over the pillar's edge.)
- Share of the line: in 2-D the band particles within one support share a contact point's
  force; in 3-D a chord of the line through the support sphere (pi/4 of its diameter on
  average). This sets only how fast the line moves, not where it stops.
- The band particle's force is spread over the melt within its support by kernel weight (on
  the band alone it tears those few particles off the melt), and its reaction is booked on
  the solid neighbours by kernel weight: the wetting force over melt and solid sums to zero
  (:attr:`ContactAngle.reaction`; a rigid solid does not move by it).

Without the model (no ``surface.contact_angle_deg``) c = 1 in melt and solid alike and a
melt/solid contact is no surface: a sessile drop then settles near 90 deg.
"""
from __future__ import annotations

import math

import torch

from torchsph.core.kernels import Kernel
from torchsph.core.neighbors import Domain
from torchsph.core.state import Phase
from torchsph.physics.fluid import dot, gather_nb, pair_geometry, pair_sum, tiny
from torchsph.physics.free_surface import SelectionArrays, colour_pair_weights

# the spread of cos(theta) over the solid's normals in a band particle's support above which the
# solid turns there (an edge) for band_curvature = "clear"
EDGE_SPREAD = 0.1


def unit(v: torch.Tensor) -> torch.Tensor:
    """v / |v| over the last axis (0 where v = 0)."""
    return v / torch.sqrt(dot(v, v)).clamp_min(tiny(v)).unsqueeze(-1)


class ContactAngle:
    """Young's force on the melt's contact band and its reaction on the solid (see the
    module's docstring)."""

    pin = True  # Gibbs's criterion at the solid's edges (False: the blended normal alone, for tests)

    def __init__(self, angle_deg: float, kernel: Kernel, h: float, domain: Domain, threshold: float,
                 clear: bool = False):
        """``clear``: the band's curvature from the surface particles beside it that have no solid
        in their support (else from all of them; see the module's docstring)."""
        self.cos = math.cos(math.radians(angle_deg))
        self.clear = clear
        self.kernel, self.h, self.domain, self.threshold = kernel, h, domain, threshold
        self.band = None  # (rows,) bool: the contact band among the melt rows at the last evaluation
        self.bufs = SelectionArrays()

    def select(self, state, nb: torch.Tensor, mask: torch.Tensor, table=None):
        """At a pair selection: the melt rows of the table ``nb`` (``mask``: its real entries)
        with solid (any non-fluid material) in it. Only they can meet solid within a kernel
        support before the next selection (the table reaches a skin further), so the band is
        sought among them alone: the work follows the melt beside the solid, not all melt."""
        solid = gather_nb(state.phase != Phase.FLUID, nb) & mask
        self.bufs.reset()
        self.sub = torch.nonzero(solid.any(1)).squeeze(1)  # (a selection may read the host)
        self.nb_c, self.mask_c = nb.index_select(0, self.sub), mask.index_select(0, self.sub).to(state.x.dtype)
        self.solid_nb = solid.index_select(0, self.sub).to(state.x.dtype)
        self.S = None
        if table is not None and self.pin:
            # the solid neighbours of the contact rows, and their rows of the table: their
            # surface normals are evaluated at every step from the state then (solid_normals)
            solid = self.solid_nb > 0
            self.S, inv = torch.unique(torch.where(solid, self.nb_c, -1), return_inverse=True)
            self.at_S = inv  # (R, k): each entry's place in S (S[0] = -1 where some entry is not solid)
            S = self.S.clamp_min(0)
            self.nbS, maskS = table.gather(S, trim=True)
            self.solS = (gather_nb(state.phase != Phase.FLUID, self.nbS) & maskS).to(state.x.dtype)
            self.rowS = table.has_row().index_select(0, S) & (self.S >= 0)

    def solid_normals(self, state):
        """The outward normals of the solid's surface particles among the contact rows' solid
        neighbours, per table entry: (R, k, d) and (R, k) bool (a surface normal is known:
        the solid neighbour has a row in the table and its solid-only colour gradient exceeds
        the surface threshold). The solid's colour is its own, c = 1 in the solid only; it is
        evaluated on this state (a function of the state alone: a restart or a decomposed run
        reads the same normals)."""
        S = self.S.clamp_min(0)
        dxp, r = pair_geometry(state.x, S, self.nbS, self.domain, self.h)
        w, _ = colour_pair_weights(state.m, state.rho, S, self.nbS, r, self.kernel, self.h)
        gs = pair_sum(w * self.solS, dxp)
        gn = torch.sqrt(dot(gs, gs))
        ok = (gn * self.h > self.threshold) & self.rowS
        ns = -gs / gn.clamp_min(tiny(gn)).unsqueeze(-1)
        return ns.index_select(0, self.at_S.reshape(-1)).reshape(*self.at_S.shape, state.dim), \
            ok.index_select(0, self.at_S.reshape(-1)).reshape(self.at_S.shape) & (self.solid_nb > 0)

    def contact_band(self, state, rows, g: torch.Tensor, on: torch.Tensor) -> torch.Tensor:
        """The melt rows ``rows`` in the contact band (R,) bool: surface particles (``on``)
        with solid in their support. Also keeps, for :meth:`force`, the solid's outward normal
        n_w and the unit vector t in the solid's tangent plane pointing out of the melt.
        ``g``: the rows' colour gradient over all material. (Evaluated on the rows with solid
        in their table, :meth:`select`.)"""
        sub, nb = self.sub, self.nb_c
        rows_c = rows.index_select(0, sub)
        # the solid neighbours' part of the colour gradient (points into the solid), and their
        # kernel weights V_j W_ij for the reaction; the pair geometry is kept for force()
        self.geom = pair_geometry(state.x, rows_c, nb, self.domain, self.h)
        dxp, r = self.geom
        w, Vj = colour_pair_weights(state.m, state.rho, rows_c, nb, r, self.kernel, self.h)
        gs = pair_sum(w * self.solid_nb, dxp)
        self.weights = Vj * self.kernel.w(r, self.h) * self.solid_nb
        gsn = torch.sqrt(dot(gs, gs))
        self.band_c = on.index_select(0, sub) & (gsn * self.h > self.threshold)
        if self.clear:  # the rows with solid inside their kernel support
            self.near_c = ((self.solid_nb > 0) & (r < self.kernel.radius(self.h))).any(1)
        self.n_w = -gs / gsn.clamp_min(tiny(gsn)).unsqueeze(-1)
        out = -(g.index_select(0, sub) - gs)  # the melt-only colour gradient, reversed: out of the melt
        self.t = unit(out - dot(out, self.n_w).unsqueeze(-1) * self.n_w)
        self.band = torch.zeros_like(on).index_copy_(0, sub, self.band_c)
        return self.band

    def force(self, state, rows, normals: torch.Tensor, kappa: torch.Tensor,
              surface: torch.Tensor, alpha: torch.Tensor) -> torch.Tensor:
        """Young's unbalanced force on the melt rows ``rows`` (R, d; zero off the band), in N
        (per unit depth in 2-D): alpha (cos theta_eq - cos theta) t, with theta the angle
        between the solid and the melt's surface beside the band (the kernel average of
        ``normals`` (N, d) over the surface particles, ``surface`` (N,) bool, that are not in
        the band), shared over the band particles of the contact line within a kernel
        support. ``alpha``: the rows' tension (R,). Also sets ``k_band`` and ``n_band`` (R,)."""
        sub, nb, mask, band = self.sub, self.nb_c, self.mask_c, self.band_c
        rows_c = rows.index_select(0, sub)
        dxp, r = self.geom  # (this state's: contact_band() came first)
        Wk = self.kernel.w(r, self.h) * mask
        band_full = self.bufs.whole("band", surface, rows, self.band)
        beside = (gather_nb(surface & ~band_full, nb)).to(Wk.dtype) * Wk
        bsum = beside.sum(1)
        seen = (bsum > 0) & band
        wsum = bsum.clamp_min(tiny(bsum))
        n_d = unit(pair_sum(beside, gather_nb(normals, nb)))
        # the angle at the band's height: the surface's normal turns by its curvature on the
        # way down (cos(theta) grows by z / R over a height z on a circle / sphere of radius
        # R: the meridian's curvature kappa / (d - 1)), z from the band particle up to the
        # average point beside it. (Carried further down to the solid's face, dx/2 below the
        # band's first layer, the 2-D caps of 90 and 120 deg settled 4.5 and 8.5 deg low.)
        up = -dot(dxp, self.n_w.unsqueeze(1))  # (x_j - x_i) . n_w
        z_d = (up * beside).sum(1) / wsum
        kappa_nb = gather_nb(kappa, nb)
        k_d = (kappa_nb * beside).sum(1) / wsum / (state.dim - 1)
        k_t = k_d  # the curvature the band's tension takes
        if self.clear:  # from the surface beside with no solid in its support, where there is some
            near = self.bufs.whole("near", surface, rows, torch.zeros_like(self.band).index_copy_(0, sub, self.near_c))
            far = gather_nb(surface & ~near, nb).to(Wk.dtype) * Wk
            fsum = far.sum(1)
            k_t = torch.where(fsum > 0, (kappa_nb * far).sum(1) / fsum.clamp_min(tiny(fsum)) / (state.dim - 1), k_d)
        cos_d = dot(n_d, self.n_w) - k_d * z_d
        if self.S is not None:
            ns_nb, ns_ok = self.solid_normals(state)
            # Gibbs's criterion: where the solid's surface turns within the support (an edge),
            # the line stays where theta_eq lies between the angles the melt's surface makes
            # with the solid's normals there; outside that range it is driven by the nearest
            cand = dot(n_d.unsqueeze(1), ns_nb) - (k_d * z_d).unsqueeze(1)
            # (a normal of the solid that faces away from the melt particle, e.g. the far
            # side of a thin plate, is no part of the surface the line sits on)
            facing = dot(dxp, ns_nb) > -0.5 * r
            use = ns_ok & (Wk > 0) & facing
            big = torch.finfo(cand.dtype).max
            c_lo = torch.where(use, cand, torch.full_like(cand, big)).amin(1)
            c_hi = torch.where(use, cand, torch.full_like(cand, -big)).amax(1)
            has = use.any(1)
            lo = torch.minimum(torch.where(has, c_lo, cos_d), cos_d)
            hi = torch.maximum(torch.where(has, c_hi, cos_d), cos_d)
            self.spread = torch.where(has, hi - lo, torch.zeros_like(lo))
            cos_d = torch.clamp(torch.full_like(cos_d, self.cos), lo, hi)
            if self.clear:  # at an edge (the solid's normals disagree) the band keeps the default's curvature
                k_t = torch.where(self.spread > EDGE_SPREAD, k_d, k_t)
        n_rows = rows.shape[0]
        # the surface's curvature and normal beside the band
        self.k_band = torch.zeros(n_rows, dtype=Wk.dtype, device=Wk.device).index_copy_(0, sub, k_t * (state.dim - 1))
        self.n_band = torch.zeros(n_rows, state.dim, dtype=Wk.dtype, device=Wk.device).index_copy_(
            0, sub, torch.where(band.unsqueeze(-1), n_d, torch.zeros_like(n_d)))
        # the band particles within a support: 2-D, one contact point's; 3-D, a chord of the
        # line through the support sphere (pi/4 of its diameter on average)
        count = 1.0 + (gather_nb(band_full, nb).to(Wk.dtype) * mask).sum(1)
        share = 1.0 / count if state.dim == 2 else (0.5 * math.pi * self.kernel.radius(self.h)) / count
        self.drive = torch.where(seen, self.cos - cos_d, torch.zeros_like(cos_d))  # (diagnosis, on the sub-rows)
        mag = alpha.index_select(0, sub) * (self.cos - cos_d) * share
        F = torch.where(seen.unsqueeze(-1), mag.unsqueeze(-1) * self.t, torch.zeros_like(self.t))
        self.book(state, F)
        # spread over the melt within the band particle's support (kernel weights, itself
        # included): a force on the few band particles alone tears them off the melt
        melt_nb = (1.0 - self.solid_nb) * Wk * (gather_nb(state.m, nb) / gather_nb(state.rho, nb))
        w_self = (state.m.index_select(0, rows_c) / state.rho.index_select(0, rows_c)) * self.kernel.w(
            torch.zeros((), dtype=Wk.dtype), self.h)
        norm = (melt_nb.sum(1) + w_self).unsqueeze(-1)
        out = self.bufs.accumulator("spread", state.x, nb, rows_c)
        out.index_add_(0, nb.reshape(-1), (melt_nb.unsqueeze(-1) * (F / norm).unsqueeze(1)).reshape(-1, state.dim))
        out.index_add_(0, rows_c, w_self.unsqueeze(-1) * F / norm)
        return out.index_select(0, rows)

    def book(self, state, force: torch.Tensor) -> torch.Tensor:
        """The reaction on the solid of ``force`` (on the sub-rows of :meth:`select`, in N;
        zero off the band): each band particle's force, reversed, shared over its solid
        neighbours by V_j W_ij; returns it per table entry (R, k, d) and keeps it for
        :attr:`reaction`."""
        wsum = self.weights.sum(1, keepdim=True)
        share = self.weights / wsum.clamp_min(tiny(wsum)) * self.band_c.to(force.dtype).unsqueeze(-1)
        pair = -share.unsqueeze(-1) * force.unsqueeze(1)  # (R, k, d)
        self._reaction = (state.x, self.nb_c.reshape(-1), pair.reshape(-1, state.dim))
        return pair

    _reaction = None  # (positions, entries, forces): the reaction, summed when read

    @property
    def reaction(self) -> torch.Tensor | None:
        """The reaction (N, d) on the solid at the last evaluation (summed per particle when
        read: the step itself does not use it; a rigid solid does not move by it)."""
        if self._reaction is None:
            return None
        x, idx, f = self._reaction
        return torch.zeros_like(x).index_add_(0, idx, f)


__all__ = ["ContactAngle"]
