"""Kernels: normalisation, gradient consistency, compact support (SPEC 3.3)."""
import math

import pytest
import torch

from torchsph.core.kernels import KERNELS, make_kernel


def radial_integral(kernel, h, fn, n=200_000):
    """Integral over R^d of fn(r) with the radial measure (exact up to quadrature)."""
    r = torch.linspace(0.0, kernel.radius(h), n + 1, dtype=torch.float64)
    shell = 2 * math.pi * r if kernel.dim == 2 else 4 * math.pi * r * r
    y = fn(r) * shell
    return float(torch.trapezoid(y, r))


@pytest.mark.parametrize("name", sorted(KERNELS))
@pytest.mark.parametrize("dim", [2, 3])
@pytest.mark.parametrize("h", [0.013, 1.0])
def test_normalisation(name, dim, h):
    k = make_kernel(name, dim)
    integral = radial_integral(k, h, lambda r: k.w(r, h))
    assert abs(integral - 1.0) < 1e-3


@pytest.mark.parametrize("name", sorted(KERNELS))
@pytest.mark.parametrize("dim", [2, 3])
def test_gradient_is_derivative_of_value(name, dim):
    k = make_kernel(name, dim)
    h = 0.7
    r = torch.linspace(0.01, 2 * h - 0.01, 999, dtype=torch.float64)
    eps = 1e-6
    fd = (k.w(r + eps, h) - k.w(r - eps, h)) / (2 * eps)
    assert torch.allclose(k.dwdr(r, h), fd, rtol=1e-6, atol=1e-8 * float(k.sigma(h)))


@pytest.mark.parametrize("name", sorted(KERNELS))
@pytest.mark.parametrize("dim", [2, 3])
def test_gradient_first_moment(name, dim):
    """int x (x . grad W) dV / d ... = -1: the continuous identity behind SPH gradients
    (int x_a dW/dx_b dV = -delta_ab), in radial form -(1/d) int r dW/dr dV = 1."""
    k = make_kernel(name, dim)
    h = 1.3
    m = radial_integral(k, h, lambda r: -r * k.dwdr(r, h)) / dim
    assert abs(m - 1.0) < 1e-3


@pytest.mark.parametrize("name", sorted(KERNELS))
def test_compact_support_and_sign(name):
    k = make_kernel(name, 3)
    h = 0.5
    r = torch.tensor([2 * h, 2 * h + 1e-9, 3 * h], dtype=torch.float64)
    assert torch.all(k.w(r, h) == 0) and torch.all(k.dwdr(r, h) == 0)
    r = torch.linspace(1e-3, 2 * h - 1e-3, 100, dtype=torch.float64)
    assert torch.all(k.w(r, h) > 0) and torch.all(k.dwdr(r, h) < 0)
    assert float(k.dwdr(torch.zeros(1, dtype=torch.float64), h)) == 0.0


def test_unknown_kernel():
    with pytest.raises(ValueError, match="unknown kernel"):
        make_kernel("gaussian", 2)
