"""Particle state: one tensor per field, all on one device and in one float dtype."""
from __future__ import annotations

from dataclasses import dataclass, fields
from typing import Any, Callable

import torch


class Phase:
    """Material tag of a particle (plain ints, not an enum: a traced step compares tensors
    with them)."""

    FLUID = 0  # moves by the momentum equation
    WALL = 1  # rigid boundary particle (Adami 2012 wall condition; fixed temperature)
    SOLID = 2  # rigid body that conducts heat (moves kinematically; energy equation only)


@dataclass(frozen=True)
class Field:
    """A field of the particle state: the name a snapshot gives it, its kind, unit and meaning."""
    dataset: str
    kind: str  # "float" | "int"
    unit: str
    doc: str


# the state's fields, declared once: the state's constructor, its conversions, the snapshots
# (HDF5 and XDMF) and the per-particle array registry (:mod:`torchsph.step.particles`) read them
FIELDS = {
    "x": Field("position", "float", "m", "position (N, d)"),
    "v": Field("velocity", "float", "m/s", "velocity (N, d)"),
    "rho": Field("density", "float", "kg/m^3", "density"),
    "m": Field("mass", "float", "kg", "mass"),
    "p": Field("pressure", "float", "Pa", "pressure"),
    "T": Field("temperature", "float", "K", "temperature"),
    "T_peak": Field("peak_temperature", "float", "K", "the highest temperature reached"),
    "phase": Field("phase", "int", "", "0 fluid, 1 wall, 2 solid"),
    "id": Field("id", "int", "", "stable particle id"),
    "body": Field("body", "int", "", "rigid body (0: none)"),
}


@dataclass(frozen=True)
class Array:
    """The declaration of a per-particle array an object holds between steps (first dimension:
    the particles), read by the registry (:mod:`torchsph.step.particles`) and so by checkpoints,
    migration and ghost refresh, particle insertion and removal, and the snapshots.

    ``output``: the name ``[run] fields`` takes it by (and its snapshot dataset); None: not
    offered. ``lazy``: a cache built from the state when first needed (where a checkpoint or a
    migration does not carry it, it is dropped and built again). ``travels``: False for an
    array that belongs to the neighbour table that made it (a one-process checkpoint keeps it
    with the table; a migration, a particle removal or another rank count drops it, and the
    next build is a full one). ``from_case``: made from the case at set-up and extended as
    particles are added: a checkpoint does not store it (a restart or a branch takes the case's).
    ``vector``: (N, d), else (N,). ``when``: carried only while ``when(holder)`` is true."""
    doc: str
    unit: str = ""
    output: str | None = None
    lazy: bool = False
    travels: bool = True
    from_case: bool = False
    vector: bool = False
    when: Callable[[Any], bool] | None = None


class Holder:
    """An object that holds per-particle arrays: it declares them (``ARRAYS``: name ->
    :class:`Array`, held as the attribute of that name) under a prefix (``array_prefix``;
    the registry names them ``PREFIX.NAME``). ``put_back_after_selection``: the holder's
    arrays are per-selection caches, put back after a re-armed simulation selects its pairs."""

    array_prefix: str = ""
    ARRAYS: dict[str, Array] = {}
    put_back_after_selection: bool = True

    def arrays(self) -> dict[str, Any]:
        """The declared arrays as held now (None: not held)."""
        return {k: getattr(self, k, None) for k, a in self.ARRAYS.items() if a.when is None or a.when(self)}

    def set_array(self, name: str, value) -> None:
        if name not in self.ARRAYS:
            raise KeyError(f"{type(self).__name__} declares no array {name!r} (it declares {', '.join(self.ARRAYS)})")
        setattr(self, name, value)


@dataclass
class ParticleState:
    """Fields of N particles in d dimensions (SI units).

    x, v: (N, d) position and velocity; rho, m, p, T: (N,) density, mass, pressure and
    temperature; T_peak: (N,) the highest temperature each particle has reached (the fusion
    line is where it crossed the liquidus); phase: (N,) int8 :class:`Phase`; id: (N,) int64 stable particle id;
    body: (N,) int64 rigid body a particle belongs to (0: none, e.g. melt; 1, 2, ...:
    substrate, wire) -- a solid moves with its body's velocity, melt that solidifies
    joins the body it rests on.
    """

    x: torch.Tensor
    v: torch.Tensor
    rho: torch.Tensor
    m: torch.Tensor
    p: torch.Tensor
    T: torch.Tensor
    T_peak: torch.Tensor
    phase: torch.Tensor
    id: torch.Tensor
    body: torch.Tensor

    def __post_init__(self):
        n = self.x.shape[0]
        for f in fields(self):
            t = getattr(self, f.name)
            if t.shape[0] != n:
                raise ValueError(f"ParticleState: field {f.name} has {t.shape[0]} rows, expected {n}")

    @property
    def n(self) -> int:
        return self.x.shape[0]

    @property
    def dim(self) -> int:
        return self.x.shape[1]

    @property
    def dtype(self) -> torch.dtype:
        return self.x.dtype

    @property
    def device(self) -> torch.device:
        return self.x.device

    def to(self, device=None, dtype=None) -> "ParticleState":
        return ParticleState(**{name: getattr(self, name).to(device=device, dtype=dtype if f.kind == "float" else None)
                                for name, f in FIELDS.items()})

    def clone(self) -> "ParticleState":
        return ParticleState(**{f.name: getattr(self, f.name).clone() for f in fields(self)})

    @staticmethod
    def cat(states: list["ParticleState"]) -> "ParticleState":
        return ParticleState(**{f.name: torch.cat([getattr(s, f.name) for s in states])
                                for f in fields(ParticleState)})

    @staticmethod
    def create(x, v, rho, m, phase, T=None, p=None, id=None, body=0, dtype=torch.float64,
               device="cpu") -> "ParticleState":
        """Build a state from array-likes; missing T/p default to 0 and ids to 0..N-1."""
        f = lambda a: torch.as_tensor(a, dtype=dtype, device=device)  # noqa: E731
        x = f(x)
        n = x.shape[0]
        full = lambda a: f(a).expand(n).clone() if f(a).ndim == 0 else f(a)  # noqa: E731
        T = full(0.0 if T is None else T)
        return ParticleState(
            x=x, v=f(v).reshape(x.shape).clone(), rho=full(rho), m=full(m),
            p=full(0.0 if p is None else p), T=T, T_peak=T.clone(),
            phase=torch.as_tensor(phase, dtype=torch.int8, device=device).expand(n).clone(),
            id=(torch.arange(n, device=device) if id is None
                else torch.as_tensor(id, dtype=torch.long, device=device)),
            body=torch.as_tensor(body, dtype=torch.long, device=device).expand(n).clone())
