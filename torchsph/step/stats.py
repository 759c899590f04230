"""Per-term work statistics of a run (the physics plan's cost, reported in summary.json)."""
from __future__ import annotations

import torch


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
        per_row = table.counts  # the table's rows (the work set's, with an active set)
        nbuilt = max(int((per_row > 0).sum()), 1)
        self.n = s.n
        own = sim.comm.owned(sim)
        integrated = sim.fluid_mask.clone()
        if sim.thermal is not None:
            integrated.index_fill_(0, sim.thermal.rows, True)
        self.n_active = int((integrated if own is None else integrated & own).sum())
        self.all_pairs = s.n * int(per_row.sum()) / nbuilt
        def pairs(rows):  # from the per-row counts (no gather of the table's rows); 0 without a row
            if per_row.numel() == 0:
                return 0
            s = table.slot.index_select(0, rows)
            return int(torch.where(s >= 0, per_row.index_select(0, s.clamp_min(0)), 0).sum())
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
