"""Smoothing kernels with compact support 2h, in 2-D and 3-D.

Each kernel gives the value ``W(r, h)`` and the radial derivative ``dW/dr(r, h)``
(a scalar per pair; the gradient is ``dW/dr * (x_i - x_j) / r``). Both are exactly
zero for ``r >= 2h``, so pairs kept in a Verlet list with a skin beyond the support
contribute nothing and need no masking.
"""
from __future__ import annotations

import math

import torch


class Kernel:
    """Base class: ``sigma(h)`` normalisation times a shape function of q = r/h."""

    name = "base"
    support = 2.0  # in units of h

    def __init__(self, dim: int):
        if dim not in (2, 3):
            raise ValueError(f"kernel dimension must be 2 or 3, got {dim}")
        self.dim = dim

    def radius(self, h: float) -> float:
        return self.support * h

    def sigma(self, h: float) -> float:  # pragma: no cover - abstract
        raise NotImplementedError

    def w(self, r: torch.Tensor, h: float) -> torch.Tensor:  # pragma: no cover
        raise NotImplementedError

    def dwdr(self, r: torch.Tensor, h: float) -> torch.Tensor:  # pragma: no cover
        raise NotImplementedError


class CubicSpline(Kernel):
    """Monaghan's M4 cubic spline."""

    name = "cubic_spline"

    def sigma(self, h: float) -> float:
        return 10.0 / (7.0 * math.pi * h**2) if self.dim == 2 else 1.0 / (math.pi * h**3)

    def w(self, r, h):
        q = r / h
        a = torch.clamp(2.0 - q, min=0.0)
        b = torch.clamp(1.0 - q, min=0.0)
        return self.sigma(h) * (0.25 * a**3 - b**3)

    def dwdr(self, r, h):
        q = r / h
        a = torch.clamp(2.0 - q, min=0.0)
        b = torch.clamp(1.0 - q, min=0.0)
        return (self.sigma(h) / h) * (-0.75 * a**2 + 3.0 * b**2)


class WendlandC2(Kernel):
    """Wendland C2 kernel, W = sigma (1 - q/2)^4 (2q + 1)."""

    name = "wendland_c2"

    def sigma(self, h: float) -> float:
        return 7.0 / (4.0 * math.pi * h**2) if self.dim == 2 else 21.0 / (16.0 * math.pi * h**3)

    def w(self, r, h):
        q = r / h
        a = torch.clamp(1.0 - 0.5 * q, min=0.0)
        return self.sigma(h) * a**4 * (2.0 * q + 1.0)

    def dwdr(self, r, h):
        q = r / h
        a = torch.clamp(1.0 - 0.5 * q, min=0.0)
        return (self.sigma(h) / h) * (-5.0 * q) * a**3


KERNELS = {k.name: k for k in (CubicSpline, WendlandC2)}


def make_kernel(name: str, dim: int) -> Kernel:
    try:
        return KERNELS[name](dim)
    except KeyError:
        raise ValueError(f"unknown kernel {name!r} (allowed: {', '.join(KERNELS)})") from None
