"""Particle state: one tensor per field, all on one device and in one float dtype."""
from __future__ import annotations

from dataclasses import dataclass, fields

import torch


class Phase:
    """Material tag of a particle (plain ints, not an enum: a traced step compares tensors
    with them)."""

    FLUID = 0  # moves by the momentum equation
    WALL = 1  # rigid boundary particle (Adami 2012 wall condition; fixed temperature)
    SOLID = 2  # rigid body that conducts heat (moves kinematically; energy equation only)


FLOAT_FIELDS = ("x", "v", "rho", "m", "p", "T", "T_peak")
INT_FIELDS = ("phase", "id", "body")


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
        kw = {}
        for name in FLOAT_FIELDS:
            kw[name] = getattr(self, name).to(device=device, dtype=dtype)
        for name in INT_FIELDS:
            kw[name] = getattr(self, name).to(device=device)
        return ParticleState(**kw)

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
