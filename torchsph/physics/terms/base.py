"""The term protocol: a physics term that a case switches on by naming its section, and
that the step evaluates without naming it.

A term declares
- ``section`` and ``schema``: its case section and keys (validated like every section;
  ``needs``: the sections it cannot work without, ``check``: rules across keys);
- ``reads`` and ``writes``: the fields it reads (the state's, e.g. ``"T"``; a registry name
  such as ``"sf.kappa"``; or a field another term writes, e.g. ``"grad_T"``), on its own rows
  or its neighbours', and what it writes: the rates it adds to (``"heat"``: W per particle
  into the energy equation; ``"acceleration"``: m/s^2 into the momentum equation) and the
  per-particle fields it makes (each one of its ``ARRAYS``, computed by ``evaluate``). The
  step orders the terms that make fields by these declarations (:mod:`torchsph.step.stages`)
  and refuses, at set-up, a term that reads a field nothing in the case writes;
- its time-step limits (``limits``, seconds, with ``limit_formulas`` for the messages);
- its per-particle arrays (``ARRAYS``: name -> :class:`~torchsph.core.state.Array`, held as the
  attributes of those names; ``add_particles`` extends them), which the one array registry
  (:mod:`torchsph.step.particles`) carries, as ``SECTION.NAME``, through checkpoints, MPI migration
  and ghost refresh, particle insertion and removal, and into the snapshots where an array
  declares an ``output`` name and ``[run] fields`` names it;
- for a heat source, ``seeds``: the particles it heats, which the active set keeps in the work.

A term that a case does not name is never built, so it costs nothing. The step calls the
hooks at fixed points (:class:`torchsph.step.simulation.Simulation`): ``select`` after every pair
selection, ``evaluate`` (a term that makes fields) every step once the pairs are selected and
before any rate, ``heat`` with the conduction and beams, ``acceleration`` with the fluid
forces, ``limits`` with the others."""
from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import torch

from torchsph.core.schema import Key
from torchsph.core.state import Array, Holder  # noqa: F401 (Array re-exported: a term declares its arrays with it)

RATES = ("heat", "acceleration")


@dataclass
class TermContext:
    """What a term may build itself from, besides the validated case: the scene's spacing,
    the smoothing length and kernel, the domain, and the float type and device."""
    dx: float
    h: float
    kernel: Any
    domain: Any
    dim: int
    dtype: torch.dtype
    device: Any


class Term(Holder):
    """Base class of a composable physics term (see the module doc)."""

    section: str = ""
    doc: str = ""
    schema: dict[str, Key] = {}
    needs: tuple[str, ...] = ()
    reads: tuple[str, ...] = ()
    writes: tuple[str, ...] = ()
    limit_formulas: dict[str, str] = {}

    @classmethod
    def check(cls, cfg: dict) -> None:
        """Rules across keys or sections (raise :class:`~torchsph.core.schema.CaseError`)."""

    @classmethod
    def from_case(cls, cfg: dict, ctx: TermContext) -> "Term":
        raise NotImplementedError(f"term [{cls.section}] has no from_case")

    # --- hooks the step calls (defaults: nothing) ------------------------------
    def select(self, sim) -> None:
        """After every pair selection (a neighbour rebuild, a phase change, a restore)."""

    def heat(self, sim, t: float | torch.Tensor, rows: torch.Tensor) -> torch.Tensor:
        """W per particle on ``rows`` (the conducting rows) at time ``t`` (in the step a 0-d
        tensor: decide on it with tensor operations, not ``if``, so the step stays one graph)."""
        raise NotImplementedError

    def acceleration(self, sim, v: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """(rows, accelerations on them) at the end of the step (``v``: the velocities the
        viscous forces are evaluated with)."""
        raise NotImplementedError

    def seeds(self, sim, t: float) -> torch.Tensor | None:
        """Mask of the particles this term heats at time ``t`` (kept in the active set)."""
        return None

    def limits(self, sim) -> dict[str, Any]:
        """Time-step limits (s): numbers, or 0-d device tensors (read with the others at once)."""
        return {}

    @property
    def array_prefix(self) -> str:
        """The registry names this term's arrays ``SECTION.NAME``."""
        return self.section

    @property
    def fields(self) -> tuple[str, ...]:
        """The per-particle fields this term makes (its writes that are not rates)."""
        return tuple(w for w in self.writes if w not in RATES)

    def evaluate(self, sim) -> None:
        """Make the fields this term writes, from the state once the step's pairs are selected
        (the positions and temperatures at the end of the step), before any rate reads them."""
        raise NotImplementedError(f"term [{self.section}] writes {self.fields} and has no evaluate")

    def add_particles(self, new) -> None:
        """Extend the per-particle arrays for particles appended to the state (default: each
        held array with zeros for the new particles)."""
        for k, v in self.arrays().items():
            if v is not None:
                self.set_array(k, torch.cat([v, torch.zeros((new.n,) + v.shape[1:], dtype=v.dtype, device=v.device)]))

    def plan(self) -> Any:
        """What the physics plan reports for this term."""
        return True


TERMS: dict[str, type[Term]] = {}


def register(cls: type[Term]) -> type[Term]:
    """Class decorator: make a term available to cases under its ``section``."""
    bad = set(cls.writes) - set(RATES) - set(cls.ARRAYS)
    if not cls.section or bad:
        raise TypeError(f"{cls.__name__}: a term needs a section and writes rates {RATES} or fields it declares in "
                        f"ARRAYS (got {sorted(bad)})")
    if cls.section in TERMS and TERMS[cls.section] is not cls:
        raise TypeError(f"{cls.__name__}: section [{cls.section}] is taken by {TERMS[cls.section].__name__}")
    TERMS[cls.section] = cls
    return cls


def owned_sum(sim, rows: torch.Tensor, p: torch.Tensor) -> torch.Tensor:
    """The sum of ``p`` (values on ``rows``) over the particles this process owns (a
    decomposed run books its own particles only; ghosts are copies)."""
    own = sim.comm.owned(sim)
    if own is not None:
        p = torch.where(own.index_select(0, rows), p, torch.zeros_like(p))
    return p.sum()
