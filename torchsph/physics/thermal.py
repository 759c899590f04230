"""Energy equation: Cleary-Monaghan heat conduction (3.13) with per-particle conductivity
and the effective heat capacity of melting (2.11).

rho c_eff dT/dt = div(k grad T) is solved for every particle that is not a fixed-
temperature wall (fluid and rigid solid alike); wall particles hold their temperature
(a Dirichlet boundary). The step evaluates the pair sum with the cached sparse operator
of :mod:`torchsph.physics.heat_operator`; :func:`conduction_pairs`, the same sum on a neighbour
table, is its reference (the tests compare the two at every step).
"""
from __future__ import annotations

import math

import torch

from torchsph.core.kernels import Kernel
from torchsph.core.neighbors import Domain
from torchsph.core.state import Array, Holder, ParticleState, Phase
from torchsph.physics.beam import beams_power, reachable
from torchsph.physics.beam_heat import beam_power_decomposed, plan_beams
from torchsph.physics.conduction_select import rigid_marks, select_operator
from torchsph.physics.conduction_window import integrated_rows, split_operator
from torchsph.physics.enthalpy import (
    Inversion,
    ThermalParams,
    banded_temperature,
    effective_heat_capacity,
    enthalpy,
    liquid_fraction,
    mushy_capacity,
    temperature_from_enthalpy,
)
from torchsph.physics.fluid import embed, gather_nb, pair_geometry
from torchsph.physics.free_surface import ColourGradient
from torchsph.physics.heat_operator import ENTRY_BLOCK, by_rows
from torchsph.physics.losses import SurfaceLosses, flat_surface_delta, surface_area, surface_rows

# the conduction's per-particle arrays (the registry, torchsph.step.particles, carries them)
CONDUCTION_ARRAYS = {
    "k": Array("thermal conductivity", "W/(m K)", output="conductivity", from_case=True),
    "T_set": Array("the walls' prescribed temperature", "K"),
    "steady": Array("solid with no phase change since the conduction matrix was made", lazy=True),
    "x_op": Array("the positions the conduction matrix was made at", "m", lazy=True, vector=True),
    "zeta_cache": Array("the Laplacian's normalisation zeta at the last selection", lazy=True),
    "area_cache": Array("free-surface area of the losses at the last selection (0 off the surface)", "m^2",
                        output="surface_area", lazy=True),
    "normal": Array("outward normal of the losses' surface", lazy=True, vector=True),
    "zeta_ok": Array("rows whose zeta is up to date", lazy=True),
    "area_ok": Array("rows whose area is up to date", lazy=True),
    # the last rebuild's values, reused by the lazy recomputation: carried only while it is
    # pending (else unused, and kept out of the per-step ghost refresh)
    "zeta_prev": Array("zeta at the rebuild before", lazy=True, when=lambda th: getattr(th, "zeta_cache", None) is None),
    "area_prev": Array("area at the rebuild before", "m^2", lazy=True, when=lambda th: getattr(th, "area_cache", None) is None),
    "normal_prev": Array("normal at the rebuild before", lazy=True, vector=True, when=lambda th: getattr(th, "area_cache", None) is None),
    "lit": Array("lit by a beam at the last evaluation", output="lit", lazy=True),
}


def conduction_pairs(x, T, k, m, rho, zeta, rows, nb, kernel: Kernel, h: float, domain: Domain):
    """(div k grad T)_i = sum_j 4 (m_j / rho_j) k_i k_j / (k_i + k_j) (T_i - T_j) (1/r) dW/dr
    (Cleary & Monaghan 1999), W/m^3, times 2 / (zeta_i + zeta_j) (see :func:`laplacian_norm`).
    dW/dr < 0, so heat flows from hot to cold; the pair exchange V_i q_ij is antisymmetric,
    so the total energy is conserved."""
    dx, r = pair_geometry(x, rows, nb, domain, h)
    dWr = kernel.dwdr(r, h) / r
    k_i = k.index_select(0, rows).unsqueeze(1)
    k_j = gather_nb(k, nb)
    kij = 4.0 * k_i * k_j / (k_i + k_j)
    corr = 2.0 / (zeta.index_select(0, rows).unsqueeze(1) + gather_nb(zeta, nb))
    dT = T.index_select(0, rows).unsqueeze(1) - gather_nb(T, nb)
    return (gather_nb(m, nb) / gather_nb(rho, nb) * kij * corr * dT * dWr).sum(1)


def laplacian_norm(x, m, rho, rows, nb, kernel: Kernel, h: float, domain: Domain):
    """zeta_i = -(1/d) sum_j V_j r_ij dW/dr: the discrete form of the identity
    -(1/d) int r dW/dr dV = 1 on which the SPH Laplacian rests. On a lattice it is off by
    the kernel's lattice error (Wendland C2, h = 1.5 dx: -0.26 % in 2-D), an error that
    does not shrink with dx at fixed h/dx; dividing the pair term by the mean zeta of the
    pair removes it and keeps the exchange antisymmetric."""
    dx, r = pair_geometry(x, rows, nb, domain, h)
    return -(gather_nb(m, nb) / gather_nb(rho, nb) * r * kernel.dwdr(r, h)).sum(1) / x.shape[1]


def wall_temperature_pairs(x, T, rows, nb, mask, kernel: Kernel, h: float, domain: Domain):
    """Shepard averages sum_f T_f W / sum_f W over the conducting neighbours of walls."""
    dx, r = pair_geometry(x, rows, nb, domain, h)
    Wk = kernel.w(r, h) * mask
    return (gather_nb(T, nb) * Wk).sum(1), Wk.sum(1)


class Conduction(Holder):
    """Heat conduction for all non-wall particles. Wall particles are fixed-temperature
    (Dirichlet) boundaries: like the no-slip velocity of Adami et al. (2012), a wall
    particle takes the mirrored value T_w = 2 T_set - <T>_w (Shepard average of its
    conducting neighbours), so that the prescribed temperature holds on the wall surface
    between the last solid and the first wall layer rather than at the wall particles."""
    array_prefix, ARRAYS = "th", CONDUCTION_ARRAYS

    def __init__(self, params: ThermalParams, kernel: Kernel, h: float, domain: Domain,
                 conductivity: torch.Tensor, compile: bool = False, beams=(), dx: float = 0.0,
                 losses: SurfaceLosses | None = None, h_over_dx: float = 1.5, colour: ColourGradient | None = None):
        self.prm = params
        self.kernel = kernel
        self.h = h
        self.domain = domain
        self.k = conductivity  # (N,) W/(m K), per particle
        self.beams = list(beams)  # surface heat sources (2.7)
        self.dx = dx
        self.losses = losses if losses is not None else SurfaceLosses()
        self.delta_norm = flat_surface_delta(kernel, h_over_dx) if self.losses.active else 1.0
        self._zeta_fn = torch.compile(laplacian_norm, dynamic=True) if compile else laplacian_norm
        # the colour gradient, shared with the surface forces when both exist (one per step)
        self.colour = colour if colour is not None else ColourGradient(kernel, h, domain, compile=compile)
        self.area_want = None  # the area rows asked of the colour stage at the last selection
        self.surface_memo = None  # (rows, area, the surface rows: surface_rows)

    def select_pairs(self, state: ParticleState, table,
                     active: torch.Tensor | None = None, work: torch.Tensor | None = None,
                     x_ref: torch.Tensor | None = None, new_table: bool = True, reach: float | None = None, cross=None):
        """Rows: every particle but the walls, or with an active set only its active particles (and the
        walls of its work set). ``x_ref``: the positions at the last neighbour build (default: now);
        ``new_table``: the table was just built (else the phases changed, or the particles were swapped in
        with their arrays); ``reach``: how far a particle may move from ``x_ref`` before the next build
        (None: unknown); ``cross``: the only rigid rows read (:func:`~torchsph.step.bookkeeping.cross_rows`)."""
        wall = state.phase == Phase.WALL
        self.wall_mask = wall
        # Laplacian normalisation and surface area per particle (and the surface normal):
        # recomputed after each neighbour rebuild, except where they cannot have changed
        self._mark_rigid(state, table, work, cross)
        self.zeta_cache = None
        self.area_cache = None
        self.rows = torch.nonzero(~wall if active is None else ~wall & active).squeeze(1)
        self.table = table  # (its rows are read where computed: rows_and_table)
        x_ref = state.x if x_ref is None else x_ref
        comm = getattr(self, "comm", None)
        op = select_operator(self, table, state, x_ref, new_table)
        op.select(table, self.steady, state.body, work, cross)
        self.rows_w = torch.nonzero(wall if work is None else wall & work).squeeze(1)
        own = getattr(self, "owned", None)  # (ghosts off the rows: their owners count them)
        rest = torch.ones(state.n, dtype=torch.bool, device=state.rho.device) if own is None else own.clone()
        rest.index_fill_(0, self.rows, False).index_fill_(0, self.rows_w, False)
        self._rho_rest = torch.where(rest, state.rho, torch.full_like(state.rho, math.inf)).min()
        if not hasattr(self, "T_set"):
            self.T_set = state.T.clone()  # the walls' prescribed temperatures
        if self.rows_w.numel():
            nbw, mw = table.gather(self.rows_w, within=True)
            self.nb_w = nbw
            self.mask_w = (mw & ~gather_nb(wall, nbw)).to(state.dtype)
        self.beam_rows = self.beam_candidates(x_ref, reach, comm)
        self.mushy_cap = mushy_capacity(state.T.index_select(0, self.rows), self.prm)
        if self.losses.active:  # the rows whose area the next evaluation computes
            sub, _ = self.rows_to_compute("area")
            self.colour.want("area", self.rows if sub is None else self.rows.index_select(0, sub), table)
            self.area_want = (self.area_prev, self.area_ok)
            self.colour.want_norm(zeta_rows(self, table))

    def wall_temperature(self, state: ParticleState, T: torch.Tensor) -> torch.Tensor:
        """T with wall rows replaced by the mirrored Dirichlet value 2 T_set - <T>."""
        if not self.rows_w.numel():
            return T
        sT, sW = wall_temperature_pairs(state.x, T, self.rows_w, self.nb_w, self.mask_w,
                                        self.kernel, self.h, self.domain)
        Tset = self.T_set.index_select(0, self.rows_w)
        Tw = torch.where(sW > 0, 2.0 * Tset - sT / torch.where(sW > 0, sW, torch.ones_like(sW)), Tset)
        return T.index_copy(0, self.rows_w, Tw)

    # Cached geometry: zeta and the surface area (with the normal) of a particle depend only on
    # the positions and volumes of its neighbours. Where a particle and all its neighbours
    # (the Verlet list, a superset of the kernel support until the next rebuild) are solid,
    # of one rigid body and have no melt in their own lists (solid next to melt is the
    # melt's wall, its density set by the melt's pressure), they move together and keep
    # their volumes: the values computed at an earlier rebuild, when this was already so,
    # still hold (to round-off) and are kept. Phase changes re-select, so a neighbour that
    # melts marks the particle; particles added (a fed wire's layer) give old rows new
    # neighbours of their own body, so the next rebuild recomputes every row.
    zeta_ok = area_ok = None  # per particle: the cached value holds and was computed rigid
    steady = x_op = None  # per particle (CONDUCTION_ARRAYS): made with the conduction matrix
    zeta_prev = area_prev = normal_prev = None

    def forget_geometry(self):
        """Neighbours change (particles added or removed): zeta and the area are evaluated
        afresh for every row at the next evaluation; the conduction operator is made anew
        (its entries name particles by row)."""
        self.zeta_ok = self.area_ok = None
        self.op = None

    def _mark_rigid(self, state: ParticleState, table, work=None, cross=None):
        """Per particle: solid, not next to melt, and so are all its neighbours, of its body.
        Only the rows of the table's ``work`` set (None: all) are read: the others have no
        neighbours (a solid one is rigid). ``cross``: :func:`rigid_marks`'s."""
        self.rigid = rigid_marks(state, table, work, cross)
        n = state.n
        for name in ("zeta", "area"):
            ok = getattr(self, f"{name}_ok")
            val = getattr(self, f"{name}_cache", None)
            val = getattr(self, f"{name}_prev", None) if val is None else val  # (2 selections, 0 evaluations: kept)
            keep = ok is not None and val is not None and ok.shape[0] == n
            setattr(self, f"{name}_ok", ok & self.rigid if keep else None)
            setattr(self, f"{name}_prev", val if keep else None)
        self.normal_prev = getattr(self, "normal", None) if self.area_prev is not None else None
        if self.normal_prev is None or self.normal_prev.shape[0] != n:
            self.area_prev = self.area_ok = self.normal_prev = None

    def rows_to_compute(self, name: str):
        """(positions in rows to compute, previous full-length values or None: compute all)."""
        ok, prev = getattr(self, f"{name}_ok"), getattr(self, f"{name}_prev")
        if prev is None:
            return None, None
        return torch.nonzero(~ok.index_select(0, self.rows)).squeeze(1), prev

    def computed(self, name: str, n: int):
        """After computing: the values of every row hold; the rigid ones may be kept later."""
        in_rows = torch.zeros(n, dtype=torch.bool, device=self.rows.device).index_fill_(0, self.rows, True)
        setattr(self, f"{name}_ok", in_rows & self.rigid)
        setattr(self, f"{name}_prev", None)
        return in_rows

    def heat_rate(self, state: ParticleState, T: torch.Tensor) -> torch.Tensor:
        """div(k grad T) per unit volume (W/m^3) at temperatures ``T``; 0 on walls."""
        return embed(self.rows, self.heat_rate_rows(state, T), state.n)

    def prepare(self, state: ParticleState):
        """Once per pair selection, at its first evaluation: zeta and the operator's values (the
        step calls it before its second half, which then has no branch on them)."""
        if self.zeta_cache is None:
            self.zeta_cache = self.zeta(state)
        if not self.op.built:  # once per selection, when zeta is known
            self.op.build(self.k, self.zeta_cache, self.k_summary()[1])
            split_operator(self, state)
        if self.losses.active:  # the surface rows, made here outside the traced part of the step
            surface_rows(self, state)
        plan_beams(self, state, self.rows)  # the beams' tracing, outside the traced part of the step
        if self.int_rows_for is not self.rows or (self.op.split is not None and self.int_rows is None):
            integrated_rows(self)

    def heat_rate_rows(self, state: ParticleState, T: torch.Tensor) -> torch.Tensor:
        """div(k grad T) (W/m^3) on ``rows`` only."""
        T = self.wall_temperature(state, T)
        self.prepare(state)
        q = self.op.apply(state.x, T, self.k, state.m, state.rho, self.zeta_cache, self.slow_now)
        return q if self.op.at is None else T.new_zeros(self.rows.shape).index_copy_(0, self.op.at, q)

    def zeta(self, state: ParticleState) -> torch.Tensor:
        """Per-particle Laplacian normalisation, used where it lies in [0.95, 1.05] (else 1): it corrects the
        interior lattice error only; where the kernel is truncated (a free surface,
        zeta ~ 0.5) the plain SPH operator, which acts as an insulated boundary, is kept.
        Walls, and particles outside the rows (an active set's frozen halo), count as 1."""
        sub, prev = self.rows_to_compute("zeta")
        rows = self.rows if sub is None else self.rows.index_select(0, sub)
        z = zeta_of(self, state, rows)
        z = torch.where((z > 0.95) & (z < 1.05), z, torch.ones_like(z))
        in_rows = self.computed("zeta", state.n)
        one = torch.ones(state.n, dtype=z.dtype, device=z.device)  # off the rows (at 0 a halo pair had twice its g)
        return torch.where(in_rows, prev, one).index_copy(0, rows, z) if prev is not None else one.index_copy(0, rows, z)

    def power(self, state: ParticleState, T: torch.Tensor, t: float, per_particle: bool = False, rows_only: bool = False):
        """Heat per particle (W; ``rows_only``: of ``rows`` only): conduction V_i div(k grad T),
        beam power, minus surface losses; and the totals by kind (W) (``per_particle``: the
        per-particle arrays by kind instead, for a diagnosis). The step integrates the
        specific enthalpy, dh/dt = P_i / m_i, and recovers T from h(T) = int c_eff dT (2.11):
        the latent heat is absorbed exactly however narrow the mushy interval is compared
        with one step's temperature change. Conduction: one sparse product and the moving
        pairs on every row at every step (:mod:`torchsph.physics.heat_operator`)."""
        rows, n = self.rows, state.n  # every term on the rows only (the others get none)
        parts = {"conduction": self.heat_rate_rows(state, T) * (state.m.index_select(0, rows) / state.rho.index_select(0, rows))}
        if self.beams:
            parts["beam"] = self.beam_power_rows(state, t, rows)
            lit = parts["beam"] > 0
            self.lit = torch.zeros(n, dtype=torch.bool, device=lit.device).index_copy_(0, rows, lit)
            self.n_lit = lit.sum()  # a tensor: the plan statistics sum it without a sync per step
        if self.losses.active:
            if self.area_cache is not None and self.area_want is not None:  # the area came back with the particles (a restore)
                self.area_want = None
                self.colour.want("area", None)
            at, srows, area = surface_rows(self, state)  # only they lose heat (the area made if due)
            fl = self.losses.flux(T.index_select(0, srows), lambda T_: enthalpy(T_, self.prm, 0.0))
            lost = {name: -f * area for name, f in fl.items()}
        else:
            lost = {}
        P = sum(parts.values())
        if lost:  # summed on the surface rows in the order of the kinds (the values of a sum of every row)
            P = P.index_copy(0, at, sum(lost.values(), P.index_select(0, at)))
            parts.update({k: v.new_zeros(rows.shape).index_copy_(0, at, v) for k, v in lost.items()}
                         if per_particle else {})
        P = P if rows_only else embed(rows, P, n)
        if per_particle:
            return P, {k: embed(rows, v, n) for k, v in parts.items()}
        own = getattr(self, "owned", None)  # a decomposed run books its own particles only
        mine = lambda v, r: v if own is None else torch.where(own.index_select(0, r), v, torch.zeros_like(v))  # noqa: E731
        totals = {k: mine(v, rows).sum() for k, v in parts.items()}
        totals.update({k: mine(v, srows).sum() for k, v in lost.items()})
        totals.setdefault("beam", torch.zeros((), dtype=T.dtype, device=T.device))
        return P, totals

    def beam_power(self, state: ParticleState, t: float, rows: torch.Tensor) -> torch.Tensor:
        """Power (W) each particle absorbs from all beams; only ``rows`` absorb or shadow
        (with an active set, the beams' footprints are in it: lit particles seed it)."""
        return embed(rows, self.beam_power_rows(state, t, rows), state.n)

    beam_rows = None  # per beam: the positions in ``rows`` that it can reach until the next build
    # the conduction window (numerics.conduction_window, 0: none; slow rows colder than slow_below), its start,
    # this step's factor (0-d, None: the slow pairs wait), closed in this step; :func:`integrated_rows`, and
    # its rows; this step's (:func:`start_step`); the next may take int_rows only; a checkpoint's fast rows
    window, slow_below, slow_mark, slow_now, closed = 0.0, math.inf, None, None, False
    int_rows = int_rows_for = step_rows = restored_fast = None
    partial_next = False
    refreeze_limit = 0.02  # share of G's rows re-solidified (not in G) at which G is made anew
    provisional = False  # steady set guessed (arrays not carried): G is made anew at the next build

    def beam_candidates(self, x_ref: torch.Tensor, reach: float | None, comm) -> list | None:
        """Per beam, the positions in ``rows`` it can reach before the next neighbour build
        (:func:`torchsph.physics.beam.reachable`; each process over its own rows)."""
        if not self.beams or reach is None:
            return None
        return reachable(self.beams, x_ref.index_select(0, self.rows), reach)

    def beam_power_rows(self, state: ParticleState, t: float, rows: torch.Tensor) -> torch.Tensor:
        """:meth:`beam_power` on ``rows`` only (each beam traced on the rows it can reach)."""
        comm = getattr(self, "comm", None)
        if comm is not None and comm.size > 1:
            return beam_power_decomposed(self, state, t, rows, comm, self.beam_rows if rows is getattr(self, "rows", None) else None)
        return beams_power(self.beams, state.x, t, self.dx, plan=plan_beams(self, state, rows))

    def lit_mask(self, state: ParticleState, t: float) -> torch.Tensor | None:
        """Particles any beam lights at time t (all non-wall particles considered)."""
        if not self.beams:
            return None
        return self.beam_power(state, t, torch.nonzero(state.phase != Phase.WALL).squeeze(1)) > 0

    def add_particles(self, new: ParticleState):
        """Extend the per-particle arrays for particles appended to the state."""
        self.k = torch.cat([self.k, torch.full((new.n,), self.prm.conductivity, dtype=self.k.dtype,
                                               device=self.k.device)])
        self.T_set = torch.cat([self.T_set, new.T])
        if self.steady is not None:  # not in the conduction matrix: steady from its next making
            self.steady = torch.cat([self.steady, torch.zeros(new.n, dtype=torch.bool, device=self.steady.device)])
            self.x_op = torch.cat([self.x_op, new.x])
        for name in ("zeta_cache", "area_cache", "normal"):  # kept to length until the forced rebuild
            v = getattr(self, name, None)
            if v is not None:
                setattr(self, name, torch.cat([v, torch.zeros((new.n,) + v.shape[1:], dtype=v.dtype, device=v.device)]))
        if getattr(self, "lit", None) is not None:
            self.lit = torch.cat([self.lit, torch.zeros(new.n, dtype=torch.bool, device=self.lit.device)])

    def surface_area(self, state: ParticleState) -> torch.Tensor:
        """:func:`surface_area` of this model's rows (sets ``normal``)."""
        return surface_area(self, state)

    def to_enthalpy(self, T: torch.Tensor) -> torch.Tensor:
        return enthalpy(T, self.prm, 0.0)

    mushy_cap = 1 << 62  # rows :func:`banded_temperature` inverts by Newton (all until a selection sets it)
    def to_temperature_unchecked(self, H: torch.Tensor, guess: torch.Tensor) -> "Inversion":
        """T from the specific enthalpy (:func:`banded_temperature`: closed form off the mushy band, Newton
        from ``guess`` on it), the convergence not read: an :class:`Inversion` whose ``bad`` mask the step
        reads with its other decisions, and whose ``fixed()`` inverts the rows that did not converge."""
        if self.prm.latent_heat <= 0.0:  # exact: nothing to check
            return Inversion(self.to_temperature(H, guess), None, H, self.prm)
        T, bad = banded_temperature(H, self.prm, 0.0, guess, self.mushy_cap)  # (an empty H gets an empty mask: every process reads alike)
        return Inversion(T, bad, H, self.prm)

    def to_temperature(self, H: torch.Tensor, guess: torch.Tensor | None = None) -> torch.Tensor:
        return temperature_from_enthalpy(H, self.prm, 0.0, guess)

    def limit(self, state: ParticleState):
        """Thermal time-step limit 0.125 rho c_p h^2 / k (3.17, fixed), a 0-d float64 tensor
        (inf without conduction)."""
        kmax = self.k_summary()[0]
        lim = 0.125 * self.rho_min(state).double() * self.prm.specific_heat * self.h**2 / kmax
        return torch.where(kmax > 0, lim, torch.full_like(lim, math.inf))

    def k_summary(self) -> tuple[torch.Tensor, torch.Tensor | None]:
        """(the largest conductivity as a 0-d float64 tensor, the one conductivity where all are
        equal or None), made once per conductivity array: passes over every particle (and one
        host read) at the first use after k is set, not at every step."""
        memo = self.__dict__.get("_k_summary")
        if memo is None or memo[0] is not self.k:
            k = self.k
            kmax = k.max()
            memo = self._k_summary = (k, kmax.double(), k[0].clone() if bool(k.min() == kmax) else None)
        return memo[1], memo[2]

    def rho_min(self, state: ParticleState) -> torch.Tensor:
        """The smallest density of all particles, reading only the rows, the walls among them
        and, for the rest (cold solid left out, whose density does not change), the value
        taken at the pair selection."""
        r = self._rho_rest
        if self.rows.numel():
            r = torch.minimum(state.rho.index_select(0, self.rows).min(), r)
        return r if not self.rows_w.numel() else torch.minimum(r, state.rho.index_select(0, self.rows_w).min())


def zeta_rows(th, table, limit: int = 4 * ENTRY_BLOCK):
    """At a selection: the rows whose zeta the next evaluation makes, for the colour stage to
    make from the pairs it reads for the area anyway (kept as ``th.zeta_want``), or None: a
    whole zeta (a restart, new particles: made in blocks) or a compiled zeta is made apart."""
    sub, _ = th.rows_to_compute("zeta")
    th.zeta_want = None
    if sub is not None and th._zeta_fn is laplacian_norm and sub.numel() * table.k <= limit:
        th.zeta_want = th.rows.index_select(0, sub)
    return th.zeta_want


def zeta_of(th, state: ParticleState, rows: torch.Tensor) -> torch.Tensor:
    """zeta (unclipped) of ``rows`` of ``th`` (:class:`Conduction`): the colour stage's where it
    made them at this state (:func:`zeta_rows`), else in blocks of table rows."""
    want = getattr(th, "zeta_want", None)
    z = th.colour.norm(state, want) if want is not None else None
    if z is None or z.shape[0] != rows.numel():
        z = by_rows(lambda r, t: th._zeta_fn(state.x, state.m, state.rho, r, t, th.kernel, th.h, th.domain),
                    rows, th.table.gather(rows, within=True)[0])
    return z


__all__ = ["ThermalParams", "Conduction", "SurfaceLosses", "effective_heat_capacity", "enthalpy",
           "temperature_from_enthalpy", "liquid_fraction", "conduction_pairs"]
