"""A term made for the registry's tests, defined here only (no edit of the solver): it holds
two per-particle arrays of its own and declares them, nothing else.

    [mpiexec -n K] python tests/tally_term.py CASE [torchsph CLI options]

runs the torchsph CLI with the term registered, so a case may name ``[tally]``.

``tag`` is each fluid particle's id when the term first saw it, ``count`` the number of
force evaluations in which the particle's row still carried its own tag. Both travel only if
the registry carries them (checkpoints, migration, ghost refresh, particle insertion and
removal): a row that lost its values, or took another particle's, stops counting. After K
steps every fluid particle has been evaluated K + 1 times (the set-up's evaluation and one per
step), in one process or on any number of ranks, restarted or not."""
from __future__ import annotations

import torch

from torchsph.core.state import Array
from torchsph.physics.terms import Term, register


@register
class Tally(Term):
    section = "tally"
    doc = "a test's term: counts each fluid particle's force evaluations"
    needs = ("fluid",)
    reads = ("id",)
    writes = ("acceleration",)
    ARRAYS = {"tag": Array("the particle's id when the term first saw it (-1: not yet)"),
              "count": Array("force evaluations with the row's own tag", output="tally_count")}
    tag = count = None

    @classmethod
    def from_case(cls, cfg, ctx):
        return cls()

    def select(self, sim):
        if self.tag is None:
            n = sim.state.n
            self.tag = torch.full((n,), -1, dtype=torch.long)
            self.count = torch.zeros(n, dtype=torch.long)

    def add_particles(self, new):
        self.tag = torch.cat([self.tag, torch.full((new.n,), -1, dtype=torch.long)])
        self.count = torch.cat([self.count, torch.zeros(new.n, dtype=torch.long)])

    def acceleration(self, sim, v):
        rows = torch.nonzero(sim.fluid_mask).squeeze(1)
        ids = sim.state.id.index_select(0, rows)
        tag = self.tag.index_select(0, rows)
        self.tag = self.tag.index_copy(0, rows, torch.where(tag < 0, ids, tag))
        own = (self.tag.index_select(0, rows) == ids).long()
        self.count = self.count.index_add(0, rows, own)
        return rows, torch.zeros((rows.numel(), sim.state.dim), dtype=sim.state.dtype)


if __name__ == "__main__":
    from torchsph.__main__ import main

    main()
