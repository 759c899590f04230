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

import torch

from torchsph.core.neighbors import Domain
from torchsph.core.state import ParticleState, Phase
from torchsph.core.verlet import VerletList
from torchsph.physics.conduction_window import end_rows, live_rows, slow_factor, start_step
from torchsph.physics.enthalpy import stored_energy
from torchsph.physics.fluid import Embedded, WeaklyCompressibleFluid
from torchsph.physics.surface import SurfaceForces
from torchsph.physics.terms import available as available_terms
from torchsph.physics.thermal import Conduction
from torchsph.step import bookkeeping, diagnosis, particles, rates, stages
from torchsph.step import integrator as step
from torchsph.step import limits as step_limits
from torchsph.step.active import ActiveSet
from torchsph.step.comm import SerialComm
from torchsph.step.limits import LIMIT_FORMULAS, SimulationError, StepInfo, UnstableStepError  # noqa: F401 (re-exported)
from torchsph.step.phases import PhaseChange
from torchsph.step.stats import PlanStats


class Simulation:
    """Single-process solver: owns the state, the neighbour list and the clock."""

    def __init__(self, state: ParticleState, fluid: WeaklyCompressibleFluid | None, domain: Domain,
                 skin: float, cfl: float = 0.25, dt_fixed: float | None = None,
                 allow_unstable_dt: bool = False, max_compression: float = 0.3, dx: float = 0.0,
                 damping_time: float = 0.0, thermal: Conduction | None = None,
                 phase_change: tuple[float, float, float] | None = None,
                 surface: SurfaceForces | None = None, active: ActiveSet | None = None,
                 feeder=None, comm=None, escape=None, partial_rebuild: bool = True, terms=()):
        """``fluid`` and ``thermal`` are the physics a scene declares; either may be None
        and then costs nothing (a conduction study has no momentum, a flow no energy).
        ``active`` leaves cold quiescent solid out of the work (:mod:`torchsph.step.active`);
        ``feeder`` adds particles as the run goes (``new_particles(sim, t)``, e.g. a fed
        wire); ``escape`` says which particles have left the scene for good
        (``outside(x, t)``, :class:`~torchsph.scenes.deposition.EscapeBox`): they are removed at the
        next neighbour rebuild. ``partial_rebuild``: neighbour rebuilds keep the largest rigid
        body's mutual pairs and search only the other rows (:class:`~torchsph.core.verlet.VerletList`;
        scenes with fluid; a decomposed run's first rebuild after a migration is a full one). ``terms``: the composable terms the case names
        (:mod:`torchsph.physics.terms`), each evaluated at its hooks and nowhere else."""
        self.state = state
        self.terms = list(terms)
        self.heat_terms = [t for t in self.terms if "heat" in t.writes]
        self.force_terms = [t for t in self.terms if "acceleration" in t.writes]
        if (self.heat_terms and thermal is None) or (self.force_terms and fluid is None):
            raise ValueError("Simulation: a heat term needs the thermal model, a force term the fluid model")
        self.comm = comm if comm is not None else SerialComm()  # decomposition hooks (no-ops in one process)
        self.rebuilt = False  # the last step rebuilt the neighbour list
        self.new_body_velocity = False
        self.active_set = active if (active is not None and not domain.any_periodic) else None
        self.feeder = feeder
        self.escape = escape
        self.plan = PlanStats()
        self.fluid_mask = state.phase == Phase.FLUID
        self.n_fluid = int(self.fluid_mask.sum())
        self.fluid_model = fluid  # active only while there are fluid particles
        # the rate arrays, reused from step to step in one process (torchsph.physics.fluid.Embedded)
        self.outs = {k: Embedded() for k in ("dvdt", "drhodt", "dTdt")} if self.comm.size == 1 else {}
        if fluid is not None:
            fluid.outs = self.outs
        self.thermal = thermal
        self.surface_model = surface  # free-surface forces; active with the fluid
        if surface is not None and fluid is None:
            raise ValueError("Simulation: surface forces need the fluid model")
        # (T_S, T_L, C): solids melt above T_L, melt freezes below T_S, mushy drag C
        self.phase_change = PhaseChange(*phase_change) if isinstance(phase_change, tuple) else phase_change
        if phase_change is not None and (fluid is None or thermal is None):
            raise ValueError("Simulation: phase change needs both the fluid and the thermal model")
        # velocity of each rigid body (row b = body b; row 0 unused), from its solid particles
        self.body_velocity = bookkeeping.body_velocities(self, state)
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
        self.partial_rebuild = partial_rebuild and fluid is not None
        self.t = 0.0
        self.step = 0
        self.stale = False  # the active set must be refreshed at the next rebuild point
        if thermal is not None:
            thermal.comm, thermal.owned = self.comm, self.comm.owned(self)
        if surface is not None:
            surface.sum_owned = self.comm.sum_owned
        if self.active_set is not None and thermal is not None:
            thermal.lit = thermal.lit_mask(state, 0.0)  # the beams' footprint seeds the active set
        self.fields = stages.Fields(self.terms, set(particles.declared(self)), available_terms())  # (a read with no writer: refused)
        self.refresh_pairs(force=True)
        stages.evaluate_fields(self)
        self.dvdt = torch.zeros_like(state.v)
        self.drhodt = torch.zeros_like(state.rho)
        if self.fluid is not None:
            self.dvdt = self.accelerations(state.v)
            self.drhodt, _ = self.fluid.continuity(state.v, state.m)
        self.dTdt = None  # specific enthalpy rate dh/dt (W/kg) when the scene has heat
        self.energy = {}  # J by kind (beam, conduction from walls, losses), integrated as the step does
        self.heat_totals = {}  # W by kind at the last evaluation (the trapezoid's left end)
        self.E0 = None  # J, the stored energy at the start
        self.T_prev = state.T  # the temperatures before the step (for a diagnosis)
        if thermal is not None:
            P, self.heat_totals = rates.heat_power(self, state.T, 0.0)
            self.dTdt = P / state.m
            self.E0 = stored_energy(state, thermal.prm, 0.0, self.comm.owned(self))
        self.comm.end_step(self)  # ghosts (if any) take their owners' values
        self.rebuilt = False  # the set-up build needs no migration
        self.info = self.measure()
        diagnosis.check_finite(self, state.v)
        self.T_seen = self.state.T if self.active_set is not None else None
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

    def accelerations(self, v_eval, terms: bool = False):
        """The momentum equation's rates (:func:`torchsph.step.rates.accelerations`)."""
        return rates.accelerations(self, v_eval, terms)

    # --- neighbours ---------------------------------------------------------
    def refresh_pairs(self, force: bool = False):
        stale = self.stale
        subset = (lambda: bookkeeping.work_set(self, stale)) if self.active_set is not None else None
        force = force or stale
        if not force and self.comm.size > 1:  # all processes rebuild at the same steps
            force = self.nl.needs_rebuild(self.state.x, self.moving_rows(), self.comm)
            if not force:
                return
        rigid = (lambda: bookkeeping.rigid_groups(self)) if self.partial_rebuild else None
        if self.nl.update(self.state.x, force=force, subset=subset, rigid=rigid, rows=self.moving_rows()):
            self.stale = False
            self.rebuilt = True
            self.nl.body_ref = bookkeeping.rigid_of(self.state.phase, self.state.body)  # whose motion is their body's from here
            self.select_pairs(new_table=True)
            self.moving_rows()  # for the new work set, at the rebuild

    def rebuild(self):
        """Build the neighbour table now, between steps (a tool, a state set from outside), and evaluate
        the accelerations on it (the next step's continuity reads that evaluation's pair geometry)."""
        self.refresh_pairs(force=True)
        stages.evaluate_fields(self)
        if self.fluid is not None:
            self.dvdt = self.accelerations(self.state.v)

    moving = moving_for = moving_key = None  # the rows of moving_rows() and what they were made for

    def moving_rows(self) -> torch.Tensor | None:
        return bookkeeping.moving_rows(self)

    @property
    def active_mask(self) -> torch.Tensor | None:
        return self.active_set.active if self.active_set is not None else None

    n_selections = 0  # pair selections so far (a decomposition refreshes every ghost after one)

    def select_pairs(self, new_table: bool = False):
        """Every model's pair subsets of the current table (:func:`torchsph.step.bookkeeping.select_pairs`)."""
        bookkeeping.select_pairs(self, new_table)

    # --- time-step control (torchsph.step.limits) --------------------------------
    T_seen = None  # with an active set: the temperatures the last step left (others were set by hand)
    lim_cache = None  # (step, n, limits) of choose_dt, which advance() reuses (same state)
    pre_limits = None  # the limits before the step being taken (for a diagnosis)

    def measure(self) -> dict[str, float]:
        return step_limits.measure(self)

    def limits(self) -> dict[str, float]:
        """Every time-step limit of SPEC §4 that applies to this scene (seconds)."""
        return step_limits.limits(self)

    def choose_dt(self) -> tuple[float, str]:
        """The step's dt and its binding limit: from the limits the last step read at its
        end (the state has not changed since), else read now."""
        c = self.lim_cache
        lim = c[2] if c is not None and c[:2] == (self.step, self.state.n) else self.limits()
        self.lim_cache = (self.step, self.state.n, lim)
        if self.dt_fixed is not None:
            return self.dt_fixed, "fixed"
        name, val = step_limits.binding(lim)
        return val, name

    def binding_limit(self) -> tuple[str, float]:
        return step_limits.binding(self.limits())

    def check_fixed_dt(self):
        """Refuse a fixed dt above any stability limit unless the case allows it."""
        formulas = {k: v for term in self.terms for k, v in term.limit_formulas.items()}
        step_limits.check_fixed_dt(self.dt_fixed, self.limits(), self.allow_unstable_dt, formulas)

    # --- one step -----------------------------------------------------------
    def advance(self, dt: float | None = None, limit: str = "given") -> StepInfo:
        """One kick-drift-kick step; dt defaults to the automatic (or fixed) step."""
        cache, self.lim_cache = self.lim_cache, None
        self.pre_limits = (cache[2] if cache is not None and cache[:2] == (self.step, self.state.n)
                           else self.limits())  # of the last good state, for a diagnosis
        if dt is None:
            dt, limit = self.choose_dt()
        if self.T_seen is not None and self.state.T is not self.T_seen and self.comm.size == 1:
            self.stale = True  # temperatures set from outside the step: the active set is refreshed now
        self.comm.begin_step(self)  # migration and new ghosts after a rebuild (decomposed runs)
        self.rebuilt = False
        self.T_prev = self.state.T
        th = self.thermal
        rows_start = start_step(th) if th is not None else None  # between windows, the frozen rows wait
        def scalar(v: float) -> torch.Tensor:  # a 0-d tensor for the traced parts (a fill: no copy, no read)
            return torch.full((), v, dtype=torch.float64, device=self.state.device)
        dt_t = scalar(dt)
        if self.fluid is not None and self.fluid.prm.gravity_ramp > 0:  # the accelerations at t + dt see g(t + dt)
            self.fluid.ramp_gravity(self.t + dt)
        half = step.first_half(self, dt_t)  # 1a-1e
        self.comm.after_drift(self)
        v_half, v_tilde, rows0, H_half_r, inv = half[:5]
        vh_f = half.vh_f  # (in place: the state's v holds u~; whole arrays only where particles change)
        fr_half = self.fluid.fluid_rows if vh_f is not None else None
        T0 = self.T_prev
        H_half = None  # the whole array, made only where particles are added, removed or re-selected

        def whole_H_half():
            return self.thermal.to_enthalpy(T0).index_copy_(0, rows0, H_half_r)
        answers = bookkeeping.mid_step_read(self, (rows0, inv) if self.thermal is not None else None)  # one read
        if self.feeder is not None:  # new particles enter at t + dt
            new = self.feeder.new_particles(self, self.t + dt, answers)
            if new is not None and new.n:
                if vh_f is not None:
                    v_half, v_tilde = step.whole_velocities(self.state, half, fr_half)
                    vh_f = None
                new, perm = particles.add_particles(self, new)  # this process's share of them
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
        due = None
        if self.escape is not None:  # at a rebuild point: particles that have left the scene go
            due, keep = particles.remove_escaped(self, self.t + dt, (lambda: whole_H_half() if H_half is None else H_half)
                                             if self.thermal is not None else None)
            if keep is not None:
                if vh_f is not None:  # (the state holds its kept rows already)
                    v_half, v_tilde = step.whole_velocities(self.state, half, fr_half, keep)
                    vh_f = None
                else:
                    v_half, v_tilde = v_half[keep], v_tilde[keep]
                if self.thermal is not None:
                    H_half = (whole_H_half() if H_half is None else H_half)[keep]
                    new_row = torch.cumsum(keep.long(), 0) - 1
                    rows0 = new_row.index_select(0, rows0[keep.index_select(0, rows0)])
        if due is None:
            self.refresh_pairs()
        elif due:  # decided above (on every process): no second test, no second collective
            self.refresh_pairs(force=True)
        stages.evaluate_fields(self)  # the terms' fields, before the rates read them
        damping = None  # the settling drag (numerics.damping_time_s)
        if self.fluid is not None and self.t + dt < self.damping_time:
            damping = scalar(step_limits.damping_rate(self.damping_time, self.t + dt))
        step.close_momentum(self, dt_t, damping, v_half, v_tilde, vh_f)  # 2, 3c
        if vh_f is not None:  # u~, for a diagnosis only: made if one is due
            fr, vt_f = fr_half, half.vt_f
            v_tilde = lambda: self.state.v.index_copy(0, fr, vt_f)  # noqa: E731
        ending = None
        if th is not None:  # the rows of the end's temperatures, and their h_{n+1/2}
            th.prepare(self.state)  # a new selection's cached values, outside the traced parts
            f = slow_factor(th, self.t, dt, self.pre_limits)  # the slow rows' window closes (host numbers)
            th.slow_now, th.closed = (None, False) if f is None else (scalar(f), True)
            rows = end_rows(th, rows0, rows_start)
            if H_half is None and rows is rows0:
                Hh = H_half_r
            else:
                Hh = (whole_H_half() if H_half is None else H_half).index_select(0, rows)
            ending = step.close_energy(self, dt_t, scalar(self.t + dt), rows, Hh)  # 2, 3b
            th.slow_now = None
        self.t += dt
        self.step += 1
        flags = bookkeeping.finish_step(self, dt, ending)
        if th is not None:
            th.partial_next, th.closed = not self.heat_terms and live_rows(th) is th.int_rows, False
        diagnosis.check_finite(self, v_tilde, dt, limit, flags.get("T_ok"))
        self.plan.add(self)
        if self.active_set is not None:
            self.T_seen = self.state.T
        return StepInfo(dt, limit, self.info["vmax"], self.info["amax"])

    def set_body_velocity(self, body: int, v: torch.Tensor):
        """Change a rigid body's velocity; its solid particles take it at the end of the step."""
        self.body_velocity[body] = v
        self.new_body_velocity = True

    # --- the particle set (torchsph.step.particles) ---------------------------------
    def particle_arrays(self) -> dict[str, torch.Tensor]:
        """Every per-particle array the step carries from one step to the next, by name."""
        return particles.particle_arrays(self)

    def set_particle_arrays(self, d: dict[str, torch.Tensor]):
        particles.set_particle_arrays(self, d)

    def rearm(self, arrays: dict[str, torch.Tensor], table=None):
        """Put a swapped particle set back (:func:`torchsph.step.particles.rearm`; a restore too)."""
        particles.rearm(self, arrays, table)
        self.T_seen = self.state.T if self.active_set is not None else None  # (not set by hand)

    def energy_balance(self) -> dict:
        """Energy bookkeeping (J) since the start (:func:`torchsph.step.bookkeeping.energy_balance`)."""
        return bookkeeping.energy_balance(self)
