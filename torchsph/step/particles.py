"""The per-particle array registry and the particle set's changes.

One list of every per-particle array a step carries to the next (the state, the rates, the
Verlet reference positions and each term's caches), by name: checkpoints, the MPI
migration and ghost refresh, and particle insertion and removal all go through it, and
:func:`rearm` puts a swapped particle set back into a simulation (the one sequence after a
checkpoint restore, a migration and a decomposed restart)."""
from __future__ import annotations

import torch

from torchsph.core.schema import CaseError
from torchsph.core.state import FIELDS, Array, ParticleState, Phase

# the simulation's own per-particle arrays: the rates carried from one step to the next
RATES = {
    "dvdt": Array("acceleration at the end of the last step", "m/s^2", output="acceleration", vector=True),
    "drhodt": Array("density rate of the last continuity sum", "kg/(m^3 s)", output="density_rate"),
    "dTdt": Array("specific enthalpy rate dh/dt of the last heat evaluation", "W/kg", output="enthalpy_rate"),
}
# names written by earlier versions (a global MPI checkpoint stores the registry's names)
RENAMED = {"th._zeta": "th.zeta_cache", "th._area": "th.area_cache", "th._zeta_ok": "th.zeta_ok",
           "th._area_ok": "th.area_ok", "th._zeta_prev": "th.zeta_prev", "th._area_prev": "th.area_prev",
           "th._normal_prev": "th.normal_prev"}


def holders(sim) -> dict:
    """Every object of ``sim`` that holds per-particle arrays (:class:`torchsph.core.state.Holder`),
    by its prefix: the neighbour list, the active set, the physics and the composable terms
    (those a scene does not build are absent)."""
    objs = [sim.nl, sim.thermal, sim.surface_model, sim.active_set, *sim.terms]
    return {o.array_prefix: o for o in objs if o is not None}


def declared(sim) -> dict[str, Array]:
    """The declaration of every per-particle array ``sim`` may hold, by registry name."""
    d = {f"state.{k}": Array(f.doc, f.unit, output=f.dataset) for k, f in FIELDS.items()}
    d.update(RATES)
    for prefix, o in holders(sim).items():
        d.update({f"{prefix}.{k}": a for k, a in o.ARRAYS.items()})
    return d


def lazy_caches(sim) -> frozenset:
    """The per-particle caches built lazily (some processes of a decomposed run may not hold
    them): where a checkpoint or a migration does not carry one, it is dropped and rebuilt
    whole."""
    return frozenset(k for k, a in declared(sim).items() if a.lazy)


def particle_arrays(sim, with_table: bool = False) -> dict[str, torch.Tensor]:
    """Every per-particle array the step carries from one step to the next, by name (None
    entries omitted): the state, the rates and every holder's declared arrays. ``with_table``:
    also those that belong to the neighbour table (``travels=False``: what a checkpoint of
    one process keeps with the table)."""
    d = {f"state.{k}": getattr(sim.state, k) for k in FIELDS}
    d.update({k: getattr(sim, k) for k in RATES})
    for prefix, o in holders(sim).items():
        held = o.arrays()
        odd = set(held) - set(o.ARRAYS)
        if odd:
            raise TypeError(f"{type(o).__name__} holds arrays it does not declare in ARRAYS: {sorted(odd)}")
        d.update({f"{prefix}.{k}": v for k, v in held.items() if with_table or o.ARRAYS[k].travels})
    return {k: v for k, v in d.items() if v is not None}


def set_particle_arrays(sim, d: dict[str, torch.Tensor]):
    """Put arrays named as in :func:`particle_arrays` back (after a permutation)."""
    st = {k[6:]: v for k, v in d.items() if k.startswith("state.")}
    if st:
        sim.state = ParticleState(**st)
    owners = holders(sim)
    for k, v in d.items():
        k = RENAMED.get(k, k)
        if k.startswith("state."):
            continue
        if k in RATES:
            setattr(sim, k, v)
            continue
        owner, name = k.split(".", 1)
        owners[owner].set_array(name, v)
    fluid_set(sim)


def output_names(sim) -> dict[str, str]:
    """What ``[run] fields`` may name: each offered array's output name -> its registry name."""
    return {a.output: k for k, a in declared(sim).items() if a.output is not None and not k.startswith("state.")}


def output_fields(sim, names) -> dict[str, str]:
    """``[run] fields``: dataset name -> registry name, for each name given (an output name, or
    a registry name such as ``sf.kappa``); an array this simulation does not hold is refused
    naming the key, the value and what is allowed."""
    offered, dec = output_names(sim), declared(sim)
    out = {}
    for name in names:
        if name in offered:
            out[name] = offered[name]
        elif name in dec and not name.startswith("state."):
            out[name] = name
        else:
            raise CaseError(f"[run] fields = {list(names)!r}: no per-particle array {name!r} in this case "
                            f"(allowed: {', '.join(sorted(offered))}, or a registry name: "
                            f"{', '.join(k for k in dec if not k.startswith('state.'))})")
    return out


def field_values(sim, fields: dict[str, str]) -> dict[str, torch.Tensor]:
    """The arrays of ``fields`` (:func:`output_fields`) as held now: one not held at this
    moment (a lazily built cache, not yet built) is NaN on every particle."""
    held, dec = particle_arrays(sim, with_table=True), declared(sim)
    out = {}
    s = sim.state
    for dataset, key in fields.items():
        v = held.get(key)
        if v is None:
            v = torch.full((s.n, s.dim) if dec[key].vector else (s.n,), float("nan"), dtype=s.dtype, device=s.device)
        out[dataset] = v
    return out


def rearm(sim, arrays: dict[str, torch.Tensor], table=None):
    """Put per-particle arrays (named as in :func:`particle_arrays`) into ``sim`` after its
    particles were swapped (a checkpoint restored, a migration between ranks): the arrays
    first; then every lazily built cache that ``arrays`` does not hold is dropped (it is
    rebuilt whole when next needed, never left over from the particles before: a cache kept
    from other rows is wrong); ``table()`` (if given) sets the neighbour table; the pair
    subsets are selected anew, which resets the per-rebuild caches, and the given ones are
    put back; the fluid's pair geometry (what the next continuity sum reuses) is
    recomputed, the rates kept."""
    arrays = {RENAMED.get(k, k): v for k, v in arrays.items()}
    sim.lim_cache = None  # the limits the last step read were of other particles
    held = particle_arrays(sim, with_table=True)
    set_particle_arrays(sim, arrays)
    owners, lazy = holders(sim), lazy_caches(sim)
    for k in held:
        if k in lazy and k not in arrays:
            owner, name = k.split(".", 1)
            owners[owner].set_array(name, None)
    if sim.thermal is not None:  # (the conduction operator names particles by row)
        sim.thermal.op = None
    if table is not None:
        table()
    sim.select_pairs()
    caches = tuple(f"{p}." for p, o in owners.items() if o.put_back_after_selection)
    set_particle_arrays(sim, {k: v for k, v in arrays.items() if k.startswith(caches)})
    if sim.fluid is not None:
        saved = sim.dvdt.clone()  # (the evaluation may write into the same reused array)
        sim.fluid.momentum(sim.state, sim.state.v)  # sets p and the cached geometry only
        sim.dvdt = saved


def add_particles(sim, new: ParticleState):
    """Append particles (e.g. a fed wire's new layer) at rest relative to their body, with
    zero rates; the neighbour list is rebuilt at the next rebuild point (forced). Every
    process of a decomposed run is given the same ``new`` and keeps the ones in its slab.
    Returns (the particles added here, the row permutation the decomposition applied to
    keep its own rows first, or None)."""
    sim.stale = True
    if sim.thermal is not None:  # on every process: the geometry is evaluated afresh
        sim.thermal.forget_geometry()
    new, own = sim.comm.claim(sim, new)
    if new.n == 0:
        return new, None
    z = lambda t: torch.cat([t, torch.zeros((new.n,) + t.shape[1:], dtype=t.dtype, device=t.device)])  # noqa: E731
    sim.state = ParticleState.cat([sim.state, new])
    if sim.nl.x_mig is not None:  # (a decomposition measures their motion from here)
        sim.nl.x_mig = torch.cat([sim.nl.x_mig, new.x])
    sim.dvdt, sim.drhodt = z(sim.dvdt), z(sim.drhodt)
    if sim.dTdt is not None:
        sim.dTdt = z(sim.dTdt)
        sim.thermal.add_particles(new)
        # the enthalpy the new particles bring in (the stored energy counts it)
        fed = new.m * sim.thermal.to_enthalpy(new.T)
        fed = (fed if own is None else torch.where(own, fed, torch.zeros_like(fed))).sum()
        sim.energy["fed"] = sim.energy.get("fed", 0.0) + fed
    if sim.active_set is not None:
        sim.active_set.pad(new.n)
    for term in sim.terms:
        term.add_particles(new)
    fluid_set(sim)
    return new, sim.comm.place_new(sim, new.n)


def remove_escaped(sim, t: float, H_half=None):
    """At a rebuild point (the step would rebuild the neighbour list anyway: an escaping
    particle is a fast one, and its rows and columns go with the rebuild), remove the
    particles outside the scene (``sim.escape.outside``), booking their mass and stored
    energy (``escaped``, a loss in the energy balance). Every process removes the same
    particles (owned rows and their ghost copies, by id). Returns (whether a rebuild is due,
    the kept-rows mask or None). ``H_half()``: the specific enthalpy at the half step, what
    the particles hold in the energy balance at this point of the step (the flows to them
    are booked up to it)."""
    due = sim.nl.needs_rebuild(sim.state.x, sim.moving_rows(), sim.comm) or sim.stale  # (every process takes part)
    if sim.comm.size > 1:
        due = sim.comm.any(due)
    if not due:
        return False, None
    s = sim.state
    out = sim.escape.outside(s.x, t)
    own = sim.comm.owned(sim)
    mine = out if own is None else out & own
    ids = sim.comm.union_ids(s.id[mine])
    if ids.numel() == 0:
        return True, None
    keep = ~torch.isin(s.id, ids.to(s.id.device))
    sim.escape.book(int(mine.sum()), float(s.m[mine].sum()))
    if sim.thermal is not None:
        lost = (s.m * H_half())[mine].sum()
        sim.energy["escaped"] = sim.energy.get("escaped", 0.0) - lost
        sim.thermal.forget_geometry()  # neighbours change: the geometry is evaluated afresh
    n = s.n
    set_particle_arrays(sim, {k: v[keep] for k, v in particle_arrays(sim).items() if v.shape[0] == n})
    sim.comm.drop_rows(sim, keep)
    sim.T_prev = sim.T_prev[keep]
    sim.stale = True
    return True, keep


def fluid_set(sim):
    """The fluid set after particles changed phase, were added or removed (not re-selected)."""
    sim.fluid_mask = sim.state.phase == Phase.FLUID
    sim.n_fluid = int(sim.fluid_mask.sum())
