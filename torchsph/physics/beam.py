"""Directional Gaussian surface heat sources (2.7), with shadowing, in 3-D.

A beam of power Q0, efficiency eta0 and 1/e^2 radius r travels along the unit vector
e_src through an aim point (which may move). Its intensity per unit area normal to the
beam is q(a, b) = eta0 2 Q0 / (pi r^2) exp(-2 (a^2 + b^2) / r^2), with (a, b) the
coordinates in the plane normal to e_src. On a surface with normal n the flux per unit
surface area is q <-n . e_src>, so a surface patch absorbs q times its area projected
onto the beam plane; the <-n . e_src> factor of (2.7) is that projection.

Discretely the beam plane is cut into square bins of the particle spacing; in each bin
the first material particle the beam meets (smallest depth along e_src; ties broken by
index) absorbs q times the bin area, and every particle behind it is in its shadow (the
intensity is taken at the bin centre). The absorbed power is
then the midpoint quadrature of the Gaussian
over the part of the beam that hits material: eta0 Q0 on a plate that covers the spot,
at any tilt. No surface normal is needed, and no loop runs over particles or bins.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field

import torch


@dataclass
class Beam:
    power: float  # W
    efficiency: float  # absorbed fraction eta0
    radius: float  # 1/e^2 radius, m
    direction: tuple  # propagation direction e_src (normalised here)
    aim: tuple  # a point on the beam axis at t = 0, m
    velocity: tuple = field(default_factory=lambda: (0.0, 0.0, 0.0))  # motion of the aim point
    _frames: dict = field(default_factory=dict, repr=False, compare=False)  # device constants

    def __post_init__(self):
        e = [float(c) for c in self.direction]
        n = math.sqrt(sum(c * c for c in e))
        if len(e) != 3 or n == 0:
            raise ValueError("Beam.direction must be a non-zero 3-vector")
        self.direction = tuple(c / n for c in e)

    def basis(self):
        """Two unit vectors spanning the plane normal to the beam."""
        e = self.direction
        ref = (1.0, 0.0, 0.0) if abs(e[0]) < 0.9 else (0.0, 1.0, 0.0)
        u = (e[1] * ref[2] - e[2] * ref[1], e[2] * ref[0] - e[0] * ref[2], e[0] * ref[1] - e[1] * ref[0])
        nu = math.sqrt(sum(c * c for c in u))
        u = tuple(c / nu for c in u)
        w = (e[1] * u[2] - e[2] * u[1], e[2] * u[0] - e[0] * u[2], e[0] * u[1] - e[1] * u[0])
        return u, w

    def constants(self, dtype, device):
        """(e, u, w, aim at t = 0, aim velocity) as tensors on ``device``, made once."""
        key = (dtype, str(device))
        if key not in self._frames:
            self._frames[key] = tuple(torch.tensor(v, dtype=dtype, device=device) for v in
                                      (self.direction, *self.basis(), self.aim, self.velocity))
        return self._frames[key]


def intensity(q0, inv_r2, a, b):
    """The Gaussian's intensity q0 exp(-2 (a^2 + b^2) / r^2) normal to the beam (``inv_r2`` = 2 / r^2)."""
    return q0 * torch.exp(-(a * a + b * b) * inv_r2)


def beam_frame(x: torch.Tensor, beam: Beam, t: float):
    """(depth along the beam, and the two coordinates across it) of each particle at time t."""
    e, u, w, aim0, vel = beam.constants(x.dtype, x.device)
    rel = x - (aim0 + t * vel)
    a, b = rel @ u, rel @ w
    return rel @ e, a, b


def in_beam(x: torch.Tensor, beam: Beam, t: float, cutoff: float = 3.0) -> torch.Tensor:
    """Mask of the particles inside the traced cylinder (radius ``cutoff`` r) of a beam."""
    _, a, b = beam_frame(x, beam, t)
    return a * a + b * b < (cutoff * beam.radius) ** 2


def beam_power(x: torch.Tensor, material: torch.Tensor, beam: Beam, t: float, dx: float,
               cutoff: float = 3.0, ids: torch.Tensor | None = None) -> torch.Tensor:
    """Power (W) each particle absorbs from ``beam`` at time t; ``material`` marks the
    particles that can absorb or shadow (all but, e.g., vapour or ghost particles).
    Only the disc of radius ``cutoff`` r around the axis is traced (the Gaussian carries
    1 - exp(-2 cutoff^2) of the power inside it: 1.5e-8 for 3). Ties (equal depth in a bin,
    equal distance from the axis) go to the smallest ``ids`` (default: the row index), so
    a decomposed run that gathers the candidates in id order shadows as one process does."""
    if x.shape[1] != 3:
        raise ValueError("beams need a 3-D scene")
    plan = BeamPlan([beam], [None], x.shape[0], x.dtype, x.device, dx, cutoff)
    return plan.trace(x, t, material, ids)


class BeamPlan:
    """Several beams traced together, each over its own rows, in one set of operations
    (a loop over beams cost ~60 small operations per beam and step). Made once per pair
    selection (the rows fixed until the next): ``subsets`` per beam, the rows it traces
    (positions in the ``n`` rows traced; None: all of them); ``rows``: those rows' particles
    (then :meth:`trace` reads the positions of every particle). The rows of all beams are
    laid one after another (a row a beam can reach appears once per such beam), each beam
    on its own grid of bins; the constants of each entry's beam are gathered once here."""

    def __init__(self, beams, subsets, n: int, dtype, device, dx: float, cutoff: float = 3.0,
                 rows: torch.Tensor | None = None):
        parts = [torch.arange(n, device=device) if s is None else s for s in subsets]
        self.n, self.dx = n, dx
        self.idx = torch.cat(parts) if parts else torch.zeros(0, dtype=torch.long, device=device)
        # the particles traced: positions in ``x`` (with ``rows``, ``x`` holds every particle
        # and only the traced rows are gathered; alone and over all rows, none is)
        self.whole = rows is None and len(parts) == 1 and subsets[0] is None
        self.src = self.idx if rows is None else rows.index_select(0, self.idx)
        sizes = torch.tensor([p.numel() for p in parts], device=device)
        self.nseg = len(parts)
        self.seg = torch.repeat_interleave(torch.arange(self.nseg, device=device), sizes)
        consts = [b.constants(dtype, device) for b in beams]
        # each beam's frame (e, u, w) as the columns of a 3 x 3, its aim and the aim's velocity;
        # the entries of beam k are the rows spans[k] of the plan (one product each)
        self.frames = [torch.stack(c[:3], 1) for c in consts]
        self.aims = [(c[3], c[4] if any(b.velocity) else None) for c, b in zip(consts, beams)]
        ends = [0]
        for p in parts:
            ends.append(ends[-1] + p.numel())
        self.spans = [(ends[k], ends[k + 1] - ends[k]) for k in range(len(parts))]
        radius = torch.tensor([b.radius for b in beams], dtype=dtype, device=device)
        q0 = torch.tensor([b.efficiency * 2.0 * b.power / (math.pi * b.radius**2) for b in beams],
                          dtype=dtype, device=device)
        self.reach2 = ((cutoff * radius) ** 2).index_select(0, self.seg)
        self.q0_beam, self.inv_r2_beam = q0, 2.0 / radius**2
        self.inv_r2 = self.inv_r2_beam.index_select(0, self.seg)
        self.q0 = q0.index_select(0, self.seg)
        # bins of side dx around the candidate nearest each axis: (2M + 1)^2 per beam, plus
        # one per beam for the rows that are no candidates (nothing is taken from it)
        self.M = max((int(math.ceil(2.0 * cutoff * b.radius / dx)) + 1 for b in beams), default=1)
        side = 2 * self.M + 1
        self.side, self.nbin = side, side * side
        self.base = self.seg * (self.nbin + 1)

    def trace(self, x: torch.Tensor, t, material: torch.Tensor | None = None,
              ids: torch.Tensor | None = None) -> torch.Tensor:
        """Power (W) per plan entry; ``x``: the positions of the ``n`` rows traced (with the
        plan's ``rows``: of every particle); ``material``, ``ids``: per row of ``x``.
        Bins of side dx centred on the candidate nearest the axis: on a lattice seen along
        an axis every column then sits at a bin centre (bins with edges on the columns split
        them by round-off, leaving empty bins whose power nobody absorbed: -51 % was seen).
        Fixed shapes, no read of the host."""
        dev, dt, dx, M, side = x.device, x.dtype, self.dx, self.M, self.side
        if not self.spans:
            return x.new_zeros(0)
        xr = x if self.whole else x.index_select(0, self.src)
        # (depth, a, b) in each beam's frame: (x - aim) F = x F - aim F, one product per beam
        # (per entry frames in a batched or broadcast product were 2-5x slower)
        parts = []
        for (s, m), F, (aim, vel) in zip(self.spans, self.frames, self.aims):
            c = (aim if vel is None else aim + t * vel) @ F
            parts.append(torch.addmm(-c, xr.narrow(0, s, m), F))
        depth, a, b = (torch.cat(parts) if len(parts) > 1 else parts[0]).unbind(-1)
        rho2 = a * a + b * b
        cand = rho2 < self.reach2
        if material is not None:
            cand = cand & (material if self.whole else material.index_select(0, self.src))
        inf = torch.full_like(rho2, math.inf)
        big = torch.iinfo(torch.long).max
        nseg, seg = self.nseg, self.seg
        pos = torch.arange(rho2.numel(), device=dev)
        # each beam's candidate nearest its axis (the first such row on a tie)
        near = torch.full((nseg,), math.inf, dtype=dt, device=dev).scatter_reduce(0, seg, torch.where(cand, rho2, inf), "amin")
        at_min = cand & (rho2 == near.index_select(0, seg))
        k0 = torch.full((nseg,), big, dtype=torch.long, device=dev).scatter_reduce(
            0, seg, torch.where(at_min, pos, torch.full_like(pos, big)), "amin").clamp_max(max(rho2.numel() - 1, 0))
        a0_beam, b0_beam = a.index_select(0, k0), b.index_select(0, k0)  # each beam's bin centre (0, 0)
        a0, b0 = a0_beam.index_select(0, seg), b0_beam.index_select(0, seg)
        ia = torch.floor((a - a0) / dx + 0.5).long()
        ib = torch.floor((b - b0) / dx + 0.5).long()
        key = self.base + torch.where(cand, (ia + M).clamp(0, side - 1) * side + (ib + M).clamp(0, side - 1),
                                      torch.full_like(ia, self.nbin))
        nkey = nseg * (self.nbin + 1)
        dmin = torch.full((nkey,), math.inf, dtype=dt, device=dev).scatter_reduce(0, key, torch.where(cand, depth, inf), "amin")
        front = cand & (depth == dmin.index_select(0, key))
        key_i = pos if ids is None else (ids if self.whole else ids.index_select(0, self.src))
        first = torch.full((nkey,), big, dtype=torch.long, device=dev).scatter_reduce(
            0, key, torch.where(front, key_i, torch.full_like(key_i, big)), "amin")
        lit = front & (key_i == first.index_select(0, key))
        # midpoint rule: the intensity at the bin centre times the bin area (sampling at the
        # hit particle instead is biased where the lattice aliases with the bins: +3.4 % seen)
        ac = a0 + ia.to(dt) * dx
        bc = b0 + ib.to(dt) * dx
        q = intensity(self.q0, self.inv_r2, ac, bc)
        held = self.holes(dmin, a0_beam, b0_beam)  # the power of the empty bins between lit ones, per bin
        return torch.where(lit, q * (dx * dx) + held.index_select(0, key), torch.zeros_like(q))

    def holes(self, dmin: torch.Tensor, a0: torch.Tensor, b0: torch.Tensor) -> torch.Tensor:
        """Per bin key: the power of the empty bins next to it that lie between two lit bins
        (along a, along b or along a diagonal), shared equally among those lit neighbours.
        Bodies whose lattices are offset from each other (a wire over a substrate) put the
        columns of one at the bin edges of the other, where round-off sends a column to either
        bin: one bin gets two, its neighbour none, and that bin's power was lost (-4 to -15 % of
        a beam in the deposition scene at dx = 0.2 mm). Such a hole has lit bins on both sides
        along the axis its columns were split on (two holes cannot be adjacent there; where
        both axes split, a hole at a crossing has them along the diagonals), while a bin beyond
        a silhouette's edge has not. The hole's power is its midpoint value, as a lit bin's.
        ``a0``, ``b0``: each beam's bin centre (0, 0) in its frame (nseg,)."""
        nseg, M, side, dx = self.nseg, self.M, self.side, self.dx
        lit = torch.isfinite(dmin.view(nseg, self.nbin + 1)[:, : self.nbin]).view(nseg, side, side)
        pad = torch.nn.functional.pad(lit, (1, 1, 1, 1))
        # the neighbour pairs (offset of one member; the other is opposite): a, b, the diagonals
        steps = ((1, 0), (0, 1), (1, 1), (1, -1))
        at = lambda p, da, db: p[:, 1 + da: 1 + da + side, 1 + db: 1 + db + side]  # noqa: E731
        pairs = [at(pad, da, db) & at(pad, -da, -db) for da, db in steps]
        hole = ~lit & (pairs[0] | pairs[1] | pairs[2] | pairs[3])
        i = torch.arange(-M, M + 1, dtype=dmin.dtype, device=dmin.device) * dx
        ac, bc = a0.view(nseg, 1, 1) + i.view(1, side, 1), b0.view(nseg, 1, 1) + i.view(1, 1, side)
        q = intensity(self.q0_beam.view(nseg, 1, 1), self.inv_r2_beam.view(nseg, 1, 1), ac, bc)
        n_pairs = sum(p.to(q.dtype) for p in pairs)
        share = torch.where(hole, q * (dx * dx), torch.zeros_like(q)) / (2.0 * n_pairs).clamp_min(1.0)
        got = torch.zeros_like(q)
        for (da, db), p in zip(steps, pairs):  # each member of a qualifying pair takes a share
            sp = torch.nn.functional.pad(torch.where(p & hole, share, torch.zeros_like(share)), (1, 1, 1, 1))
            got = got + at(sp, -da, -db) + at(sp, da, db)
        return torch.nn.functional.pad(got.reshape(nseg, self.nbin), (0, 1)).reshape(-1)

    def power(self, x: torch.Tensor, t) -> torch.Tensor:
        """Power (W) each of the ``n`` rows absorbs from all beams (summed over beams in order)."""
        return torch.zeros(self.n, dtype=x.dtype, device=x.device).index_add_(0, self.idx, self.trace(x, t))


def reachable(beams, x: torch.Tensor, reach: float, cutoff: float = 3.0) -> list:
    """For each beam whose aim does not move: the rows of ``x`` within its traced cylinder
    (``cutoff`` r) widened by ``reach``; particles that move less than ``reach`` from ``x``
    cannot enter it from elsewhere. None for a moving beam (every row is traced)."""
    out = []
    for b in beams:
        if any(b.velocity):
            out.append(None)
            continue
        _, a, c = beam_frame(x, b, 0.0)
        out.append(torch.nonzero((a * a + c * c).sqrt() < cutoff * b.radius + reach * (1 + 1e-9) + 1e-12).squeeze(1))
    return out


def beams_power(beams, x: torch.Tensor, t: float, dx: float, subsets: list | None = None,
                rows: torch.Tensor | None = None, plan: "BeamPlan | None" = None) -> torch.Tensor:
    """Power (W) each row absorbs from all ``beams`` (all rows material); each beam traced
    only on its rows of ``subsets`` (:func:`reachable`; None: on all). The rows are those of
    ``x``, or with ``rows`` the particles ``rows`` of ``x`` (positions of every particle):
    then only the rows a beam traces are gathered (the full scene's 733 600 conducting rows
    made a 7 ms copy per step for the few thousand a beam can reach). ``plan``: the
    :class:`BeamPlan` of these beams, subsets and rows, where the caller keeps one."""
    n = x.shape[0] if rows is None else rows.numel()
    if plan is None:
        plan = BeamPlan(beams, [None] * len(beams) if subsets is None else subsets, n, x.dtype, x.device, dx, rows=rows)
    return plan.power(x, t)


def gaussian_fraction_in_strip(width: float, radius: float) -> float:
    """Fraction of a Gaussian beam (1/e^2 radius r) inside a strip |a| < width/2: the
    projection of a long cylinder of diameter ``width`` seen side-on."""
    return math.erf(width / (math.sqrt(2.0) * radius))
