"""The one interface through which a domain decomposition plugs into the solver.

The solver core never imports MPI: :class:`~torchsph.step.simulation.Simulation` calls these
hooks, which do nothing in one process. ``parallel/`` provides the MPI implementation
(slabs along x with ghost halos).
"""
from __future__ import annotations

import torch


class SerialComm:
    """One process: every particle is owned, every reduction is the identity."""

    rank = 0
    size = 1

    def owned(self, sim) -> torch.Tensor | None:
        """Mask of the particles this process owns (None: all)."""
        return None

    def levels(self, sim) -> torch.Tensor | None:
        """Per particle: 0 if owned, else k for a ghost within k search radii of this
        process's domain (None: all owned)."""
        return None

    def reduce_measure(self, vals: list[float]) -> list[float]:
        """[vmax, amax, rho_min, compression]: max, max, min, max over processes."""
        return vals

    def merge_limits(self, lim: dict[str, float]) -> dict[str, float]:
        """Each time-step limit: the minimum over processes."""
        return lim

    def any(self, flag: bool) -> bool:
        return flag

    def reduce_max(self, vals: list[float]) -> list[float]:
        """Each value's maximum over processes."""
        return vals

    def sum(self, vals: list[float]) -> list[float]:
        return vals

    def sum_owned(self, rows: torch.Tensor, values: torch.Tensor) -> torch.Tensor:
        """The sum over the first axis of ``values`` (one row per entry of ``rows``, local row
        numbers) over the particles each process owns, summed over processes."""
        return values.sum(0)

    def union_keys(self, keys) -> list[str]:
        """The names any process holds, sorted (each process books only what happened on its
        particles: a fed layer or an escape may create a name on some processes only)."""
        return sorted(keys)

    def gather_rows(self, d: dict[str, torch.Tensor]) -> dict[str, torch.Tensor]:
        """Each array concatenated over processes (rank order)."""
        return d

    def claim(self, sim, new):
        """Of particles to be added (the same on every process): the ones this process holds
        (its own, and copies of others' it needs), and the mask of its own (None: all)."""
        return new, None

    def place_new(self, sim, k: int) -> torch.Tensor | None:
        """After ``k`` particles were appended: reorder rows as the decomposition needs
        (returns the permutation applied, or None)."""
        return None

    def union_ids(self, ids: torch.Tensor) -> torch.Tensor:
        """The particle ids every process passed, on every process."""
        return ids

    def drop_rows(self, sim, keep: torch.Tensor):
        """After rows were removed (``keep``: the rows kept, of the old numbering): renumber
        what the decomposition holds by row."""

    def begin_step(self, sim):
        """Before a step: migration and new ghosts when the last step rebuilt the pairs."""

    def after_drift(self, sim):
        """After the drift: ghosts whose drift this process cannot make exactly (a shift that
        reads neighbours it does not hold) take their owners' positions."""

    def end_step(self, sim):
        """After a step (and after set-up): ghost particles take their owners' values."""

    def check(self, sim):
        """Refuse what the decomposition does not support (raises ValueError)."""
