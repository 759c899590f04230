"""MPI domain decomposition: slabs along x with ghost halos (mpi4py).

Each rank owns the particles of one slab [b_r, b_{r+1}) of x and holds, after its owned
particles, ghost copies of the particles other ranks own within ``halo`` of its slab. It
runs the unchanged single-process step on owned + ghosts; at the end of every step each
ghost takes its owner's values of every per-particle array (``Simulation.particle_arrays``:
state, rates, Verlet reference, the physics' caches). The halo is thick enough for one
step's chain of neighbour-dependent stages (``stages`` search radii, plus the Verlet skin
for the motion between migrations), so owned particles see exactly the neighbours and
values they would in one process: the decomposed run equals the single-process run up to
the order of floating-point sums.

All ranks rebuild their neighbour lists at the same steps (a global decision), so the
per-rebuild caches match the single-process run; at the start of the step after a
rebuild, particles migrate to the rank owning their slab and the ghost sets are chosen
anew (the neighbour tables are built again over the working particles at the reference positions). Slab boundaries start at
equal particle counts and are moved to equal measured cost (per-particle costs of fluid,
working solid and idle solid fitted to the ranks' measured work, :meth:`SlabComm.migrate`).
"""
from __future__ import annotations

import math
import time

import numpy as np
import torch
from mpi4py import MPI

from torchsph.step.particles import fluid_set

STATE_PREFIX = "state."


def _np(t: torch.Tensor) -> np.ndarray:
    return t.detach().cpu().numpy()


class _TimedComm:
    """An mpi4py communicator whose calls add their wall time to ``waited``: the time a
    rank spends in communication (mostly waiting for slower ranks) is told apart from its
    own work, so the load imbalance is measured on the work; ``sent`` counts the array bytes
    this rank handed to them (what leaves the rank: an alltoall's own entry is not counted)."""

    def __init__(self, comm):
        self._c = comm
        self.waited = 0.0
        self.sent = 0

    def __getattr__(self, name):
        f = getattr(self._c, name)
        if not callable(f) or name.startswith("Get_"):
            return f

        def timed(*a, **k):
            t = time.perf_counter()
            if a:
                self.sent += _payload_bytes(a[0], self._c.Get_rank() if name == "alltoall" else None)
            try:
                return f(*a, **k)
            finally:
                self.waited += time.perf_counter() - t
        return timed


def _payload_bytes(obj, skip: int | None = None) -> int:
    """The array bytes in a message (numpy arrays in dicts, lists and tuples; ``skip``: the
    entry of an alltoall list that stays on this rank)."""
    if isinstance(obj, np.ndarray):
        return obj.nbytes
    if isinstance(obj, torch.Tensor):
        return obj.numel() * obj.element_size()
    if isinstance(obj, dict):
        return sum(_payload_bytes(v) for v in obj.values())
    if isinstance(obj, (list, tuple)):
        return sum(_payload_bytes(v) for i, v in enumerate(obj) if i != skip)
    return 0


def equal_bounds(comm, size: int, x: np.ndarray, w: np.ndarray | None = None) -> np.ndarray:
    """Slab boundaries at equal (weighted) shares of all ranks' particles along x."""
    w = np.ones_like(x) if w is None else w
    xs = np.concatenate(comm.allgather(x))
    ws = np.concatenate(comm.allgather(w))
    order = np.argsort(xs, kind="stable")
    cw = np.cumsum(ws[order])
    b = [-np.inf]
    for r in range(1, size):
        k = int(np.searchsorted(cw, cw[-1] * r / size))
        k = min(max(k, 0), xs.size - 1)
        b.append(xs[order][k])
    return np.array(b + [np.inf])


def common_arrays(comm, sim):
    """The per-particle arrays every rank holds (lazily built caches may exist on some ranks
    only), and the names of the ones left out here."""
    arrays = sim.particle_arrays()
    common = set.intersection(*comm.allgather(set(arrays)))
    return {k: v for k, v in arrays.items() if k in common}, [k for k in arrays if k not in common]


class SlabComm:
    """The :class:`torchsph.step.comm.SerialComm` interface over MPI ranks (see the module doc)."""

    def __init__(self, search: float, skin: float, stages: int = 3, comm=None,
                 rebalance_every: int = 0, weights: dict | None = None, slack_skins: float = 4.0):
        self.c = _TimedComm(comm or MPI.COMM_WORLD)
        self.rank, self.size = self.c.Get_rank(), self.c.Get_size()
        # the halo: the step's chain of stages, plus the motion between migrations: the
        # Verlet skin and the slack (a migration is due once some particle has moved half
        # the slack since the last: until then a rebuild keeps the rows, ghosts and caches)
        self.slack = slack_skins * skin
        self.halo = stages * search + skin + self.slack
        self.search = search
        self.depth = stages - 1  # ghost levels whose continuity the owned rows depend on
        self.n_owned = 0
        self.bounds = None  # (size + 1,) slab boundaries in x
        self.period = None  # (lo, length) of a periodic x axis (:meth:`distribute`), else None
        self.send = []  # per rank: local rows (owned) whose copies are ghosts there
        self.recv = []  # per rank: local rows of the ghosts received from it
        self.rebalance_every = rebalance_every
        self.weights = weights or {"fluid": 4.0, "solid": 1.0, "idle": 0.1}
        self.n_migrations = 0
        self.busy = 0.0  # this rank's work (step wall time less communication) since the last migration
        self.imbalance = []  # per migration: max / mean over ranks of the work since the last one
        self._owned_cache = (None, None)
        self._t0 = None
        self._seen = None  # (selections, rows) at the last ghost refresh: a full one when either changed
        self.n_refresh = [0, 0]  # ghost refreshes: full, of the working ghosts only

    # --- the SerialComm interface --------------------------------------------------------
    def owned(self, sim) -> torch.Tensor:
        n = sim.state.n
        key = (n, self.n_owned)
        if self._owned_cache[0] != key:
            self._owned_cache = (key, torch.arange(n, device=sim.state.device) < self.n_owned)
        return self._owned_cache[1]

    def slab_span(self, q: int) -> tuple[float, float]:
        """Slab q's [lo, hi) in x; on a periodic x axis the end slabs end at the domain's ends."""
        lo, hi = float(self.bounds[q]), float(self.bounds[q + 1])
        if self.period is not None:
            lo, hi = max(lo, self.period[0]), min(hi, self.period[0] + self.period[1])
        return lo, hi

    def images(self):
        """The shifts of x under which a particle is seen: itself, and on a periodic x axis its
        images one period either side (a slab at one end reaches across to the other)."""
        return (0.0,) if self.period is None else (0.0, -self.period[1], self.period[1])

    def in_reach(self, x, q: int):
        """Mask of the positions ``x`` (numpy, along x, wrapped into a periodic domain) within
        the halo of slab q, through the periodic images."""
        lo, hi = self.slab_span(q)
        sel = np.zeros(x.shape, bool)
        for s in self.images():
            sel |= (x + s >= lo - self.halo) & (x + s < hi + self.halo)
        return sel

    def levels(self, sim) -> torch.Tensor:
        x = sim.state.x[:, 0]
        lo, hi = self.slab_span(self.rank)
        d = torch.stack([(lo - (x + s)).clamp_min(0.0) + ((x + s) - hi).clamp_min(0.0) for s in self.images()]).amin(0)
        lvl = torch.ceil(d / self.search).long().clamp_min(1)
        lvl[: self.n_owned] = 0
        return lvl

    def reduce_measure(self, vals):
        v = np.array([vals[0], vals[1], -vals[2], vals[3]], dtype=np.float64)
        out = np.empty_like(v)
        self.c.Allreduce(v, out, op=MPI.MAX)
        return [out[0], out[1], -out[2], out[3]]

    def merge_limits(self, lim):
        merged = {}
        for d in self.c.allgather(lim):
            for k, v in d.items():
                merged[k] = min(v, merged.get(k, math.inf))
        return merged

    def any(self, flag: bool) -> bool:
        return bool(self.c.allreduce(bool(flag), op=MPI.LOR))

    def reduce_max(self, vals):
        v = np.asarray(vals, dtype=np.float64)
        out = np.empty_like(v)
        self.c.Allreduce(v, out, op=MPI.MAX)
        return out.tolist()

    def sum(self, vals):
        v = np.asarray(vals, dtype=np.float64)
        out = np.empty_like(v)
        self.c.Allreduce(v, out, op=MPI.SUM)
        return out.tolist()

    def sum_owned(self, rows, values):
        mine = values[rows < self.n_owned].sum(0)
        return torch.as_tensor(self.sum(_np(mine).reshape(-1)), dtype=values.dtype,
                               device=values.device).reshape(mine.shape)

    def union_keys(self, keys):
        return sorted(set().union(*self.c.allgather(list(keys))))

    def gather_rows(self, d):
        got = self.c.allgather({k: _np(v) for k, v in d.items()})
        return {k: torch.as_tensor(np.concatenate([g[k] for g in got])).to(v.device) for k, v in d.items()}

    def union_ids(self, ids):
        got = self.c.allgather(_np(ids))
        return torch.as_tensor(np.concatenate(got)).to(device=ids.device, dtype=ids.dtype)

    def drop_rows(self, sim, keep):
        """Rows removed on every rank alike (a particle and its ghost copies): the owned count
        and the send / receive lists follow the new numbering, in their old order (what a
        rank sends and its peer receives stay matched)."""
        keep = keep.cpu()
        new_row = torch.cumsum(keep.long(), 0) - 1
        self.n_owned = int(keep[: self.n_owned].sum())
        self.send = [new_row[r[keep[r]]] for r in self.send]
        self.recv = [new_row[r[keep[r]]] for r in self.recv]
        self._owned_cache = (None, None)

    def slab_of(self, x: torch.Tensor) -> np.ndarray:
        return np.searchsorted(self.bounds, _np(x[:, 0]), side="right") - 1

    def claim(self, sim, new):
        """Of particles added on every rank alike (a fed wire's layer): the ones this rank
        owns, then copies of the ones other ranks own within this rank's halo."""
        return _claim(self, sim, new)

    def place_new(self, sim, k):
        """The k rows just appended: see :func:`_place_new`."""
        return _place_new(self, sim, k)

    def table_at_reference(self, sim):
        """The neighbour table as the last rebuild made it: all pairs within the Verlet radius
        at the reference positions (over the active set's work particles when skipping)."""
        work = sim.active_set.work if sim.active_set is not None else None
        sim.nl.build(sim.nl.x_ref, None if work is None or bool(work.all()) else work)

    def check(self, sim):
        """Everything the single-process step does runs on slabs (a periodic x axis, resultants
        over the whole surface): nothing to refuse."""

    def begin_step(self, sim):
        t, w = time.perf_counter(), self.c.waited
        if self._t0 is not None:
            self.busy += (t - self._t0[0]) - (w - self._t0[1])
        self._t0 = (t, w)
        if sim.rebuilt and self.migration_due(sim):
            self.migrate(sim)

    n_kept = 0  # rebuilds that kept the decomposition (no migration was due)

    def migration_due(self, sim) -> bool:
        """After a rebuild: whether some particle has moved more than half the halo's slack
        since the last migration (at the rebuild's positions, or now), over every rank. Until
        then every particle within the halo's reach of a slab stays among its ghosts until
        the next rebuild (a Verlet interval adds at most a skin: the halo holds the skin and the slack), and the rows, the
        ghost lists and every per-rebuild cache stay."""
        x_mig = sim.nl.x_mig
        n = self.n_owned
        if x_mig is None or x_mig.shape[0] != sim.state.n:
            return True
        d = 0.0
        if n:
            dom = sim.domain
            a = dom.minimum_image(sim.nl.x_ref[:n] - x_mig[:n])
            b = dom.minimum_image(sim.state.x[:n] - x_mig[:n])
            d = float(torch.maximum((a * a).sum(-1), (b * b).sum(-1)).max())
        d = self.c.allreduce(d, op=MPI.MAX)
        due = d > (0.5 * self.slack) ** 2
        self.n_kept += not due
        return due

    def mark(self, sim):
        """The positions of a new decomposition (what :meth:`migration_due` measures from);
        the partial rebuild's body rows, of the rows before, are dropped (the next rebuild is
        a full one)."""
        sim.nl.x_mig = sim.state.x.clone()
        sim.nl.static = sim.nl.x_full = None

    def end_step(self, sim):
        self.refresh(sim)

    def after_drift(self, sim):
        """See :func:`_positions_from_owners`."""
        _positions_from_owners(self, sim)

    # --- decomposition ----------------------------------------------------------------------
    def distribute(self, arrays: dict[str, torch.Tensor], first: bool = False, domain=None):
        """New local arrays: this rank's owned particles (rows of ``arrays`` it owns now, or
        with ``first`` the whole replicated set) sent to their slab's rank, then the ghosts.
        Returns the new arrays; sets n_owned and the send / receive lists. ``domain``: the
        scene's (:class:`torchsph.core.neighbors.Domain`), once: a periodic x axis makes the end
        slabs each other's neighbours."""
        if domain is not None and domain.periodic[0]:
            self.period = (float(domain.lo[0]), float(domain.length[0]))
        x = _np(arrays["state.x"])[:, 0]
        if first:  # every rank holds every particle: take the ones of this slab directly
            if self.bounds is None:
                self.bounds = equal_bounds(self.c, self.size, x if self.rank == 0 else x[:0])
            own = (np.searchsorted(self.bounds, x, side="right") - 1) == self.rank
            mine = {k: v[torch.as_tensor(own)] for k, v in arrays.items()}
        else:
            dest = np.searchsorted(self.bounds, x, side="right") - 1
            stay = torch.as_tensor(dest == self.rank)  # (kept here as they are: not pickled to itself)
            out = [{k: _np(v[torch.as_tensor(dest == q)]) for k, v in arrays.items()} if q != self.rank else {}
                   for q in range(self.size)]
            got = self.c.alltoall(out)
            got[self.rank] = {k: v[stay] for k, v in arrays.items()}
            mine = {k: torch.cat([torch.as_tensor(g[k]) for g in got]) for k in arrays}
        order = torch.argsort(mine["state.id"])  # a deterministic order: by particle id
        mine = {k: v[order] for k, v in mine.items()}
        self.n_owned = int(mine["state.id"].shape[0])
        xo = _np(mine["state.x"])[:, 0]
        self.send, out = [], []
        for q in range(self.size):
            if q == self.rank:
                sel = np.zeros(xo.shape, bool)
            else:
                sel = self.in_reach(xo, q)
            rows = np.nonzero(sel)[0]
            self.send.append(torch.as_tensor(rows))
            out.append({k: _np(v[torch.as_tensor(rows)]) for k, v in mine.items()})
        got = self.c.alltoall(out)
        blocks, self.recv, start = [mine], [], self.n_owned
        for q, g in enumerate(got):
            n = g["state.id"].shape[0]
            self.recv.append(torch.arange(start, start + n))
            start += n
            blocks.append({k: torch.as_tensor(g[k]) for k in mine})
        return {k: torch.cat([b[k].to(mine[k].dtype) for b in blocks]) for k in mine}

    def refresh(self, sim):
        """See :func:`_refresh`."""
        _refresh(self, sim)

    # a migration moves the slab boundaries when the ranks' work differs by more than this
    REBALANCE_ABOVE = 1.1

    def migrate(self, sim):
        """After a rebuild: particles move to the rank of their slab, ghosts are chosen anew,
        the neighbour table is built again over the working particles at the reference
        positions (the pairs the single-process table holds; cost ∝ the work set, where
        carrying every row by particle id cost ∝ all particles), the caches restored.

        Load balance: a rank's work is modelled from the particles it owns, per-particle
        costs of fluid, working solid and idle (left out) solid (:attr:`weights`); every
        ``rebalance_every`` migrations, or at any migration where the modelled work of the
        ranks differs by more than :attr:`REBALANCE_ABOVE`, the boundaries move to equal
        shares of it. The decisions read no clock, so the decomposition, and with it every
        rounding, is a function of the state alone: a run repeats bit for bit and a restart
        continues it exactly (costs fitted to measured step times, tried at dc34313, made
        the slab bounds depend on timing and 2-rank runs differ by 1e-9 from run to run).
        The measured imbalance (step time less communication wait) is recorded for the
        summary."""
        self.n_migrations += 1
        arrays, _ = common_arrays(self.c, sim)
        n = self.n_owned
        owned_arrays = {k: v[:n] for k, v in arrays.items()}
        fl = owned_arrays["state.phase"] == 0
        work = owned_arrays["as.work"] if "as.work" in owned_arrays else torch.ones_like(fl)
        counts = [int(fl.sum()), int((work & ~fl).sum()), int((~work & ~fl).sum())]
        stats = self.c.allgather((self.busy, counts))
        self.busy = 0.0
        times = np.array([t for t, _ in stats])
        if times.max() > 0:
            self.imbalance.append(float(times.max() / times.mean()))
        c = np.array([cnt for _, cnt in stats], dtype=np.float64)
        model = c @ np.array([self.weights["fluid"], self.weights["solid"], self.weights["idle"]])
        imb = float(model.max() / model.mean()) if model.max() > 0 else 1.0
        if self.rebalance_every and (self.n_migrations % self.rebalance_every == 0 or imb > self.REBALANCE_ABOVE):
            w = np.where(_np(fl), self.weights["fluid"], np.where(_np(work), self.weights["solid"], self.weights["idle"]))
            self.bounds = equal_bounds(self.c, self.size, _np(owned_arrays["state.x"])[:, 0], w)
        new = self.distribute(owned_arrays)
        sim.rearm(new, table=lambda: self.table_at_reference(sim))
        self.mark(sim)

    # --- gathering ----------------------------------------------------------------------------
    def gather_owned(self, sim, names=None) -> dict[str, np.ndarray] | None:
        """Rank 0: the owned rows of all ranks' per-particle arrays, in particle-id order
        (the arrays every rank holds)."""
        arrays, _ = common_arrays(self.c, sim)
        names = names or list(arrays)
        mine = {k: _np(arrays[k][: self.n_owned]) for k in names if k in arrays}
        got = self.c.gather(mine, root=0)
        if self.rank != 0:
            return None
        out = {k: np.concatenate([g[k] for g in got]) for k in mine}
        order = np.argsort(out["state.id"], kind="stable")
        return {k: v[order] for k, v in out.items()}


def _claim(comm, sim, new):
    """Of particles added on every rank alike (a fed wire's layer): the ones this rank
    owns, then copies of the ones other ranks own within this rank's halo (ghosts from
    the start, so no rank misses a neighbour until the next migration)."""
    from dataclasses import fields as dc_fields

    from torchsph.core.state import ParticleState

    x = _np(new.x)[:, 0]
    dest = np.searchsorted(comm.bounds, x, side="right") - 1
    near = comm.in_reach(x, comm.rank)
    own = dest == comm.rank
    # ghost order: by owner rank, then as given (the owner appends its send rows alike)
    ghost = np.concatenate([np.nonzero(near & (dest == q))[0] for q in range(comm.size) if q != comm.rank])
    rows = np.concatenate([np.nonzero(own)[0], ghost]).astype(np.int64)
    comm._new = {"n_own": int(own.sum()), "ghost_owner": dest[ghost],
                 # rows among this rank's new particles that rank q holds as ghosts
                 "send": [np.nonzero(comm.in_reach(x[own], q))[0]
                          if q != comm.rank else np.zeros(0, np.int64) for q in range(comm.size)]}
    sel = torch.as_tensor(rows, device=new.x.device)
    local = ParticleState(**{f.name: getattr(new, f.name).index_select(0, sel) for f in dc_fields(new)})
    mine = torch.zeros(local.n, dtype=torch.bool, device=new.x.device)
    mine[: comm._new["n_own"]] = True
    return local, mine


def _place_new(comm, sim, k):
    """The k rows just appended (this rank's new particles, then new ghosts): the owned
    ones move in front of the old ghosts, the ghosts join their owners' blocks, and the
    send lists gain the owned ones other ranks now hold as ghosts."""
    n = sim.state.n
    n0 = n - k
    k_own = comm._new["n_own"]
    dev = sim.state.device
    ar = lambda a, b: torch.arange(a, b, device=dev)  # noqa: E731
    perm = torch.cat([ar(0, comm.n_owned), ar(n0, n0 + k_own), ar(comm.n_owned, n0), ar(n0 + k_own, n)])
    sim.set_particle_arrays({key: v.index_select(0, perm) for key, v in sim.particle_arrays().items()
                             if v.shape[0] == n})
    owned0 = comm.n_owned
    comm.n_owned += k_own
    comm.recv = [r + k_own for r in comm.recv]  # old ghosts moved down by k_own
    g_rows = np.arange(n - (k - k_own), n)  # the new ghosts' rows now
    owner = comm._new["ghost_owner"]
    for q in range(comm.size):
        add = torch.as_tensor(g_rows[owner == q], dtype=torch.long)
        comm.recv[q] = torch.cat([comm.recv[q], add])
        comm.send[q] = torch.cat([comm.send[q], torch.as_tensor(owned0 + comm._new["send"][q], dtype=torch.long)])
    return perm


def _positions_from_owners(comm, sim):
    """With particle shifting a ghost's shift reads neighbours up to a search radius beyond
    it, which the outer ghosts lack: the fluid ghosts take their owners' positions before
    anything reads the drifted ones (the pair geometry that the next step's continuity and
    shift reuse included; without this the sloshing tank with shifting ended 0.07 of its
    size off the single-process run in x after 40 steps on 2 ranks)."""
    if sim.fluid is None or sim.fluid.prm.shifting <= 0:
        return
    x = sim.state.x
    fluid = sim.state.phase == 0
    out = [{} for _ in range(comm.size)]
    for q in range(comm.size):
        if q != comm.rank:
            f = fluid.index_select(0, comm.send[q])  # (the ghost list's fluid entries, and where they stand)
            out[q] = {"pos": _np(torch.nonzero(f).squeeze(1)), "x": _np(x.index_select(0, comm.send[q][f]))}
    got = comm.c.alltoall(out)
    for q, g in enumerate(got):
        if q == comm.rank or not len(g["pos"]):
            continue
        rows = comm.recv[q].index_select(0, torch.as_tensor(g["pos"], dtype=torch.long))
        x.index_copy_(0, rows, torch.as_tensor(g["x"], dtype=x.dtype).to(x.device))


def _refresh(comm, sim):
    """Ghost rows take their owners' current values of every per-particle array.

    Between pair selections only the ghosts whose owners are in the active set's work set
    (or fluid) are sent: a particle outside it is rigid cold solid, which no pair term
    reads and whose only change in a step, x + dt v with its body's velocity, every rank
    computes alike. After a selection (a rebuild, a phase change), a migration or a change
    of rows every ghost is sent."""
    arrays = sim.particle_arrays()
    key = (sim.n_selections, sim.state.n)
    hot = None
    if key == comm._seen and "as.work" in arrays:
        hot = arrays["as.work"] | (sim.state.phase == 0)
    comm._seen = key
    comm.n_refresh[hot is not None] += 1
    send = comm.send if hot is None else [s[hot.index_select(0, s)] if s.numel() else s for s in comm.send]
    out = [{k: _np(v.index_select(0, send[q])) for k, v in arrays.items()} if q != comm.rank else {}
           for q in range(comm.size)]
    if hot is not None:  # which of the ghost list's entries come
        for q in range(comm.size):
            if q != comm.rank:
                out[q]["_pos"] = _np(torch.nonzero(hot.index_select(0, comm.send[q])).squeeze(1))
    got = comm.c.alltoall(out)
    changed = False
    for q, g in enumerate(got):
        rows = comm.recv[q]
        if "_pos" in g:
            rows = rows.index_select(0, torch.as_tensor(g.pop("_pos"), dtype=torch.long))
        if rows.numel() == 0:
            continue
        for k, v in g.items():
            if k not in arrays:  # a lazily built cache this rank has not built: it builds it whole
                continue
            # in place, on the ghost rows only: a copy of every whole array at every step
            # cost 20-45 ms of a full-scene step on each rank
            arrays[k].index_copy_(0, rows, torch.as_tensor(v, dtype=arrays[k].dtype))
            changed = True
    if changed:  # (a ghost's phase may have changed)
        fluid_set(sim)
