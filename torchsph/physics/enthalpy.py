"""The enthalpy method (SPEC §2): the material's thermal parameters, enthalpy and effective heat
capacity across the mushy zone, temperature from enthalpy (banded Newton), the stored energy."""
from __future__ import annotations

import math
from dataclasses import dataclass

import torch

from torchsph.core.state import ParticleState, Phase


@dataclass
class ThermalParams:
    conductivity: float  # W/(m K)
    specific_heat: float  # J/(kg K)
    latent_heat: float = 0.0  # J/kg, melting
    solidus: float = 0.0  # K
    liquidus: float = 0.0  # K


def effective_heat_capacity(T: torch.Tensor, prm: ThermalParams) -> torch.Tensor:
    """c_eff = c_p + h_f exp(-((T - T_SL)/(T_L - T_S))^2) / (sqrt(pi) (T_L - T_S)) (2.11);
    its integral over T adds exactly h_f to the enthalpy."""
    if prm.latent_heat <= 0.0:
        return torch.full_like(T, prm.specific_heat)
    dT = prm.liquidus - prm.solidus
    tsl = 0.5 * (prm.solidus + prm.liquidus)
    return prm.specific_heat + prm.latent_heat * torch.exp(-((T - tsl) / dT) ** 2) / (math.sqrt(math.pi) * dT)


def enthalpy(T: torch.Tensor, prm: ThermalParams, T_ref: float) -> torch.Tensor:
    """h(T) = int_{T_ref}^T c_eff dT' (J/kg), in closed form."""
    h = prm.specific_heat * (T - T_ref)
    if prm.latent_heat > 0.0:
        dT = prm.liquidus - prm.solidus
        tsl = 0.5 * (prm.solidus + prm.liquidus)
        h = h + 0.5 * prm.latent_heat * (torch.erf((T - tsl) / dT) - math.erf((T_ref - tsl) / dT))
    return h


def temperature_from_enthalpy(H: torch.Tensor, prm: ThermalParams, T_ref: float,
                              guess: torch.Tensor | None = None) -> torch.Tensor:
    """Invert h(T) = H (h from :func:`enthalpy`): exact for no latent heat; with latent
    heat, bisection on the bracket the latent part allows (h is strictly increasing, as
    c_eff >= c_p > 0), then two Newton polishes. Vectorised over particles.

    With a ``guess`` (last step's temperatures) three Newton steps are tried first; the
    rows whose residual |h(T) - H| is not below 1e-11 c_p max(T, 1) (e.g. a step across the
    mushy interval) fall back to the bisection."""
    cp = prm.specific_heat
    if prm.latent_heat <= 0.0:
        return T_ref + H / cp
    if guess is not None and H.numel():
        T, bad = newton_temperature(H, prm, T_ref, guess)
        if not bool(bad.any()):
            return T
        return fix_temperature(H, prm, T_ref, T, bad)
    dT = prm.liquidus - prm.solidus
    tsl = 0.5 * (prm.solidus + prm.liquidus)
    l_ref = 0.5 * prm.latent_heat * math.erf((T_ref - tsl) / dT)
    # latent part 0.5 h_f (erf(.) - erf(ref)) lies in [-0.5 h_f - l_ref, 0.5 h_f - l_ref]
    lo = T_ref + (H - (0.5 * prm.latent_heat - l_ref)) / cp
    hi = T_ref + (H + (0.5 * prm.latent_heat + l_ref)) / cp
    for _ in range(48):
        mid = 0.5 * (lo + hi)
        above = enthalpy(mid, prm, T_ref) > H
        hi = torch.where(above, mid, hi)
        lo = torch.where(above, lo, mid)
    T = 0.5 * (lo + hi)
    for _ in range(2):
        T = T - (enthalpy(T, prm, T_ref) - H) / effective_heat_capacity(T, prm)
    return T


def enthalpy_and_capacity(T: torch.Tensor, prm: ThermalParams, T_ref: float, capacity: bool = True):
    """(h(T), c_eff(T)) with latent heat, as a Newton step on h(T) = H takes them: one
    u = (T - T_SL) / (T_L - T_S) for both and the constants folded, h = c_p T + (h_f / 2) erf(u) + C,
    c_eff = c_p + K exp(-u^2): 11 operations where :func:`enthalpy` and
    :func:`effective_heat_capacity` apart take 16 (equal to round-off). ``capacity=False``: h only
    (c_eff None). Without latent heat: :func:`enthalpy` and c_p (T_L - T_S may then be 0)."""
    cp, L = prm.specific_heat, prm.latent_heat
    if L <= 0.0:
        return enthalpy(T, prm, T_ref), (effective_heat_capacity(T, prm) if capacity else None)
    dT = prm.liquidus - prm.solidus
    tsl = 0.5 * (prm.solidus + prm.liquidus)
    u = (T - tsl) / dT
    h = torch.erf(u).mul_(0.5 * L).add_(T, alpha=cp).sub_(cp * T_ref + 0.5 * L * math.erf((T_ref - tsl) / dT))
    if not capacity:
        return h, None
    return h, u.square_().neg_().exp_().mul_(L / (math.sqrt(math.pi) * dT)).add_(cp)


def newton_temperature(H: torch.Tensor, prm: ThermalParams, T_ref: float, guess: torch.Tensor):
    """(T after three Newton steps on h(T) = H from ``guess``, the mask of the rows whose
    residual is not below 1e-11 c_p max(T, 1)): no read of the host."""
    T = guess
    for _ in range(3):
        h, c = enthalpy_and_capacity(T, prm, T_ref)
        T = T - h.sub_(H).div_(c)
    h = enthalpy_and_capacity(T, prm, T_ref, capacity=False)[0]
    bad = ~(h.sub_(H).abs_() <= T.abs().clamp_min(1.0).mul_(1e-11 * prm.specific_heat))
    return T, bad


SATURATED = 6.0  # |T - T_SL| / (T_L - T_S) from which erf is exactly +-1 in float64 (erf(6) = 1 - 2e-17)


def linear_branches(prm: ThermalParams, T_ref: float) -> tuple[float, float, float, float]:
    """(H_lo, H_hi, c_lo, c_hi): below H_lo (above H_hi) the computed h(T) is exactly
    c_p (T - T_ref) + c_lo (+ c_hi), its latent part saturated, so T = T_ref + (H - c) / c_p
    inverts it in closed form."""
    dT = prm.liquidus - prm.solidus
    tsl = 0.5 * (prm.solidus + prm.liquidus)
    e_ref = math.erf((T_ref - tsl) / dT)
    c_lo, c_hi = 0.5 * prm.latent_heat * (-1.0 - e_ref), 0.5 * prm.latent_heat * (1.0 - e_ref)
    H_lo = prm.specific_heat * (tsl - SATURATED * dT - T_ref) + c_lo
    H_hi = prm.specific_heat * (tsl + SATURATED * dT - T_ref) + c_hi
    return H_lo, H_hi, c_lo, c_hi


def mushy_capacity(T: torch.Tensor, prm: ThermalParams) -> int:
    """How many rows :func:`banded_temperature` inverts by Newton: twice the rows now within
    a band 1.5 times as wide as the one where h(T) is not linear, and 64 more (read once,
    at a pair selection)."""
    if prm.latent_heat <= 0.0 or T.numel() == 0:
        return 0
    tsl, dT = 0.5 * (prm.solidus + prm.liquidus), prm.liquidus - prm.solidus
    return 2 * int(((T - tsl).abs() < 1.5 * SATURATED * dT).sum()) + 64


def banded_temperature(H: torch.Tensor, prm: ThermalParams, T_ref: float, guess: torch.Tensor, cap: int):
    """:func:`newton_temperature` with a fixed number of Newton rows: T in closed form where
    h(T) is linear (:func:`linear_branches`: most rows of a large scene, far from the mushy
    interval), Newton from ``guess`` on the ``cap`` rows whose enthalpy lies nearest the
    mushy interval's. ``bad``: Newton's unconverged rows, and any row of the band that was
    not among the ``cap`` (both inverted afresh by :meth:`Inversion.fixed`). Fixed shapes,
    no host read. With ``cap`` >= the rows, plain :func:`newton_temperature`."""
    if cap >= H.numel():
        return newton_temperature(H, prm, T_ref, guess)
    H_lo, H_hi, c_lo, c_hi = linear_branches(prm, T_ref)
    hi = H >= H_hi
    band = (H > H_lo) & ~hi
    T = T_ref + (H - torch.where(hi, c_hi, c_lo)) / prm.specific_heat
    near = torch.topk((H - 0.5 * (H_lo + H_hi)).abs(), cap, largest=False, sorted=False).indices
    Tn, bad_n = newton_temperature(H.index_select(0, near), prm, T_ref, guess.index_select(0, near))
    b_n = band.index_select(0, near)
    T.index_copy_(0, near, torch.where(b_n, Tn, T.index_select(0, near)))
    bad = band.index_copy(0, near, bad_n & b_n)  # (the band rows not among them stay flagged)
    return T, bad


def fix_temperature(H, prm: ThermalParams, T_ref: float, T: torch.Tensor, bad: torch.Tensor) -> torch.Tensor:
    """T with the ``bad`` rows inverted afresh by bisection (:func:`temperature_from_enthalpy`)."""
    idx = torch.nonzero(bad).squeeze(1)
    return T.index_copy(0, idx, temperature_from_enthalpy(H.index_select(0, idx), prm, T_ref))


def liquid_fraction(T: torch.Tensor, prm: ThermalParams) -> torch.Tensor:
    """phi = (T - T_S) / (T_L - T_S) clipped to [0, 1]."""
    if prm.liquidus <= prm.solidus:
        return (T > prm.liquidus).to(T.dtype)
    return ((T - prm.solidus) / (prm.liquidus - prm.solidus)).clamp(0.0, 1.0)


@dataclass
class Inversion:
    """Temperatures from :meth:`Conduction.to_temperature_unchecked`: ``T``, and ``bad``
    (None: exact) the rows where Newton did not converge, which ``fixed()`` inverts afresh."""
    T: torch.Tensor
    bad: torch.Tensor | None
    H: torch.Tensor
    prm: ThermalParams

    def fixed(self) -> torch.Tensor:
        return self.T if self.bad is None else fix_temperature(self.H, self.prm, 0.0, self.T, self.bad)


def stored_energy(state: ParticleState, prm: ThermalParams, T_ref: float, owned=None) -> float:
    """Stored energy sum_i m_i h(T_i) (J) relative to T_ref, walls excluded (and, in a
    decomposed run, particles this process does not own)."""
    inside = state.phase != Phase.WALL
    if owned is not None:
        inside = inside & owned
    return float((state.m * enthalpy(state.T, prm, T_ref) * inside).sum())
