"""The active set: cold, quiescent solid is left out of the work until heat reaches it.

A particle is a *seed* when it is fluid, lit by a beam, or its temperature differs from
ambient by more than a tolerance ``tol``. Around the seeds three nested regions are
grown (voxel dilation, conservative: every particle within the distance is included):

- *core* = seeds dilated by one search radius (kernel support + skin): the particles
  that can receive heat (or melt, or be lit) before the next refresh;
- *active* = core dilated by one more kernel support: the particles whose energy (and,
  for fluid, momentum) is integrated; the band active - core is the *frontier*;
- *work* = active dilated by one search radius: active plus a *halo* of inactive
  particles that enter the neighbour table as sources only, at their frozen temperature.

The set is refreshed whenever a particle outside the core becomes a seed (checked every
step; in a run that is a frontier particle), and at the next neighbour rebuild after
``max_age`` rebuilds; otherwise a neighbour rebuild keeps it. Error bound: an inactive particle is frozen at a
temperature within ``tol`` of ambient, and would have stayed within ``tol`` until it was
activated (it is activated before heat crosses the frontier band), so the heat the halo
does not take up changes no temperature by more than ``tol``; the energy it does not
take up is measured (the ``conduction`` term of the energy balance, 0 without skipping
in a scene without fixed-temperature walls).
"""
from __future__ import annotations

import math

import torch

from torchsph.core.state import Array, Holder

DENSE_VOXELS = 1 << 24  # voxel grids up to this size are dilated densely (running sums)
# voxels per dilation radius: a particle is taken in when its voxel is within this many voxels
# of a seed's along every axis, so up to (1 + 1 / VOXELS_PER_RADIUS) radius away along an axis.
# At 2 (stop 45 and before) the full scene's first work set held 54 220 particles and a step
# took 20.9 ms; at 4, 47 020 and 17.2 ms (the same conservative bound: every particle within
# the radius is in; measured on the first 20 steps, one thread)
VOXELS_PER_RADIUS = 4


def _grow_keys(keys: torch.Tensor, mult: list[int], dims: list[int], k: int) -> torch.Tensor:
    """Voxel keys (unique) grown by up to ``k`` voxels along each axis in turn (a cube)."""
    for m, d in zip(mult, dims):
        coord = (keys // m) % d
        offs = torch.arange(-k, k + 1, device=keys.device)
        nc = coord.unsqueeze(1) + offs.unsqueeze(0)
        ok = (nc >= 0) & (nc < d)
        keys = torch.unique((keys.unsqueeze(1) + offs.unsqueeze(0) * m)[ok])
    return keys


def dilate(x: torch.Tensor, seed: torch.Tensor, radius: float) -> torch.Tensor:
    """Mask of the particles within ``radius`` of a seed particle (voxels of radius /
    :data:`VOXELS_PER_RADIUS`: it may include some up to (1 + 1 / VOXELS_PER_RADIUS) radius
    further along each axis). No loop over particles: the cube of voxels is grown one axis at
    a time (a window of width 2k + 1 along each). The voxel grid spans the seeds' bounding
    box grown by the radius, not the scene: its cost follows the heated zone."""
    if radius <= 0 or not bool(seed.any()) or bool(seed.all()):
        return seed.clone()
    k = VOXELS_PER_RADIUS
    cell = radius / k
    # voxels on a fixed grid (not from the local bounding box), so that a process holding
    # part of the particles grows the same sets as one holding all of them
    c = torch.floor(x / cell).long()
    cs = c[seed]
    lo, hi = cs.min(0).values - k, cs.max(0).values + k
    box = torch.nonzero(((c >= lo) & (c <= hi)).all(1)).squeeze(1)  # the only particles that can be reached
    c = c.index_select(0, box) - lo  # >= 0
    dims = (hi - lo + 1).tolist()
    mult = [1] * len(dims)
    for a in range(len(dims) - 2, -1, -1):
        mult[a] = mult[a + 1] * dims[a + 1]
    key = (c * torch.tensor(mult, device=x.device)).sum(-1)
    seed_b = seed.index_select(0, box)
    out = torch.zeros_like(seed)
    if x.shape[1] in (2, 3) and math.prod(dims) <= DENSE_VOXELS:
        # a dense voxel grid: the cube of offsets grown one axis at a time, each a window sum of
        # width 2k + 1 from a running sum (4-5x faster on the CPU than max-pools, the same set)
        grid = torch.zeros(math.prod(dims), dtype=torch.int32, device=x.device)
        grid.index_fill_(0, key[seed_b], 1)
        g = grid.view(*dims)
        for a in range(len(dims)):
            pad = [0] * (2 * len(dims))
            pad[2 * (len(dims) - 1 - a)], pad[2 * (len(dims) - 1 - a) + 1] = k + 1, k
            run = torch.cumsum(torch.nn.functional.pad(g, pad), a, dtype=torch.int32)
            g = (run.narrow(a, 2 * k + 1, dims[a]) - run.narrow(a, 0, dims[a]) > 0).to(torch.int32)
        return out.index_fill_(0, box[g.reshape(-1).index_select(0, key) > 0], True)
    grown = _grow_keys(torch.unique(key[seed_b]), mult, dims, k)
    return out.index_fill_(0, box[torch.isin(key, grown)], True)


class ActiveSet(Holder):
    """Seeds, core, active, frontier and work masks of a scene (see the module doc)."""

    array_prefix = "as"
    put_back_after_selection = False
    ARRAYS = {"active": Array("in the active set", output="active"),
              "work": Array("in the work set (the active set and its halo)", output="working"),
              "frontier": Array("the work set's outer layer")}

    def __init__(self, tol: float, ambient: float, support: float, search: float):
        self.tol = tol
        self.ambient = ambient
        self.support = support  # kernel support 2h
        self.search = search  # support + Verlet skin
        self.active = self.work = self.frontier = None
        self.n_refresh = 0
        self.age = 0  # neighbour rebuilds since the last refresh

    # rebuilds a set is kept for at most, when nothing makes it stale (the frontier check
    # keeps it conservative; this bounds how far it may lag behind the heated zone)
    max_age = 32

    def seeds(self, state, lit: torch.Tensor | None, idx: torch.Tensor | None = None) -> torch.Tensor:
        """The seed mask, of every particle or (``idx``) of those particles only."""
        from torchsph.core.state import Phase

        phase, T = (state.phase, state.T) if idx is None else (state.phase.index_select(0, idx), state.T.index_select(0, idx))
        s = (phase == Phase.FLUID) | ((T - self.ambient).abs() > self.tol)
        if lit is not None:
            s = s | (lit if idx is None else lit.index_select(0, idx))
        return s

    def refresh(self, state, lit: torch.Tensor | None):
        seed = self.seeds(state, lit)
        # the three dilations on the particles they can reach only: a dilation by r takes in
        # particles less than 1.5 r (per axis) from its seeds (voxels of r / 2, two on each
        # side), so the work set lies within 1.5 (2 search + support) of the seeds' box; the
        # box is found once, not by each dilation over every particle (the same sets)
        x, sub = state.x, None
        if bool(seed.any()) and not bool(seed.all()):
            xs = x.index_select(0, torch.nonzero(seed).squeeze(1))
            reach = 2.0 * (2.0 * self.search + self.support)
            lo, hi = xs.min(0).values - reach, xs.max(0).values + reach
            sub = torch.nonzero(((x >= lo) & (x <= hi)).all(1)).squeeze(1)
            x, seed = x.index_select(0, sub), seed.index_select(0, sub)
        core = dilate(x, seed, self.search)
        active = dilate(x, core, self.support)
        work = dilate(x, active, self.search)
        if sub is not None:
            core, active, work = (torch.zeros(state.n, dtype=torch.bool, device=x.device).index_copy_(0, sub, m)
                                  for m in (core, active, work))
        self.active, self.work = active, work
        self.frontier = active & ~core
        self.n_refresh += 1
        self.age = 0

    def stale(self, state, lit: torch.Tensor | None, rows: torch.Tensor | None = None) -> torch.Tensor:
        """True when a particle outside the core has become a seed (heat is near the edge, or
        a particle was heated from outside the step): a 0-d device tensor (the step reads it
        with its other decisions). ``rows``: the particles whose temperature, phase and
        lighting a step changes (the conducting rows); only those of them outside the core
        are read (:meth:`edge`), since no other particle can become a seed in a step.
        Temperatures set from outside the step (by hand) are not read here: the step sees
        that the state's T is not the array it wrote and refreshes the set
        (:meth:`torchsph.step.simulation.Simulation.advance`)."""
        if rows is None:
            return (self.seeds(state, lit) & (self.frontier | ~self.active)).any()
        return self.seeds(state, lit, self.edge(rows)).any()

    _edge = None  # (rows, frontier, the rows outside the core)

    def edge(self, rows: torch.Tensor) -> torch.Tensor:
        """Those of ``rows`` outside the core (the frontier's, in a run), made once per row
        set and refresh."""
        e = self._edge
        if e is None or e[0] is not rows or e[1] is not self.frontier:
            out = self.frontier | ~self.active
            self._edge = e = (rows, self.frontier, rows.index_select(0, torch.nonzero(out.index_select(0, rows)).squeeze(1)))
        return e[2]

    def pad(self, n: int):
        """New particles (appended) start outside every set until the next refresh."""
        f = lambda m: torch.cat([m, torch.zeros(n, dtype=m.dtype, device=m.device)])  # noqa: E731
        self.active, self.work, self.frontier = f(self.active), f(self.work), f(self.frontier)

    def to_dict(self) -> dict:
        return {"active": self.active, "work": self.work, "frontier": self.frontier,
                "n_refresh": self.n_refresh, "age": self.age}
