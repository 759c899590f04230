"""Bookkeeping of a step that is not physics: which particles decide a neighbour rebuild,
the rigid group a partial rebuild keeps, the active set's work mask, the rigid bodies'
velocities and the energy balance. Functions of a :class:`~torchsph.step.simulation.Simulation`."""
from __future__ import annotations

import torch

from torchsph.core.state import ParticleState, Phase
from torchsph.physics.enthalpy import stored_energy
from torchsph.step import limits as step_limits
from torchsph.step import rates
from torchsph.step.phases import undo_drag


def rigid_of(phase: torch.Tensor, body: torch.Tensor) -> torch.Tensor:
    """Each particle's rigid body (solid with a body > 0), -1 where it is not rigid."""
    return torch.where((phase == Phase.SOLID) & (body > 0), body, torch.full_like(body, -1))


def moving_rows(sim) -> torch.Tensor | None:
    """The particles whose displacement decides a neighbour rebuild, with an active set (None,
    all, without one). A rigid body's particles move alike, so the particles that have been
    of one rigid body since the last rebuild (``nl.body_ref``, set there) are checked at one
    cold particle of it (a body with none, the whole scene heated: at its first particle still of it,
    chosen again when the phases change); every other particle is checked:
    the fluid, the walls, and the working particles that melted, froze or were welded since
    the last rebuild (their path since then is not their body's). Made at each rebuild, and
    the changed ones again when the phase or body array is replaced (a phase change, a weld)."""
    a = sim.active_set
    st = sim.state
    if a is None or a.work is None or a.work.shape[0] != st.n:
        return None
    ref = sim.nl.body_ref
    base = sim.moving_for
    if base is None or base[0] is not a.work or base[1] is not ref:
        if ref is None or ref.shape[0] != st.n:  # (a restart from an older checkpoint: all working rows)
            ref = torch.where(a.work, -1, rigid_of(st.phase, st.body))
        rigid = ref >= 0
        cold = ~a.work & rigid
        idx = torch.arange(st.n, device=st.device)
        big = torch.iinfo(torch.long).max
        first = torch.full((sim.body_velocity.shape[0],), big, dtype=torch.long, device=st.device).scatter_reduce(
            0, st.body, torch.where(cold, idx, torch.full_like(idx, big)), "amin")
        lonely = first == big  # a body with no cold particle: checked at one working particle of it
        lonely &= torch.zeros_like(lonely).index_fill_(0, ref[rigid], True)  # (bodies with rigid particles)
        keep = ~rigid
        keep.index_fill_(0, first[first != big], True)
        watch = torch.nonzero(a.work & ~keep).squeeze(1)  # of one body since the rebuild: checked once changed
        ref_w = ref.index_select(0, watch)
        base = sim.moving_for = (a.work, sim.nl.body_ref, torch.nonzero(keep).squeeze(1), watch, ref_w,
                                 lonely if bool(lonely.any()) else None)
        sim.moving_key = None
    if sim.moving_key is None or sim.moving_key[0] is not st.phase or sim.moving_key[1] is not st.body:
        _, _, keep, watch, ref_w, lonely = base
        now = rigid_of(st.phase.index_select(0, watch), st.body.index_select(0, watch))
        parts = [keep, watch[now != ref_w]]
        if lonely is not None:  # each such body's first particle still of it since the rebuild
            big = torch.iinfo(torch.long).max
            mine = (now == ref_w) & (ref_w >= 0)
            mine &= lonely.index_select(0, ref_w.clamp_min(0))
            first = torch.full_like(lonely, big, dtype=torch.long).scatter_reduce(
                0, ref_w.clamp_min(0), torch.where(mine, watch, torch.full_like(watch, big)), "amin")
            parts.append(first[first != big])  # (a body all of whose particles changed: none left to stand for)
        sim.moving = torch.cat(parts)
        sim.moving_key = (st.phase, st.body)
    return sim.moving


def rigid_groups(sim) -> torch.Tensor | None:
    """Each particle's rigid group, the particles that move together: the solid particles
    of one body (its number), the walls (0); -1 for the others (None without any)."""
    st = sim.state
    solid = (st.phase == Phase.SOLID) & (st.body > 0)
    group = torch.where(solid, st.body, torch.where(st.phase == Phase.WALL, 0, -1))
    return group if bool((group >= 0).any()) else None


def cross_rows(sim) -> torch.Tensor | None:
    """The particles whose table row may hold a partner of another rigid body, for a pair
    selection: those the last partial neighbour rebuild says so of (``VerletList.cross``), and
    those whose rigid body changed since (melted, froze, welded). None where it is not known (a
    full build, a decomposed run): the selection then reads every row outside the largest body."""
    nl, st = sim.nl, sim.state
    if (sim.comm.size > 1 or nl.cross is None or nl.body_ref is None or nl.cross.shape[0] != st.n
            or nl.body_ref.shape[0] != st.n):
        return None
    return nl.cross | (rigid_of(st.phase, st.body) != nl.body_ref)


def work_set(sim, stale: bool = True) -> torch.Tensor:
    """The active set's work mask at a neighbour rebuild, the set refreshed first when it is
    ``stale`` (a frontier particle became a seed, particles were added or removed), when it
    has none for these particles, or when it has kept its sets over ``ActiveSet.max_age``
    rebuilds. Otherwise the sets are kept as they are: they stay conservative, since heat,
    melt or a beam can only reach a particle outside the active set by crossing the
    frontier first, which the step checks (:meth:`ActiveSet.stale`), and kept sets keep
    the rows of the neighbour table and of the conduction operator (a refresh at every
    rebuild changed them at nearly every rebuild of the full scene: a new operator each)."""
    a = sim.active_set
    if stale or a.work is None or a.work.shape[0] != sim.state.n or a.age >= a.max_age:
        a.refresh(sim.state, rates.source_mask(sim))
    else:
        a.age += 1
    return a.work


def body_velocities(sim, state: ParticleState) -> torch.Tensor:
    """(bodies, dim): each rigid body's mean velocity over its solid particles, over all
    processes (the owned ones: ghosts are copies), so every process holds every body's row
    even where it holds none of its particles (a rank whose slab the fed wire misses)."""
    top = state.body.max().reshape(1) if state.n else torch.zeros(1, dtype=torch.long, device=state.device)
    nbody = int(sim.comm.gather_rows({"top": top})["top"].max()) + 1
    own = sim.comm.owned(sim)
    solid = state.phase == Phase.SOLID
    if own is not None:
        solid = solid & own[: state.n]
    solid = solid.to(state.dtype).unsqueeze(-1)
    tot = torch.zeros(nbody, state.dim, dtype=state.dtype, device=state.device).index_add_(
        0, state.body, state.v * solid)
    cnt = torch.zeros(nbody, 1, dtype=state.dtype, device=state.device).index_add_(0, state.body, solid)
    both = torch.tensor(sim.comm.sum(torch.cat([tot, cnt], 1).reshape(-1).tolist()),
                        dtype=state.dtype, device=state.device).view(nbody, state.dim + 1)
    return both[:, :-1] / both[:, -1:].clamp_min(1.0)


def energy_balance(sim) -> dict:
    """Energy bookkeeping (J) since the start: absorbed beam energy, heat from the walls
    (conduction), radiated / convected / evaporated energy (negative), the change of the
    stored energy sum m h(T), and the residual stored - (sum of the flows)."""
    if sim.thermal is None:
        return {}
    own = sim.comm.owned(sim)
    st = sim.state
    stored = stored_energy(st, sim.thermal.prm, 0.0, own) - sim.E0
    keys = sim.comm.union_keys(sim.energy)
    vals = sim.comm.sum([stored] + [float(sim.energy.get(k, 0.0)) for k in keys])
    stored, energy = vals[0], dict(zip(keys, vals[1:]))
    out = {f"{k}_J": v for k, v in energy.items()}  # gains > 0, losses < 0
    flows = sum(energy.values())
    out["stored_J"] = stored
    out["residual_J"] = stored - flows
    ref = max(sum(abs(v) for v in energy.values()), 1e-300)
    out["residual_rel"] = abs(out["residual_J"]) / ref
    return out


def end_flags(sim) -> dict:
    """The decisions the end of a step reads, as 0-d device tensors."""
    f = {}
    if sim.active_set is not None:  # heat reached the frontier band
        f["stale"] = sim.active_set.stale(sim.state, rates.source_mask(sim),
                                          sim.thermal.rows if sim.thermal is not None else None)
    if sim.fluid is None and sim.thermal is not None:
        f["T_ok"] = torch.isfinite(sim.state.T.index_select(0, sim.thermal.rows)).all()  # (only the rows' change)
    return f


class EndTemperatures:
    """The temperatures of a step's end on ``rows`` (an :class:`~torchsph.physics.enthalpy.Inversion`)
    and the peak temperatures before them: put in unchecked, put again fixed if the end of
    the step reads that some did not converge."""

    def __init__(self, s, rows, inv):
        self.rows, self.inv = rows, inv
        self.peak0 = s.T_peak.index_select(0, rows)  # the rows' peaks before them
        self.put(s, inv.T)

    def put(self, s, T):
        s.T.index_copy_(0, self.rows, T)  # (in place: the step's own array since its first half; T_prev keeps T_n)
        s.T_peak.index_copy_(0, self.rows, torch.maximum(self.peak0, T))


def finish_step(sim, dt: float, ending: EndTemperatures | None = None) -> dict:
    """The end of a step: melting and freezing with the mushy drag, the ghost refresh, then
    one read of everything the host needs (the measures, the next step's limits, whether a
    phase changed, whether the active set is stale, whether T is finite, whether the end's
    temperatures converged). The drag is taken first as if no phase changed and the
    temperatures were right; where not (a few steps of a run), it is undone, the
    temperatures are fixed or the phases change (the pairs re-selected), the drag is taken
    again, and the end is read again. Returns the read flags."""
    pc = sim.phase_change
    undo = None  # what puts the drag's velocities back
    check = ending is not None and ending.inv.bad is not None
    while True:
        extra = {"T_bad": ending.inv.bad.any()} if check else {}
        if pc is not None:
            part = ending is not None and ending.rows is sim.thermal.step_rows  # (between windows: the rows integrated)
            melt, freeze, counts = pc.decide(sim, ending.rows if part else None)
            undo = pc.drag(sim, dt)
            extra |= {"melt": counts[0], "freeze": counts[1]}
        sim.comm.end_step(sim)
        f = step_limits.end_of_step(sim, **end_flags(sim), **extra)
        if check and sim.comm.any(bool(f["T_bad"])):  # every process goes round again together
            undo_drag(sim, undo)
            ending.put(sim.state, ending.inv.fixed())
            check = False
            continue
        break
    if pc is not None:
        n = [int(f["melt"]), int(f["freeze"])]
        total = sim.comm.sum(n)  # every process re-selects together
        if any(total):
            undo_drag(sim, undo)
            pc.change(sim, melt, freeze, n[0], n[1], total)
            pc.drag(sim, dt)
            sim.comm.end_step(sim)
            f = step_limits.end_of_step(sim, **end_flags(sim))
    if "stale" in f and sim.comm.any(bool(f["stale"])):
        sim.stale = True  # refresh the active set at the next rebuild point
    return f


def mid_step_read(sim, temperatures=None) -> dict:
    """After the drift: the feeder's contact questions (``feeder.probe``), whether the
    neighbour list must be rebuilt (``nl.known``) and whether the extrapolated temperatures
    (``temperatures``: rows and an :class:`~torchsph.physics.enthalpy.Inversion`, put in unchecked;
    nothing has read them since) converged, read at once; those that did not are fixed."""
    q = {}
    if temperatures is not None and temperatures[1].bad is not None:
        q["T_bad"] = temperatures[1].bad.any()
    probe = getattr(sim.feeder, "probe", None)
    if probe is not None:
        q.update(probe(sim))
    m = sim.nl.motion(sim.state.x, sim.moving_rows())
    if m is not None:
        q["motion"] = m
    if not q:
        return {}
    flat = torch.cat([v.reshape(-1).to(torch.float64) for v in q.values()]).tolist()
    vals, at = {}, 0
    for k, v in q.items():
        vals[k] = flat[at] if v.dim() == 0 else flat[at:at + v.numel()]
        at += v.numel()
    if "motion" in vals:
        sim.nl.known = (sim.state.x, vals["motion"])
    if vals.get("T_bad"):
        rows, inv = temperatures
        sim.state.T = sim.state.T.index_copy(0, rows, inv.fixed())
    return vals


def select_pairs(sim, new_table: bool = False):
    """The pair subsets of every model on the neighbour table (after a rebuild, a phase change, a
    feed): each model's rows, and the terms', feeder's and plan's selections."""
    sim.n_selections += 1
    if sim.fluid is not None:
        sim.fluid.select_pairs(sim.state, sim.nl.table, level=sim.comm.levels(sim),
                               depth=getattr(sim.comm, "depth", 2))
    if sim.surface is not None:
        sim.surface.select_pairs(sim.state, sim.nl.table)
        if sim.fluid is not None:
            sim.surface.share_pairs(sim.fluid.rows_f, sim.fluid.nb_f, sim.nl.table)
    if sim.thermal is not None:
        sim.thermal.owned = sim.comm.owned(sim)
        sim.thermal.select_pairs(sim.state, sim.nl.table, active=sim.active_mask,
                                 work=getattr(sim.active_set, "work", None), cross=cross_rows(sim),
                                 x_ref=sim.nl.x_ref, new_table=new_table, reach=sim.nl.travel)
    for term in sim.terms:
        term.select(sim)
    if sim.feeder is not None and hasattr(sim.feeder, "select"):
        sim.feeder.select(sim)
    sim.plan.select(sim)
