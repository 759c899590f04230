"""What a scene builder makes and needs: the built scene, a scene's registry entry, lattices
of particles. The lowest layer of the scenes; :mod:`torchsph.scenes.builders` holds the registry and
the verification scenes, :mod:`torchsph.scenes.deposition` the deposition scene."""
from __future__ import annotations

from dataclasses import dataclass, field
from typing import Callable

import torch

from torchsph.core.neighbors import Domain
from torchsph.core.state import ParticleState, Phase


@dataclass
class Scene:
    state: ParticleState
    domain: Domain
    dx: float
    info: dict = field(default_factory=dict)


@dataclass
class SceneSpec:
    schema: dict
    dims: tuple
    build: Callable
    check: Callable | None = None
    doc: str = ""
    has_fluid: bool = True
    needs_thermal: bool = False
    # the [numerics] the scene's verification measured: a case that names no numerics gets these
    numerics: dict = field(default_factory=dict)
    # the heat sources the scene derives from its own keys ([[beam]] tables, beside the case's)
    beams: Callable | None = None


def lattice(counts, dx, origin=None, dtype=torch.float64, device="cpu"):
    """Cell-centred lattice points: origin + (k + 1/2) dx for k in range(count) per axis."""
    axes = [(torch.arange(n, dtype=dtype, device=device) + 0.5) * dx for n in counts]
    g = torch.stack(torch.meshgrid(*axes, indexing="ij"), dim=-1).reshape(-1, len(counts))
    if origin is not None:
        g = g + torch.as_tensor(origin, dtype=dtype, device=device)
    return g


def tait_density(p, fl):
    """Inverse Tait EOS for initial conditions."""
    B = fl["c0_m_s"] ** 2 * fl["rho0_kg_m3"] / fl["gamma"]
    return fl["rho0_kg_m3"] * ((p - fl["background_pressure_Pa"]) / B + 1.0).clamp_min(1e-3) ** (
        1.0 / fl["gamma"])


def solid_block(x, fl, dx, d, T, dtype, device, id0=0, phase=Phase.SOLID):
    """Solid (or, with ``phase``, wall) particles at ``x``, at rest, density rho0, mass rho0 dx^d."""
    rho0 = fl["rho0_kg_m3"]
    return ParticleState.create(x, torch.zeros_like(x), rho0, rho0 * dx**d, phase, T=T,
                                id=torch.arange(x.shape[0]) + id0, dtype=dtype, device=device)
