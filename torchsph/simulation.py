"""Time integration (SPEC §4): velocity-Verlet kick-drift-kick, forces evaluated at the end
of the step with the extrapolated velocity u~ = u + dt du/dt for the viscous term, and an
automatic time step from every stability limit.

Density: the thesis's half steps (1c, 3a) evaluate the force with a density extrapolated
by explicit Euler and correct it by the trapezoidal rule. For the acoustic subsystem
(rho' = -rho0 div u, u' = -c0^2 grad rho / rho0) that is Heun's method, whose
amplification factor for an oscillation of frequency w is |1 + i w dt - (w dt)^2 / 2| > 1:
every step amplifies sound waves, and a Taylor-Green vortex blew up within 0.2 s in our
runs. The density is therefore advanced like a position, with the half-step velocity
(rho_{n+1} = rho_n + dt D(x_n, u_{n+1/2})): Stormer-Verlet for (rho, u), stable for
w dt < 2. The continuity sum is linear in u, so it reuses the pair geometry of the last
force evaluation and costs one gather and one scatter per pair."""
from __future__ import annotations

import math
from dataclasses import dataclass

import torch

from .active import ActiveSet
from .comm import SerialComm
from .fluid import WeaklyCompressibleFluid, neighbour_average
from .surface import SurfaceForces
from .thermal import Conduction
from .neighbors import Domain, VerletList
from .state import ParticleState, Phase


class SimulationError(RuntimeError):
    """A run that cannot go on (blow-up, unstable time step); the message is a diagnosis."""


class UnstableStepError(SimulationError):
    """A fixed time step (``numerics.dt_s``) above a stability limit: bad input, refused
    before the first step."""


LIMIT_FORMULAS = {
    "acoustic": "cfl h / (c0 + |u|max)",
    "viscous": "0.125 h^2 rho_min / eta",
    "force": "0.25 sqrt(h / |a|max)",
    "thermal": "0.125 rho c_p h^2 / k",
    "capillary": "0.25 sqrt(rho_min h^3 / (2 pi alpha_max))",
    "evaporation": "0.5 m c_p / (A d q_evap/dT), the stiffness of the evaporation loss",
    "heating": "0.1 c_p T / |dh/dt| (with evaporation)",
}


# per-particle caches built lazily (some processes of a decomposed run may not hold them):
# where a checkpoint or a migration does not carry one, it is dropped and rebuilt whole
LAZY_CACHES = frozenset({"th.steady", "th.x_op", "th._zeta", "th._area", "th.normal", "th._zeta_ok", "th._area_ok", "th.lit",
                         "th._zeta_prev", "th._area_prev", "th._normal_prev", "sf.normal", "sf.kappa"})


class PlanStats:
    """Per-term work actually done, averaged over the steps: particles (rows) and pairs
    each term evaluated, against all particles and the pairs a full table would hold
    (estimated as N x the mean neighbour count of the rows that were built)."""

    def __init__(self):
        self.steps = 0
        self.sums: dict[str, list[float]] = {}
        self.current: dict[str, tuple[int, int]] = {}
        self.all_pairs = 0.0
        self.n = 0
        self.n_active = 0  # particles this process owns and integrates (as of the last rebuild)

    def select(self, sim):
        s = sim.state
        cur = {}
        table = sim.nl.table
        per_row = table.mask.sum(1)  # the table's rows (the work set's, with an active set)
        nbuilt = max(int((per_row > 0).sum()), 1)
        self.n = s.n
        own = sim.comm.owned(sim)
        integrated = sim.fluid_mask.clone()
        if sim.thermal is not None:
            integrated.index_fill_(0, sim.thermal.rows, True)
        self.n_active = int((integrated if own is None else integrated & own).sum())
        self.all_pairs = s.n * int(per_row.sum()) / nbuilt
        pairs = lambda rows: int(table.gather(rows, within=True)[1].sum())  # noqa: E731
        if sim.fluid is not None:
            f = sim.fluid
            cur["momentum"] = (f.rows_f.numel(), pairs(f.rows_f))
            if f.has_walls:
                cur["wall"] = (f.rows_w.numel(), int(f.mask_w.sum()))
        if sim.thermal is not None:
            th = sim.thermal
            cur["conduction"] = (th.rows.numel(), pairs(th.rows))
        self.current = cur

    def add(self, sim):
        self.steps += 1
        cur = dict(self.current)
        if sim.surface is not None:
            cur["surface"] = (sim.surface.n_surface, 0)
        if sim.thermal is not None and getattr(sim.thermal, "n_lit", None) is not None:
            cur["beam"] = (sim.thermal.n_lit, 0)
        for k, (r, p) in cur.items():
            acc = self.sums.setdefault(k, [0.0, 0.0, 0.0, 0.0])
            acc[0] += r
            acc[1] += p
            acc[2] += self.n
            acc[3] += self.all_pairs

    def report(self) -> dict:
        """{term: {particles: fraction, pairs: fraction}} averaged over the steps."""
        out = {}
        for k, (r, p, n, ap) in self.sums.items():
            out[k] = {"particles": float(r) / n if n else 0.0}
            if k in ("momentum", "wall", "conduction"):
                out[k]["pairs"] = float(p) / ap if ap else 0.0
        return out


@dataclass
class StepInfo:
    dt: float
    limit: str  # binding limit name, or "fixed"
    vmax: float
    amax: float


class Simulation:
    """Single-process solver: owns the state, the neighbour list and the clock."""

    def __init__(self, state: ParticleState, fluid: WeaklyCompressibleFluid | None, domain: Domain,
                 skin: float, cfl: float = 0.25, dt_fixed: float | None = None,
                 allow_unstable_dt: bool = False, max_compression: float = 0.3, dx: float = 0.0,
                 damping_time: float = 0.0, thermal: Conduction | None = None,
                 phase_change: tuple[float, float, float] | None = None,
                 surface: SurfaceForces | None = None, active: ActiveSet | None = None,
                 feeder=None, comm=None, escape=None, partial_rebuild: bool = True):
        """``fluid`` and ``thermal`` are the physics a scene declares; either may be None
        and then costs nothing (a conduction study has no momentum, a flow no energy).
        ``active`` leaves cold quiescent solid out of the work (:mod:`torchsph.active`);
        ``feeder`` adds particles as the run goes (``new_particles(sim, t)``, e.g. a fed
        wire); ``escape`` says which particles have left the scene for good
        (``outside(x, t)``, :class:`~torchsph.deposition.EscapeBox`): they are removed at the
        next neighbour rebuild. ``partial_rebuild``: neighbour rebuilds keep the largest rigid
        body's mutual pairs and search only the other rows (:class:`~torchsph.neighbors.VerletList`;
        one process, scenes with fluid)."""
        self.state = state
        self.comm = comm if comm is not None else SerialComm()  # decomposition hooks (no-ops in one process)
        self._rebuilt = False  # the last step rebuilt the neighbour list
        self._new_body_velocity = False
        self.active_set = active if (active is not None and not domain.any_periodic) else None
        self.feeder = feeder
        self.escape = escape
        self.plan = PlanStats()
        self.fluid_mask = state.phase == Phase.FLUID
        self.n_fluid = int(self.fluid_mask.sum())
        self.fluid_model = fluid  # active only while there are fluid particles
        self.thermal = thermal
        self.surface_model = surface  # free-surface forces; active with the fluid
        if surface is not None and fluid is None:
            raise ValueError("Simulation: surface forces need the fluid model")
        # (T_S, T_L, C): solids melt above T_L, melt freezes below T_S, mushy drag C
        self.phase_change = phase_change
        if phase_change is not None and (fluid is None or thermal is None):
            raise ValueError("Simulation: phase change needs both the fluid and the thermal model")
        # velocity of each rigid body (row b = body b; row 0 unused), from its solid particles
        self.body_velocity = self._body_velocities(state)
        if fluid is None and thermal is None:
            raise ValueError("Simulation: the scene declares no physics (no fluid, no thermal)")
        self.domain = domain
        some = fluid if fluid is not None else thermal
        self.h = some.h
        self.cfl = cfl
        self.dt_fixed = dt_fixed
        self.allow_unstable_dt = allow_unstable_dt
        self.max_compression = max_compression
        self.dx = dx  # initial particle spacing
        self.damping_time = damping_time  # settling: velocity damping for t < damping_time
        self.nl = VerletList(some.kernel.radius(some.h), skin, domain)
        self.partial_rebuild = partial_rebuild and self.comm.size == 1 and fluid is not None
        self.t = 0.0
        self.step = 0
        self._stale = False  # the active set must be refreshed at the next rebuild point
        if thermal is not None:
            thermal.comm, thermal.owned = self.comm, self.comm.owned(self)
        if self.active_set is not None and thermal is not None:
            thermal.lit = thermal.lit_mask(state, 0.0)  # the beams' footprint seeds the active set
        self._refresh_pairs(force=True)
        self.dvdt = torch.zeros_like(state.v)
        self.drhodt = torch.zeros_like(state.rho)
        if self.fluid is not None:
            self.dvdt = self._accelerations(state.v)
            self.drhodt, _ = self.fluid.continuity(state.v, state.m)
        self.dTdt = None  # specific enthalpy rate dh/dt (W/kg) when the scene has heat
        self.energy = {}  # J by kind (beam, conduction from walls, losses), integrated as the step does
        if thermal is not None:
            P, self._heat = thermal.power(state, state.T, 0.0)
            self.dTdt = P / state.m
            self._E0 = thermal.energy(state, thermal.prm, 0.0, self.comm.owned(self))
        self.comm.end_step(self)  # ghosts (if any) take their owners' values
        self._rebuilt = False  # the set-up build needs no migration
        self.info = self._measure()
        self._check_finite(state.v)
        if dt_fixed is not None:
            self.check_fixed_dt()

    @property
    def fluid(self) -> WeaklyCompressibleFluid | None:
        """The fluid model while the scene has fluid particles, else None (costs nothing)."""
        return self.fluid_model if self.n_fluid > 0 else None

    @property
    def surface(self) -> SurfaceForces | None:
        """The free-surface forces while the scene has fluid particles, else None."""
        return self.surface_model if self.n_fluid > 0 else None

    def _accelerations(self, v_eval, terms: bool = False):
        """Fluid (pressure, viscous, body) plus free-surface accelerations at the state."""
        out = self.fluid.momentum(self.state, v_eval, terms=terms)
        if self.surface is None:
            return out
        if not terms:  # the surface particles' accelerations added into the fresh array
            rows, a_s = self.surface.accelerations(self.state, rows_only=True)
            return out.index_add_(0, rows, a_s)
        a_s, parts_s = self.surface.accelerations(self.state, terms=True)
        return out[0] + a_s, {**out[1], **parts_s}

    # --- neighbours ---------------------------------------------------------
    def _refresh_pairs(self, force: bool = False):
        subset = self._work_set if self.active_set is not None else None
        force = force or self._stale
        if not force and self.comm.size > 1:  # all processes rebuild at the same steps
            force = self.comm.any(self.nl.needs_rebuild(self.state.x, self._moving_rows()))
            if not force:
                return
        rigid = self._rigid_body if self.partial_rebuild else None
        if self.nl.update(self.state.x, force=force, subset=subset, rigid=rigid, rows=self._moving_rows()):
            self._stale = False
            self._rebuilt = True
            self._select(new_table=True)
            self._moving_rows()  # for the new work set, at the rebuild

    def _moving_rows(self) -> torch.Tensor | None:
        """The particles whose displacement decides a neighbour rebuild: with an active set,
        its work set, and of the cold solid left out one per rigid body (they move with it);
        None (all) without one. Made once per work set."""
        a = self.active_set
        if a is None or a.work is None or a.work.shape[0] != self.state.n:
            return None
        if getattr(self, "_moving_for", None) is not a.work:
            st = self.state
            cold = ~a.work & (st.phase == Phase.SOLID) & (st.body > 0)
            idx = torch.arange(st.n, device=st.device)
            big = torch.iinfo(torch.long).max
            first = torch.full((self.body_velocity.shape[0],), big, dtype=torch.long, device=st.device).scatter_reduce(
                0, st.body, torch.where(cold, idx, torch.full_like(idx, big)), "amin")
            keep = ~cold
            keep.index_fill_(0, first[first < big], True)
            self._moving, self._moving_for = torch.nonzero(keep).squeeze(1), a.work
        return self._moving

    def _rigid_body(self) -> torch.Tensor | None:
        """Mask of the largest rigid group: the solid particles of one body, or the walls
        (None without either)."""
        st = self.state
        solid = (st.phase == Phase.SOLID) & (st.body > 0)
        group = torch.where(solid, st.body, torch.where(st.phase == Phase.WALL, 0, -1))
        rigid = group >= 0
        if not bool(rigid.any()):
            return None
        main = int(torch.bincount(group[rigid]).argmax())
        return group == main

    def _work_set(self) -> torch.Tensor:
        """Refresh the active set (at a neighbour rebuild) and return its work mask."""
        self.active_set.refresh(self.state, getattr(self.thermal, "lit", None))
        return self.active_set.work

    @property
    def active_mask(self) -> torch.Tensor | None:
        return self.active_set.active if self.active_set is not None else None

    n_selections = 0  # pair selections so far (a decomposition refreshes every ghost after one)

    def _select(self, new_table: bool = False):
        self.n_selections += 1
        if self.fluid is not None:
            self.fluid.select_pairs(self.state, self.nl.table, level=self.comm.levels(self),
                                    depth=getattr(self.comm, "depth", 2))
        if self.surface is not None:
            self.surface.select_pairs(self.state, self.nl.table)
        if self.thermal is not None:
            self.thermal.owned = self.comm.owned(self)
            self.thermal.select_pairs(self.state, self.nl.table, active=self.active_mask,
                                      work=self.active_set.work if self.active_set is not None else None,
                                      x_ref=self.nl.x_ref, new_table=new_table)
        self.plan.select(self)

    @property
    def n_pairs(self) -> int:
        return self.nl.table.n_pairs()

    # --- time-step control --------------------------------------------------
    def _measure(self):
        own = self.comm.owned(self)
        if self.fluid is None:
            rho = self.state.rho if own is None else self.state.rho[own]
            vals = [0.0, 0.0, float(rho.min()) if rho.numel() else float("inf"), 0.0]
            return dict(zip(("vmax", "amax", "rho_min", "compression"), self.comm.reduce_measure(vals)))
        rows = self.fluid.rows_f  # every fluid particle (and, decomposed, ghosts: masked)
        mine = None if own is None else own.index_select(0, rows)
        st = self.state
        v, a = st.v.index_select(0, rows), self.dvdt.index_select(0, rows)
        rho = st.rho.index_select(0, rows)
        comp = (rho / self.fluid.prm.rho0 - 1.0).abs()
        v2, a2 = (v * v).sum(-1), (a * a).sum(-1)
        if mine is not None:
            v2, a2 = torch.where(mine, v2, torch.zeros_like(v2)), torch.where(mine, a2, torch.zeros_like(a2))
            rho = torch.where(mine, rho, torch.full_like(rho, float("inf")))
            comp = torch.where(mine, comp, torch.zeros_like(comp))
        z = torch.zeros((1,), dtype=rho.dtype, device=rho.device)  # (a process may own no fluid)
        inf = torch.full((1,), float("inf"), dtype=rho.dtype, device=rho.device)
        vals = torch.stack([torch.cat([v2, z]).max().sqrt(), torch.cat([a2, z]).max().sqrt(),
                            torch.cat([rho, inf]).min(), torch.cat([comp, z]).max()]).tolist()
        return dict(zip(("vmax", "amax", "rho_min", "compression"), self.comm.reduce_measure(vals)))

    def limits(self) -> dict[str, float]:
        """Every time-step limit of SPEC §4 that applies to this scene (seconds)."""
        m, h = self.info, self.h
        lim = {}
        if self.fluid is not None:
            prm = self.fluid.prm
            lim["acoustic"] = self.cfl * h / (prm.c0 + m["vmax"])
            if prm.eta > 0:
                lim["viscous"] = 0.125 * h * h * m["rho_min"] / prm.eta
            if m["amax"] > 0 and math.isfinite(m["amax"]):
                lim["force"] = 0.25 * math.sqrt(h / m["amax"])
        if self.surface is not None:
            lim["capillary"] = self.surface.limit(self.state)
        if self.thermal is not None:
            lim["thermal"] = self.thermal.limit(self.state)
            if self.thermal.losses.evaporation:
                lim["evaporation"] = self.thermal.evaporation_limit(self.state)
                lim["heating"] = self._heating_limit()
        dev = [k for k, v in lim.items() if isinstance(v, torch.Tensor)]
        if dev:  # the limits computed on the device: one read
            lim.update(zip(dev, torch.stack([lim[k].reshape(()) for k in dev]).tolist()))
        lim = self.comm.merge_limits({k: v for k, v in lim.items() if math.isfinite(v)})
        return lim or {"none": math.inf}

    def _heating_limit(self):
        """0.1 c_p T / |dh/dt| over the non-wall particles: at most a 10 % temperature change
        per step. With evaporation on, a step that heats a surface particle far past T_v in
        one go meets a loss that is exponentially stiff there (a 1 200 W beam on the cube
        produced a non-finite temperature on the second step at the thermal limit). A 0-d
        float64 tensor."""
        th = self.thermal  # dh/dt is 0 off the rows (walls and the cold solid left out)
        if not th.rows.numel():
            return math.inf
        rate = self.dTdt.index_select(0, th.rows).abs()
        r = (rate / (th.prm.specific_heat * self.state.T.index_select(0, th.rows).clamp_min(1.0))).max().double()
        return torch.where(r > 0, 0.1 / r, torch.full_like(r, math.inf))

    def choose_dt(self) -> tuple[float, str]:
        lim = self.limits()
        self._lim_cache = (self.step, self.state.n, lim)  # advance() reuses them (same state)
        name = min(lim, key=lim.get)
        if self.dt_fixed is not None:
            return self.dt_fixed, "fixed"
        return lim[name], name

    def binding_limit(self) -> tuple[str, float]:
        lim = self.limits()
        name = min(lim, key=lim.get)
        return name, lim[name]

    def check_fixed_dt(self):
        """Refuse a fixed dt above any stability limit unless the case allows it."""
        for name, val in sorted(self.limits().items(), key=lambda kv: kv[1]):
            if self.dt_fixed > val and not self.allow_unstable_dt:
                raise UnstableStepError(
                    f"numerics.dt_s = {self.dt_fixed:g} s exceeds the {name} limit {val:.4g} s "
                    f"({LIMIT_FORMULAS[name]}); lower dt_s, remove it for the automatic step, "
                    "or set numerics.allow_unstable_dt = true")

    # --- one step -----------------------------------------------------------
    def advance(self, dt: float | None = None, limit: str = "given") -> StepInfo:
        """One kick-drift-kick step; dt defaults to the automatic (or fixed) step."""
        cache, self._lim_cache = getattr(self, "_lim_cache", None), None
        self._pre_limits = (cache[2] if cache is not None and cache[:2] == (self.step, self.state.n)
                            else self.limits())  # of the last good state, for a diagnosis
        if dt is None:
            dt, limit = self.choose_dt()
        self.comm.begin_step(self)  # migration and new ghosts after a rebuild (decomposed runs)
        self._rebuilt = False
        self._T_prev = self.state.T
        s = self.state
        fm = self.fluid_mask.unsqueeze(-1)
        a = self.dvdt  # zero for walls: they keep their prescribed velocity
        # (one fused pass per whole-array update: at full size these passes over every particle,
        # most of them rigid, cost more than the physics of the few that move)
        v_half = torch.add(s.v, a, alpha=0.5 * dt)  # 1a
        v_tilde = torch.add(s.v, a, alpha=dt)  # 1b, used by the viscous term at the end of the step
        if self.thermal is not None:  # the energy equation in specific enthalpy h(T)
            th = self.thermal
            rows0 = th.rows  # integrated particles (not walls; only the active set when skipping)
            T0, a_r = s.T, self.dTdt.index_select(0, rows0)
            H_r = th.to_enthalpy(T0.index_select(0, rows0))
            H_half_r = H_r + 0.5 * dt * a_r  # 1d on the rows (dh/dt = 0 off them: H_half = h(T) there)
            H_half = None  # the whole array, made only where particles are added, removed or re-selected

            def whole_H_half():
                return th.to_enthalpy(T0).index_copy_(0, rows0, H_half_r)
            # extrapolated for the evaluation at the end of the step; walls keep theirs
            s.T = s.T.index_copy(0, rows0, th.to_temperature(H_r + dt * a_r, T0.index_select(0, rows0)))
        shift = None
        if self.fluid is not None:
            self.drhodt, shift = self.fluid.continuity(  # at x_n, with u_{n+1/2}
                v_half, s.m, self.dx if self.fluid.prm.shifting > 0 else 0.0, rho=s.rho)
            s.rho = s.rho + dt * self.drhodt
        x_new = torch.add(s.x, torch.where(fm, v_half, s.v), alpha=dt)  # 1e (rigid bodies move with their velocity)
        if shift is not None:
            if self.surface is not None:
                shift = self.surface.project_shift(shift, self.fluid.rows_f)
            x_new = x_new.index_add_(0, self.fluid.rows_f, shift)
        s.x = self.domain.wrap(x_new)
        if self.feeder is not None:  # new particles enter at t + dt
            new = self.feeder.new_particles(self, self.t + dt)
            if new is not None and new.n:
                new, perm = self.add_particles(new)  # this process's share of them
                if new.n:
                    v_half = torch.cat([v_half, new.v])
                    v_tilde = torch.cat([v_tilde, new.v])
                    if self.thermal is not None:
                        H_half = torch.cat([whole_H_half() if H_half is None else H_half,
                                            self.thermal.to_enthalpy(new.T)])
                    if perm is not None:  # a decomposition keeps its own rows first
                        v_half, v_tilde = v_half.index_select(0, perm), v_tilde.index_select(0, perm)
                        if self.thermal is not None:
                            H_half = H_half.index_select(0, perm)
                fm = self.fluid_mask.unsqueeze(-1)
                s = self.state
        due = None
        if self.escape is not None:  # at a rebuild point: particles that have left the scene go
            due, keep = self._remove_escaped(self.t + dt, (lambda: whole_H_half() if H_half is None else H_half)
                                             if self.thermal is not None else None)
            if keep is not None:
                v_half, v_tilde = v_half[keep], v_tilde[keep]
                if self.thermal is not None:
                    H_half = (whole_H_half() if H_half is None else H_half)[keep]
                    new_row = torch.cumsum(keep.long(), 0) - 1
                    rows0 = new_row.index_select(0, rows0[keep.index_select(0, rows0)])
                fm = self.fluid_mask.unsqueeze(-1)
                s = self.state
        if due is None:
            self._refresh_pairs()
        elif due:  # decided above (on every process): no second test, no second collective
            self._refresh_pairs(force=True)
        if self.fluid is not None:
            self.dvdt = self._accelerations(v_tilde)  # 2
            if self.t + dt < self.damping_time:
                self.dvdt = self.dvdt - self._damping_rate(self.t + dt) * torch.where(
                    fm, v_tilde, torch.zeros_like(v_tilde))
        s.v = v_half.add_(self.dvdt, alpha=0.5 * dt)  # 3c (v_half is this step's own array)
        if self._new_body_velocity:  # a body's velocity was changed during the step (a feed starts)
            self._new_body_velocity = False
            solid = (s.phase == Phase.SOLID).unsqueeze(-1)
            s.v = torch.where(solid, self.body_velocity.index_select(0, s.body), s.v)
        if self.thermal is not None:
            P, heat = self.thermal.power(s, s.T, self.t + dt)  # 2 (W per particle; 0 on walls)
            self.dTdt = P / s.m
            for k, v in heat.items():  # accumulated on the device: no sync per step
                self.energy[k] = self.energy.get(k, 0.0) + 0.5 * dt * (self._heat[k] + v)
            self._heat = heat
            rows = th.rows if th.rows is rows0 else torch.unique(torch.cat([rows0, th.rows]))
            if H_half is None and rows is rows0:
                Hh = H_half_r
            else:
                Hh = (whole_H_half() if H_half is None else H_half).index_select(0, rows)
            s.T = s.T.index_copy(0, rows, th.to_temperature(  # 3b
                Hh + 0.5 * dt * self.dTdt.index_select(0, rows), s.T.index_select(0, rows)))
            s.T_peak = s.T_peak.index_copy(0, rows, torch.maximum(s.T_peak.index_select(0, rows), s.T.index_select(0, rows)))
        self.t += dt
        self.step += 1
        if self.phase_change is not None:
            self._update_phases(dt)
        self.comm.end_step(self)
        self.info = self._measure()
        self._check_finite(v_tilde, dt, limit)
        if self.active_set is not None and self.comm.any(self.active_set.stale(s, getattr(self.thermal, "lit", None))):
            self._stale = True  # heat reached the frontier band: refresh at the next rebuild point
        self.plan.add(self)
        return StepInfo(dt, limit, self.info["vmax"], self.info["amax"])

    def _body_velocities(self, state: ParticleState) -> torch.Tensor:
        """(bodies, dim): each rigid body's mean velocity over its solid particles, over all
        processes (the owned ones: ghosts are copies), so every process holds every body's row
        even where it holds none of its particles (a rank whose slab the fed wire misses)."""
        top = state.body.max().reshape(1) if state.n else torch.zeros(1, dtype=torch.long, device=state.device)
        nbody = int(self.comm.gather_rows({"top": top})["top"].max()) + 1
        own = self.comm.owned(self)
        solid = state.phase == Phase.SOLID
        if own is not None:
            solid = solid & own[: state.n]
        solid = solid.to(state.dtype).unsqueeze(-1)
        tot = torch.zeros(nbody, state.dim, dtype=state.dtype, device=state.device).index_add_(
            0, state.body, state.v * solid)
        cnt = torch.zeros(nbody, 1, dtype=state.dtype, device=state.device).index_add_(0, state.body, solid)
        both = torch.tensor(self.comm.sum(torch.cat([tot, cnt], 1).reshape(-1).tolist()),
                            dtype=state.dtype, device=state.device).view(nbody, state.dim + 1)
        return both[:, :-1] / both[:, -1:].clamp_min(1.0)

    def set_body_velocity(self, body: int, v: torch.Tensor):
        """Change a rigid body's velocity; its solid particles take it at the end of the step."""
        self.body_velocity[body] = v
        self._new_body_velocity = True

    # --- per-particle arrays (what a decomposition moves with a particle) -------
    def particle_arrays(self) -> dict[str, torch.Tensor]:
        """Every per-particle array the step carries from one step to the next, by name
        (None entries omitted): the state, the rates, the Verlet reference positions and the
        physics' per-particle caches."""
        from dataclasses import fields as dc_fields

        d = {f"state.{f.name}": getattr(self.state, f.name) for f in dc_fields(self.state)}
        d["dvdt"], d["drhodt"] = self.dvdt, self.drhodt
        d["dTdt"] = self.dTdt
        d["nl.x_ref"] = self.nl.x_ref
        th = self.thermal
        if th is not None:
            d.update({"th.k": th.k, "th.T_set": th.T_set, "th.steady": th.steady, "th.x_op": th.x_op, "th._zeta": th._zeta, "th._area": th._area,
                      "th.normal": getattr(th, "normal", None),
                      "th._zeta_ok": th._zeta_ok, "th._area_ok": th._area_ok,
                      # the last rebuild's values, to be reused by the lazy recomputation: carried only
                      # while it is pending (else unused, and kept out of the per-step ghost refresh)
                      "th._zeta_prev": th._zeta_prev if th._zeta is None else None,
                      "th._area_prev": th._area_prev if th._area is None else None,
                      "th._normal_prev": th._normal_prev if th._area is None else None})
            d["th.lit"] = getattr(th, "lit", None)
        sf = self.surface_model
        if sf is not None:
            d.update({"sf.normal": sf.normal, "sf.kappa": sf.kappa})
        a = self.active_set
        if a is not None:
            d.update({"as.active": a.active, "as.work": a.work, "as.frontier": a.frontier})
        return {k: v for k, v in d.items() if v is not None}

    def set_particle_arrays(self, d: dict[str, torch.Tensor]):
        """Put arrays named as in :meth:`particle_arrays` back (after a permutation)."""
        st = {k[6:]: v for k, v in d.items() if k.startswith("state.")}
        if st:
            self.state = ParticleState(**st)
        for k, v in d.items():
            if k.startswith("state."):
                continue
            obj, name = {"dvdt": (self, "dvdt"), "drhodt": (self, "drhodt"), "dTdt": (self, "dTdt"),
                         "nl.x_ref": (self.nl, "x_ref")}.get(k, (None, None))
            if obj is None:
                owner, name = k.split(".", 1)
                obj = {"th": self.thermal, "sf": self.surface_model, "as": self.active_set}[owner]
            setattr(obj, name, v)
        self.fluid_mask = self.state.phase == Phase.FLUID
        self.n_fluid = int(self.fluid_mask.sum())

    def rearm(self, arrays: dict[str, torch.Tensor], table=None):
        """Put per-particle arrays (named as in :meth:`particle_arrays`) into the simulation
        after its particles were swapped (a checkpoint restored, a migration between ranks):
        the arrays first; then every lazily built cache that ``arrays`` does not hold is
        dropped (it is rebuilt whole when next needed, never left over from the particles
        before: a cache kept from other rows is wrong); ``table()`` (if given) sets the
        neighbour table; the pair subsets are selected anew, which resets the per-rebuild
        caches, and the given ones are put back; the fluid's pair geometry (what the next
        continuity sum reuses) is recomputed, the rates kept."""
        held = self.particle_arrays()
        self.set_particle_arrays(arrays)
        for k in held:
            if k in LAZY_CACHES and k not in arrays:
                owner, name = k.split(".", 1)
                setattr({"th": self.thermal, "sf": self.surface_model}[owner], name, None)
        if table is not None:
            table()
        self._select()
        self.set_particle_arrays({k: v for k, v in arrays.items() if k.startswith(("th.", "sf."))})
        if self.fluid is not None:
            saved = self.dvdt
            self.fluid.momentum(self.state, self.state.v)  # sets p and the cached geometry only
            self.dvdt = saved

    def add_particles(self, new: ParticleState):
        """Append particles (e.g. a fed wire's new layer) at rest relative to their body,
        with zero rates; the neighbour list is rebuilt at the next rebuild point (forced).
        Every process of a decomposed run is given the same ``new`` and keeps the ones in
        its slab. Returns (the particles added here, the row permutation the decomposition
        applied to keep its own rows first, or None)."""
        self._stale = True
        if self.thermal is not None:  # on every process: the geometry is evaluated afresh
            self.thermal._zeta_ok = self.thermal._area_ok = None
        new, own = self.comm.claim(self, new)
        if new.n == 0:
            return new, None
        z = lambda t: torch.cat([t, torch.zeros((new.n,) + t.shape[1:], dtype=t.dtype, device=t.device)])  # noqa: E731
        self.state = ParticleState.cat([self.state, new])
        self.dvdt, self.drhodt = z(self.dvdt), z(self.drhodt)
        if self.dTdt is not None:
            self.dTdt = z(self.dTdt)
            self.thermal.add_particles(new)
            # the enthalpy the new particles bring in (the stored energy counts it)
            fed = new.m * self.thermal.to_enthalpy(new.T)
            fed = (fed if own is None else torch.where(own, fed, torch.zeros_like(fed))).sum()
            self.energy["fed"] = self.energy.get("fed", 0.0) + fed
        if self.active_set is not None:
            self.active_set.pad(new.n)
        self.fluid_mask = self.state.phase == Phase.FLUID
        self.n_fluid = int(self.fluid_mask.sum())
        return new, self.comm.place_new(self, new.n)

    def _remove_escaped(self, t: float, H_half=None):
        """At a rebuild point (the step would rebuild the neighbour list anyway: an escaping
        particle is a fast one, and its rows and columns go with the rebuild), remove the
        particles outside the scene (``escape.outside``), booking their mass and stored energy
        (``escaped``, a loss in the energy balance). Every process removes the same particles
        (owned rows and their ghost copies, by id). Returns (whether a rebuild is due, the
        kept-rows mask or None). ``H_half()``: the specific enthalpy at the half step, what the
        particles hold in the energy balance at this point of the step (the flows to them are
        booked up to it)."""
        due = self._stale or self.nl.needs_rebuild(self.state.x, self._moving_rows())
        if self.comm.size > 1:
            due = self.comm.any(due)
        if not due:
            return False, None
        s = self.state
        out = self.escape.outside(s.x, t)
        own = self.comm.owned(self)
        mine = out if own is None else out & own
        ids = self.comm.union_ids(s.id[mine])
        if ids.numel() == 0:
            return True, None
        keep = ~torch.isin(s.id, ids.to(s.id.device))
        self.escape.book(int(mine.sum()), float(s.m[mine].sum()))
        if self.thermal is not None:
            lost = (s.m * H_half())[mine].sum()
            self.energy["escaped"] = self.energy.get("escaped", 0.0) - lost
            th = self.thermal  # neighbours change: the geometry is evaluated afresh
            th._zeta_ok = th._area_ok = None
        n = s.n
        self.set_particle_arrays({k: v[keep] for k, v in self.particle_arrays().items() if v.shape[0] == n})
        self.comm.drop_rows(self, keep)
        self._T_prev = self._T_prev[keep]
        self._stale = True
        return True, keep

    def _resting_body(self, rows: torch.Tensor):
        """For each of ``rows``: the rigid body with the largest kernel weight among its
        solid neighbours (0 where no solid is near)."""
        s = self.state
        nb = self.nl.table.gather(rows)[0]
        m = self.fluid_model
        solid = (s.phase == Phase.SOLID).to(s.dtype)
        best = torch.zeros(rows.numel(), dtype=torch.long, device=s.device)
        best_w = torch.zeros(rows.numel(), dtype=s.dtype, device=s.device)
        for b in range(1, self.body_velocity.shape[0]):  # a loop over bodies (a handful)
            w = solid * (s.body == b).to(s.dtype)
            _, sW = neighbour_average(s.x, s.v, rows, nb, w, m.kernel, m.h, self.domain)
            take = sW > best_w
            best = torch.where(take, torch.full_like(best, b), best)
            best_w = torch.where(take, sW, best_w)
        return best

    def _solid_velocity(self, rows: torch.Tensor):
        """Shepard average of the rigid-solid neighbours' velocity around ``rows`` (the
        velocity of the body a particle rests on) and whether any solid is near."""
        s = self.state
        nb = self.nl.table.gather(rows)[0]
        solid = (s.phase == Phase.SOLID).to(s.dtype)
        m = self.fluid_model
        avg, sW = neighbour_average(s.x, s.v, rows, nb, solid, m.kernel, m.h, self.domain)
        return avg, sW > 0

    def _update_phases(self, dt: float):
        """Solid particles above T_L join the fluid (and leave their body); fluid particles
        below T_S join the rigid body they rest on (the one with the largest kernel weight
        among their solid neighbours) and take its velocity; fluid in the mushy zone is dragged towards
        the local solid velocity with the Carman-Kozeny rate C (1 - phi)^2 / (phi^3 + 1e-3),
        integrated exactly (u - u_s decays as exp(-rate dt)), so any C is stable.
        Carman-Kozeny rather than a viscosity ramp: the harmonic mean of (3.8) lets the
        low melt viscosity dominate a pair, so a viscosity ramp barely damps."""
        T_S, T_L, C = self.phase_change
        s = self.state
        melt = (s.phase == Phase.SOLID) & (s.T > T_L)
        freeze = (s.phase == Phase.FLUID) & (s.T < T_S)
        n_melt, n_freeze = torch.stack([melt.sum(), freeze.sum()]).tolist()
        g_melt, g_freeze = self.comm.sum([n_melt, n_freeze])  # every process re-selects together
        if n_freeze:  # join the body it rests on and take that body's velocity
            rows = torch.nonzero(freeze).squeeze(1)
            b = self._resting_body(rows)
            v_b = self.body_velocity.index_select(0, b)
            s.v = s.v.index_copy(0, rows, torch.where((b > 0).unsqueeze(-1), v_b, s.v.index_select(0, rows)))
            s.body = s.body.index_copy(0, rows, b)
            s.phase = torch.where(freeze, torch.full_like(s.phase, int(Phase.SOLID)), s.phase)
        if n_melt:  # melt leaves its body
            s.phase = torch.where(melt, torch.full_like(s.phase, int(Phase.FLUID)), s.phase)
            s.body = torch.where(melt, torch.zeros_like(s.body), s.body)
        if g_melt or g_freeze:
            self.fluid_mask = s.phase == Phase.FLUID
            self.n_fluid = int(self.fluid_mask.sum())
            self._select()
            self.dvdt = torch.zeros_like(s.v)
            self.drhodt = torch.zeros_like(s.rho)
            if self.fluid is not None:  # accelerations and pair geometry of the new fluid set
                self.dvdt = self._accelerations(s.v)
        if self.fluid is None or C <= 0:
            return
        rows = self.fluid_model.rows_f
        T = s.T.index_select(0, rows)
        phi = ((T - T_S) / (T_L - T_S)).clamp(0.0, 1.0)
        rate = C * (1.0 - phi) ** 2 / (phi**3 + 1e-3)
        v_s, near = self._solid_velocity(rows)
        v = s.v.index_select(0, rows)
        decay = torch.where(near, torch.exp(-rate * dt), torch.ones_like(rate)).unsqueeze(-1)
        s.v = s.v.index_copy(0, rows, v_s + (v - v_s) * decay)

    def energy_balance(self) -> dict:
        """Energy bookkeeping (J) since the start: absorbed beam energy, heat from the walls
        (conduction), radiated / convected / evaporated energy (negative), the change of the
        stored energy sum m h(T), and the residual stored - (sum of the flows)."""
        if self.thermal is None:
            return {}
        own = self.comm.owned(self)
        st = self.state
        stored = self.thermal.energy(st, self.thermal.prm, 0.0, own) - self._E0
        keys = self.comm.union_keys(self.energy)
        vals = self.comm.sum([stored] + [float(self.energy.get(k, 0.0)) for k in keys])
        stored, energy = vals[0], dict(zip(keys, vals[1:]))
        out = {f"{k}_J": v for k, v in energy.items()}  # gains > 0, losses < 0
        flows = sum(energy.values())
        out["stored_J"] = stored
        out["residual_J"] = stored - flows
        ref = max(sum(abs(v) for v in energy.values()), 1e-300)
        out["residual_rel"] = abs(out["residual_J"]) / ref
        return out

    def _damping_rate(self, t: float) -> float:
        """Settling drag -zeta(t) u: zeta = (10 / T) (1 + cos(pi t / T)) / 2, ramped to zero
        at t = T (numerics.damping_time_s), so a scene starting from a lattice can relax to
        equilibrium (e.g. a hydrostatic tank) before it is measured."""
        T = self.damping_time
        return 10.0 / T * 0.5 * (1.0 + math.cos(math.pi * t / T))

    def _check_finite(self, v_eval, dt: float = 0.0, limit: str = "-"):
        m = self.info
        if self.fluid is None:
            if not bool(torch.isfinite(self.state.T).all()):
                k = int(torch.nonzero(~torch.isfinite(self.state.T))[0])
                lim = getattr(self, "_pre_limits", None) or self.limits()
                bname = min(lim, key=lim.get)
                # the heat terms at the particle, from the last good temperatures
                _, parts = self.thermal.power(self.state, self._T_prev, self.t, per_particle=True)
                mags = {n: abs(float(torch.nan_to_num(v[k], nan=float("inf")))) for n, v in parts.items()}
                term = max(mags, key=mags.get)
                over = sorted(((dt / v, n) for n, v in lim.items() if dt > v), reverse=True)
                raise SimulationError(
                    f"blow-up at step {self.step}, t = {self.t:.6g} s: non-finite temperature at "
                    f"particle id {int(self.state.id[k])}; largest term there: {term} "
                    f"({mags[term]:.3g} W); dt used {dt:.3g} s ({limit}), binding dt limit before the "
                    f"step: {bname} = {lim[bname]:.3g} s"
                    + ("; dt exceeded " + ", ".join(f"{n} x{f:.3g}" for f, n in over) if over else ""))
            return
        bad_nan = not (math.isfinite(m["vmax"]) and math.isfinite(m["amax"]))
        bad_comp = m["compression"] > self.max_compression
        if not (bad_nan or bad_comp):
            return
        s = self.state
        saved = self.state
        self.state = s.clone()
        try:
            _, parts = self._accelerations(v_eval, terms=True)
        finally:
            self.state = saved
        if bad_nan:
            score = ~torch.isfinite(self.dvdt).all(-1) | ~torch.isfinite(s.v).all(-1)
            k = int(torch.nonzero(score)[0]) if bool(score.any()) else 0
            what = "non-finite velocity or acceleration"
        else:
            comp = (s.rho / self.fluid.prm.rho0 - 1.0).abs() * self.fluid_mask
            k = int(comp.argmax())
            what = (f"density {float(s.rho[k]):.4g} is {float(comp[k]) * 100:.0f} % off rho0 "
                    f"(limit {self.max_compression * 100:.0f} %): the weakly compressible model broke")
        mags = {name: float(torch.nan_to_num(t[k], nan=float("inf")).norm()) for name, t in parts.items()}
        term = max(mags, key=mags.get)
        lim = getattr(self, "_pre_limits", None) or self.limits()
        bname = min(lim, key=lim.get)
        lim_txt = f"binding dt limit before the step: {bname} = {lim[bname]:.3g} s"
        if dt > lim[bname]:
            over = sorted(((dt / v, k) for k, v in lim.items() if dt > v), reverse=True)
            lim_txt += "; dt exceeded " + ", ".join(f"{k} x{f:.3g}" for f, k in over)
        pos = ", ".join(f"{c:.4g}" for c in s.x[k].tolist())
        raise SimulationError(
            f"blow-up at step {self.step}, t = {self.t:.6g} s: {what} at particle id "
            f"{int(s.id[k])} (x = [{pos}]); largest term there: {term} "
            f"(|a| = {mags[term]:.3g} m/s^2); dt used {dt:.3g} s ({limit}), {lim_txt}")
