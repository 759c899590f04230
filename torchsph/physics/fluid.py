"""Weakly compressible fluid terms: Tait EOS, continuity, Adami pressure/viscous force,
density diffusion, particle shifting, gravity/body force, and the Adami-Hu-Adams (2012)
wall condition.

All pair terms work on neighbour tables (rows, k) built from the sorted pair list and
are reduced over the neighbour axis (no scatter, no atomics). Only fluid particles get
rows in the momentum and continuity sums; walls only gather from fluid neighbours for their extrapolated
pressure and velocity. No loop runs over particles or pairs. The per-pair work lives
in pure functions of tensors so that ``torch.compile`` can fuse each one into a single
loop (``compile=True``; shapes are dynamic, so a neighbour-list rebuild does not
recompile).
"""
from __future__ import annotations

import functools
from dataclasses import dataclass

import torch

from torchsph.core.kernels import Kernel
from torchsph.core.neighbors import Domain
from torchsph.core.state import ParticleState, Phase


@dataclass
class FluidParams:
    rho0: float
    c0: float
    eta: float  # dynamic viscosity, Pa s
    gravity: tuple[float, ...]  # m/s^2
    body_force: tuple[float, ...]  # extra acceleration (m/s^2), e.g. a pressure-gradient drive
    gamma: float = 7.0
    density_diffusion: float = 0.0  # delta of the delta-SPH (Molteni-Colagrossi) term; 0 = off
    background_pressure: float = 0.0  # added to the Tait pressure (Pa)
    shifting: float = 0.0  # particle-shifting coefficient C of dr = -C h^2 sum_j V_j (...) grad W; 0 = off
    gravity_ramp: float = 0.0  # s: gravity grows linearly from 0 to ``gravity`` over this time (0 = off)


def gather_nb(t: torch.Tensor, nb: torch.Tensor) -> torch.Tensor:
    """t[nb] for a (rows, k) neighbour table, via index_select (fast on CPU)."""
    return t.index_select(0, nb.reshape(-1)).view(*nb.shape, *t.shape[1:])


def tiny(t: torch.Tensor) -> float:
    """The floor of a denominator that may be zero, for ``t``'s dtype: 1e-300 in float64, the
    smallest normal number in a narrower one (1e-300 is 0 in float32: no floor at all, and a
    particle with no surface beside it divided by zero)."""
    return 1e-300 if t.dtype == torch.float64 else torch.finfo(t.dtype).tiny


def dot(a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    """Dot product over the last (spatial) axis, spelled out per component: torch.compile
    fuses it into the pair loop, whereas ``(a * b).sum(-1)`` over a length-2/3 axis
    became a slow inner reduction (measured 4x slower on the continuity pass)."""
    out = a[..., 0] * b[..., 0]
    for k in range(1, a.shape[-1]):
        out = out + a[..., k] * b[..., k]
    return out


def pair_sum(w: torch.Tensor, v: torch.Tensor) -> torch.Tensor:
    """sum_j w_ij v_ij over the neighbour axis: (R, k) weights and (R, k, d) values -> (R, d),
    as one batched product. ``(w.unsqueeze(-1) * v).sum(1)`` makes an (R, k, d) temporary
    and then reduces along its middle axis: 1.8x (11 rows) to 3.6x (2 112 rows) slower on one
    thread (measured; the same sums to round-off)."""
    return torch.bmm(w.unsqueeze(1), v).squeeze(1)


def outer_sum(a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    """sum_j a_ij (x) b_ij over the neighbour axis: (R, k, p) and (R, k, q) -> (R, p, q), as one
    batched product (the (R, k, p, q) temporary of the broadcast form, summed over k, was 7-10x
    slower: 14 against 1.5 ms for 2 112 rows of 178)."""
    return torch.bmm(a.transpose(1, 2), b)


class GeometryMemo:
    """The pair geometry shared within one evaluation of the accelerations: the terms that
    read the same rows of the same neighbour table (the same tensor objects) at the same
    positions get one (dx, r) and one dW/dr / r, the same bits as their own would be (the
    momentum, the colour gradient, the surface's smoothing and moments each made them anew:
    4 passes over the melt's (R, k, d) pairs where 1 does). Open only while
    :func:`torchsph.step.rates.accelerations` runs (nothing moves the particles in it); outside
    it, and in a traced step, every call computes its own."""

    def __init__(self):
        self.depth = 0
        self.geometry: list = []  # (x, rows, nb, dx, r)
        self.dwr: list = []  # (r, kernel, h, dW/dr / r)

    def __enter__(self):
        self.depth += 1
        return self

    def __exit__(self, *exc):
        self.depth -= 1
        if self.depth == 0:
            self.geometry.clear()
            self.dwr.clear()


GEOMETRY = GeometryMemo()


def pair_geometry(x, rows, nb, domain: Domain, h: float):
    """dx = x_i - x_j (minimum image), (R, k, d), and r = |dx| clamped away from 0 (``vector_norm``:
    one pass, 2.4x (11 rows) to 4.3x (2 112 rows x 178) faster than sqrt of the spelled-out dot
    product, measured; within an ulp of it). Shared within an evaluation (:class:`GeometryMemo`)."""
    memo = None if torch.compiler.is_compiling() or not GEOMETRY.depth else GEOMETRY
    if memo is not None:
        for e in memo.geometry:
            if e[0] is x and e[1] is rows and e[2] is nb:
                return e[3], e[4]
    dx = domain.minimum_image(x.index_select(0, rows).unsqueeze(1) - gather_nb(x, nb))
    r = torch.linalg.vector_norm(dx, dim=-1).clamp_min(1e-12 * h)
    if memo is not None:
        memo.geometry.append((x, rows, nb, dx, r))
    return dx, r


def pair_dwdr_r(r: torch.Tensor, kernel: Kernel, h: float) -> torch.Tensor:
    """dW/dr / r of the pair distances ``r`` (shared within an evaluation, :class:`GeometryMemo`)."""
    memo = None if torch.compiler.is_compiling() or not GEOMETRY.depth else GEOMETRY
    if memo is not None:
        for e in memo.dwr:
            if e[0] is r and e[1] is kernel and e[2] == h:
                return e[3]
    out = kernel.dwdr(r, h) / r
    if memo is not None:
        memo.dwr.append((r, kernel, h, out))
    return out


# --- pure per-pair functions on neighbour tables (compiled when asked) -------------
def momentum_pairs(x, u_visc, rho, p, m, rows, nb, eta: float, kernel: Kernel, h: float,
                   domain: Domain, split: bool):
    """Adami (3.8) pressure and viscous forces on the particles ``rows``, divided by m_i:
    a_i = (1/m_i) sum_j (V_i^2 + V_j^2) [-p~_ij dW/dr e_ij + eta u_ij / r_ij dW/dr].

    Returns (a_pressure, a_viscous) if ``split`` else (a, None), plus the pair geometry
    (dx, dW/dr / r) that the continuity sum and shifting reuse."""
    dx, r = pair_geometry(x, rows, nb, domain, h)
    dWr = pair_dwdr_r(r, kernel, h)
    rho_i = rho.index_select(0, rows).unsqueeze(1)
    rho_j = gather_nb(rho, nb)
    m_i = m.index_select(0, rows)
    Vi = m_i.unsqueeze(1) / rho_i
    Vj = gather_nb(m, nb) / rho_j
    fac = (Vi * Vi + Vj * Vj) * dWr
    pt = (rho_j * p.index_select(0, rows).unsqueeze(1) + rho_i * gather_nb(p, nb)) / (rho_i + rho_j)
    f_p = pair_sum(-fac * pt, dx)
    f_v = pair_sum(fac * eta, u_visc.index_select(0, rows).unsqueeze(1) - gather_nb(u_visc, nb))
    minv = (1.0 / m_i).unsqueeze(-1)
    if split:
        return f_p * minv, f_v * minv, dx, dWr
    return (f_p + f_v) * minv, None, dx, dWr


def shift_weight(Wk: torch.Tensor, W0) -> torch.Tensor:
    """The shift's pair factor 1 + 0.2 (W_ij / W(dx0))^4 (Sun et al. 2017), which multiplies
    V_j grad W_ij (:func:`continuity_pairs`, :func:`shifting_limit`)."""
    return 1.0 + 0.2 * (Wk / W0) ** 4


@functools.lru_cache(maxsize=None)
def shifting_limit(kernel: str, dim: int, h_over_dx: float) -> float:
    """The largest particle-shifting coefficient C for which the shift is stable on a lattice
    of spacing dx: the shift dr_i = -C h^2 sum_j V_j f(W_ij) grad W_ij (see
    :func:`continuity_pairs`), linearised about the lattice, moves a displacement wave
    xi e^{ik.x} by -C h^2 A(k) xi with A(k) = sum_j V_j J(r_j) (1 - cos k.r_j) (J the Jacobian
    of f grad W at the lattice offset r_j); it amplifies the wave unless C h^2 lambda_max(A(k))
    <= 2 for every k. Returned: 2 / (h^2 max over k of the largest |eigenvalue|), k on a
    13^d grid of the Brillouin zone's quarter (the lattice's symmetry gives the rest).
    Wendland C2 at h = 1.5 dx: 0.51 (2-D), 0.59 (3-D); measured on the Taylor-Green vortex,
    a 1e-12 displacement decays at C = 0.3, stays at 0.5 and grows to 3e-4 of the box in
    40 steps at 0.7."""
    import itertools
    import math

    from torchsph.core.kernels import make_kernel

    K, dx = make_kernel(kernel, dim), 1.0
    h = h_over_dx * dx
    R, m = K.radius(h), int(math.ceil(K.radius(h) / dx))
    offs = torch.tensor([o for o in itertools.product(range(-m, m + 1), repeat=dim) if any(o)],
                        dtype=torch.float64) * dx
    offs = offs[offs.norm(dim=1) < R]
    W0 = K.w(torch.tensor(dx, dtype=torch.float64), h)

    def F(r):  # f(W) grad W at offsets r
        q = r.norm(dim=-1)
        return (shift_weight(K.w(q, h), W0) * pair_dwdr_r(q, K, h)).unsqueeze(-1) * r

    eps, eye = 1e-6 * dx, torch.eye(dim, dtype=torch.float64)
    J = torch.stack([(F(offs + eps * eye[a]) - F(offs - eps * eye[a])) / (2 * eps) for a in range(dim)], -1)
    n = 13
    ks = torch.tensor(list(itertools.product(range(n), repeat=dim)), dtype=torch.float64) * (math.pi / dx / (n - 1))
    c = 1.0 - torch.cos(ks @ offs.T)  # (k, offsets)
    A = torch.einsum("ko,oij->kij", c, J) * dx**dim
    lam = torch.linalg.eigvalsh(0.5 * (A + A.transpose(1, 2))).abs().max()
    return float(2.0 / (h * h * lam))


def continuity_pairs(v, m, rho, rows, nb, dx, dWr, ff, delta_h_c0: float, rho0_over_c02: float,
                     g, h: float, kernel: Kernel, W0: float, shift_coef: float):
    """sum_j m_j (u_i - u_j) . grad_i W_ij (3.7), plus, when ``delta_h_c0`` > 0, the
    delta-SPH density diffusion over fluid-fluid pairs (``ff``) with the hydrostatic
    part of the density difference removed (rho^H_j - rho^H_i = -rho0 g.(x_i - x_j) / c0^2),
    so that a fluid at rest stays stratified.

    When ``shift_coef`` > 0 it also returns the particle-shifting displacement
    -C h^2 sum_j V_j [1 + 0.2 (W_ij / W(dx0))^4] grad_i W_ij (Sun et al. 2017), which
    reads the same neighbour data (else None)."""
    m_j = gather_nb(m, nb)
    val = m_j * dot(v.index_select(0, rows).unsqueeze(1) - gather_nb(v, nb), dx) * dWr
    need_rho_j = delta_h_c0 > 0.0 or shift_coef > 0.0
    rho_j = gather_nb(rho, nb) if need_rho_j else None
    r2 = dot(dx, dx)
    if delta_h_c0 > 0.0:
        drho = rho_j - rho.index_select(0, rows).unsqueeze(1)
        if g is not None:
            drho = drho + rho0_over_c02 * dot(dx, g)
        # psi_ij . grad_i W_ij with psi = 2 (rho_j - rho_i) x_ji / (r^2 + 0.01 h^2)
        val = val + delta_h_c0 * 2.0 * drho * (-dWr) * r2 / (r2 + 0.01 * h * h) * (m_j / rho_j) * ff
    shift = None
    if shift_coef > 0.0:
        Wk = kernel.w(torch.sqrt(r2), h)
        wgt = (m_j / rho_j) * shift_weight(Wk, W0) * dWr
        shift = pair_sum(wgt, dx) * (-shift_coef * h * h)
    return val.sum(1), shift


def wall_pairs(x, p, rho, v, rows, nb, mask, g, kernel: Kernel, h: float, domain: Domain):
    """Adami et al. (2012) sums over the fluid neighbours of wall particles ``rows``:
    sum W, sum [p_f + rho_f (g - a_w).(x_w - x_f)] W, and sum u_f W (a_w = 0)."""
    dx, r = pair_geometry(x, rows, nb, domain, h)
    Wk = kernel.w(r, h) * mask
    sumW = Wk.sum(1)
    sp = ((gather_nb(p, nb) + gather_nb(rho, nb) * dot(dx, g)) * Wk).sum(1)
    sv = pair_sum(Wk, gather_nb(v, nb))
    return sumW, sp, sv


def neighbour_average(x, v, rows, nb, weight, kernel: Kernel, h: float, domain: Domain):
    """Shepard average sum_j w_j v_j W_ij / sum_j w_j W_ij over the neighbours of ``rows``
    (``weight`` selects which neighbours count: per particle, or already per entry of ``nb``),
    and the weight sum (0: none)."""
    dx, r = pair_geometry(x, rows, nb, domain, h)
    Wk = kernel.w(r, h) * (weight if weight.dim() == 2 else gather_nb(weight, nb))
    sW = Wk.sum(1)
    avg = pair_sum(Wk, gather_nb(v, nb)) / torch.where(sW > 0, sW, torch.ones_like(sW)).unsqueeze(-1)
    return avg, sW


def embed(rows: torch.Tensor, vals: torch.Tensor, n: int, into: "Embedded | None" = None) -> torch.Tensor:
    """Full-length array holding ``vals`` at ``rows`` and zeros elsewhere (``into``: in that
    reused array, see :class:`Embedded`)."""
    if rows.numel() == n:  # rows = all particles, in order (nonzero of an all-true mask)
        return vals
    if into is not None:
        return into.put(rows, vals, n)
    out = torch.zeros((n,) + vals.shape[1:], dtype=vals.dtype, device=vals.device)
    return out.index_copy_(0, rows, vals)


class Embedded:
    """A whole-length rate array (dv/dt, drho/dt, dh/dt) made once and reused: each
    :meth:`put` zeroes only the rows written since the last (those put and those
    :meth:`mark`-ed by whoever added into it), so a step no longer zero-fills every particle
    for the few it has rates for (2-4 ms of each of three arrays at the full scene). The
    array handed out is the same one each time: a holder of an earlier one sees it change
    (who keeps one across an evaluation copies it). One process only: a decomposition
    writes its ghosts' rows in place, unmarked."""

    def __init__(self):
        self.out: torch.Tensor | None = None
        self.dirty: list[torch.Tensor] = []

    def put(self, rows: torch.Tensor, vals: torch.Tensor, n: int) -> torch.Tensor:
        out = self.out
        if (out is None or out.shape[0] != n or out.shape[1:] != vals.shape[1:] or out.dtype != vals.dtype
                or out.device != vals.device):
            out = self.out = torch.zeros((n,) + vals.shape[1:], dtype=vals.dtype, device=vals.device)
        else:
            for r in self.dirty:
                out.index_fill_(0, r, 0)
        self.dirty = [rows]
        return out.index_copy_(0, rows, vals)

    def mark(self, out: torch.Tensor, rows: torch.Tensor):
        """Rows of ``out`` written by an addition into it (if ``out`` is this array)."""
        if out is self.out:
            self.dirty.append(rows)


class WeaklyCompressibleFluid:
    """Right-hand side of the fluid equations (SPEC 2.2, 3.7, 3.8, Adami 2012 walls)."""

    def __init__(self, params: FluidParams, kernel: Kernel, h: float, domain: Domain,
                 compile: bool = False):
        self.prm = params
        self.kernel = kernel
        self.h = h
        self.domain = domain
        self.B = params.c0**2 * params.rho0 / params.gamma
        self.outs: dict[str, Embedded] = {}  # reused rate arrays (set by a one-process simulation)
        self._fns = {"momentum": momentum_pairs, "continuity": continuity_pairs,
                     "wall": wall_pairs}
        if compile:
            self._fns = {k: torch.compile(f, dynamic=True) for k, f in self._fns.items()}

    # --- equation of state -------------------------------------------------
    def eos(self, rho: torch.Tensor) -> torch.Tensor:
        g = self.prm.gamma
        return self.B * ((rho / self.prm.rho0) ** g - 1.0) + self.prm.background_pressure

    def inverse_eos(self, p: torch.Tensor) -> torch.Tensor:
        g = self.prm.gamma
        base = ((p - self.prm.background_pressure) / self.B + 1.0).clamp_min(1e-3)
        return self.prm.rho0 * base ** (1.0 / g)

    # --- pair subsets, refreshed when the neighbour list changes -----------
    def select_pairs(self, state: ParticleState, table, level: torch.Tensor | None = None, depth: int = 2):
        """Rows of the neighbour table for fluid particles (any source) and for wall
        particles (fluid sources only, by mask). Walls never get a momentum row.

        ``level`` (a decomposed run: 0 for the particles this process owns, k for ghosts
        within k search radii of its slab) keeps only the rows the owned particles' step
        depends on: momentum on level 0, continuity (hence pressure) on levels <= ``depth``
        (2: pressure -> wall extrapolation -> force; 4 with the surface chain colour
        gradient -> normals -> smoothed normals -> curvature), wall extrapolation on levels
        <= depth - 1; ghosts take their owners' accelerations afterwards."""
        fluid = state.phase == Phase.FLUID
        self.fluid_mask = fluid
        self._geom = None  # the pair geometry of the last momentum evaluation is the old pairs'
        self.fluid_rows = torch.nonzero(fluid).squeeze(1)  # every fluid particle (ghosts too): the step moves these
        self.fluid_rows_for = state.phase  # (the phase array they were found in)
        if level is None:
            self.rows_f = self.fluid_rows
            self.n_momentum = self.rows_f.numel()
        else:  # momentum rows first, then the rows that need only the continuity sum
            own = torch.nonzero(fluid & (level == 0)).squeeze(1)
            self.rows_f = torch.cat([own, torch.nonzero(fluid & (level > 0) & (level <= depth)).squeeze(1)])
            self.n_momentum = own.numel()
        self.nb_f = table.gather(self.rows_f, within=True, trim=True)[0]
        self.ff_mask = gather_nb(fluid, self.nb_f).to(state.dtype)  # source is fluid
        self.has_walls = bool((~fluid).any())
        if self.has_walls:
            # wall rows: only walls with a fluid neighbour, fluid sources packed first; found
            # from the fluid's own rows (the table is symmetric), not by reading every row
            fr = torch.nonzero(fluid).squeeze(1)
            near = torch.zeros_like(fluid)
            nbf, mf = table.gather(fr, within=True)
            near.index_fill_(0, nbf[mf], True)
            near = near & ~fluid
            rows_w = torch.nonzero(near if level is None else near & (level < depth)).squeeze(1)
            nbw, mw = table.gather(rows_w, within=True)
            mw = mw & gather_nb(fluid, nbw)
            cnt = mw.sum(1)
            keep = cnt > 0
            rows_w, mw, nbw = rows_w[keep], mw[keep], nbw[keep]
            kw = max(int(cnt.max()) if cnt.numel() else 0, 1)
            order = torch.argsort((~mw).to(torch.int8), dim=1, stable=True)[:, :kw]
            self.rows_w = rows_w
            self.nb_w = torch.gather(nbw, 1, order)
            self.mask_w = torch.gather(mw, 1, order).to(state.dtype)
            self._rest_pending = True  # the other walls' pressure and density: set once (below)

    def _g(self, like: torch.Tensor) -> torch.Tensor:
        return self._const(like)[0]

    def _const(self, like: torch.Tensor):
        """(gravity, gravity + body force) as tensors on ``like``'s device, made once (a gravity
        ramp updates them in place: :meth:`ramp_gravity`)."""
        key = (like.dtype, str(like.device))
        cache = self.__dict__.setdefault("_consts", {})
        if key not in cache:
            cache[key] = self._const_values(like)
        return cache[key]

    def _const_values(self, like: torch.Tensor):
        scale = self.__dict__.get("_g_scale", 0.0 if self.prm.gravity_ramp > 0 else 1.0)
        g = torch.as_tensor(self.prm.gravity, dtype=like.dtype, device=like.device) * scale
        return g, g + torch.as_tensor(self.prm.body_force, dtype=like.dtype, device=like.device)

    def ramp_gravity(self, t: float):
        """Gravity at time ``t`` under ``gravity_ramp``: ``gravity`` min(t / ramp, 1), written
        into the cached constants in place (traced parts read them as inputs)."""
        scale = min(t / self.prm.gravity_ramp, 1.0) if self.prm.gravity_ramp > 0 else 1.0
        if scale == self.__dict__.get("_g_scale"):
            return
        self._g_scale = scale
        for g, gb in self.__dict__.get("_consts", {}).values():
            new_g, new_gb = self._const_values(g)
            g.copy_(new_g)
            gb.copy_(new_gb)

    # --- the right-hand side ----------------------------------------------
    def momentum(self, state: ParticleState, v_eval: torch.Tensor, terms: bool = False):
        """Accelerations at ``state`` with velocities ``v_eval`` for the viscous term.

        Updates ``state.p`` (all) and, for walls, ``state.rho`` (from the extrapolated
        pressure). Returns ``dvdt`` and, with ``terms=True``, also a dict of the separate
        accelerations for diagnosis. Caches the pair geometry for :meth:`continuity`.
        """
        prm = self.prm
        x = state.x
        fluid = self.fluid_mask.unsqueeze(-1)
        g = self._g(x)
        # the pressure where it is read: the fluid rows' from the EOS, the wall rows' extrapolated
        # (the others keep theirs: the background pressure, set at the selection, or a ghost's
        # from its owner)
        # (in place: no one keeps the pressures of an earlier evaluation; a diagnosis
        # evaluates on a clone of the state)
        p = state.p.index_copy_(0, self.rows_f, self.eos(state.rho.index_select(0, self.rows_f)))
        v_w = None
        if self.has_walls:  # the walls' no-slip velocities, written into v_eval for the viscous
            # term and put back after it (a whole copy of v per evaluation cost 2-3 ms of a
            # full-scene step)
            p, u_wall, v_w = self._wall_extrapolation(state, p, v_eval, g)
            v_eval.index_copy_(0, self.rows_w, u_wall)
        state.p = p
        rows, n, k = self.rows_f, state.n, self.n_momentum
        nb_m = self.nb_f
        if k < rows.numel():  # decomposed: the ghost rows get only the pair geometry (continuity)
            rows, nb_m = rows[:k], nb_m[:k]
        a, a_v, dx, dWr = self._fns["momentum"](x, v_eval, state.rho, p, state.m, rows, nb_m,
                                                prm.eta, self.kernel, self.h, self.domain, terms)
        if v_w is not None:
            v_eval.index_copy_(0, self.rows_w, v_w)
        if k < self.rows_f.numel():
            dx_g, r_g = pair_geometry(x, self.rows_f[k:], self.nb_f[k:], self.domain, self.h)
            dx, dWr = torch.cat([dx, dx_g]), torch.cat([dWr, self.kernel.dwdr(r_g, self.h) / r_g])
        self._geom = (dx, dWr, state.rho)
        body = self._const(x)[1]
        if not terms:  # the momentum rows' accelerations, zero elsewhere (ghosts: their owners')
            return embed(rows, a + body, n, self.outs.get("dvdt"))
        a = embed(rows, a, n)
        zero = torch.zeros_like(a)
        if terms:
            a_v = embed(rows, a_v, n)
        dvdt = torch.where(fluid, a + body + (a_v if terms else 0.0), zero)
        if not terms:
            return dvdt
        parts = {"pressure": torch.where(fluid, a, zero), "viscous": torch.where(fluid, a_v, zero),
                 "body": torch.where(fluid, body.expand_as(a), zero)}
        return dvdt, parts

    def continuity(self, v: torch.Tensor, m: torch.Tensor, dx0: float = 0.0, rho: torch.Tensor | None = None):
        """drho/dt (3.7) (+ density diffusion) on the pair geometry of the last
        :meth:`momentum` call, with velocities ``v`` (walls: their prescribed velocity),
        and the particle-shifting displacement when shifting is on (else None): it moves
        particles down the gradient of the particle concentration, which keeps the
        distribution isotropic where the flow stretches it; fluid only, at most 0.1 dx0: the
        shift of the rows :attr:`rows_f` (the others do not shift)."""
        if self._geom is None:
            raise RuntimeError("continuity: the pairs were selected again since the last momentum evaluation; "
                               "evaluate the accelerations on them first (Simulation.rebuild does both)")
        dx, dWr, rho_geom = self._geom
        rho = rho_geom if rho is None else rho  # the current densities (a decomposition refreshed its ghosts')
        prm = self.prm
        W0 = float(self.kernel.w(torch.tensor(dx0, dtype=torch.float64), self.h)) if dx0 > 0 else 1.0
        dr, sh = self._fns["continuity"](v, m, rho, self.rows_f, self.nb_f, dx, dWr, self.ff_mask,
                                         prm.density_diffusion * self.h * prm.c0,
                                         prm.rho0 / prm.c0**2,
                                         self._g(v) if any(prm.gravity) else None, self.h,
                                         self.kernel, W0, prm.shifting if dx0 > 0 else 0.0)
        n = rho.shape[0]
        if sh is not None:
            norm = sh.norm(dim=-1, keepdim=True)
            lim = 0.1 * dx0
            sh = torch.where(norm > lim, sh * (lim / norm.clamp_min(tiny(norm))), sh)
        return embed(self.rows_f, dr, n, self.outs.get("drhodt")), sh

    def _wall_extrapolation(self, state, p, v_eval, g):
        """Adami, Hu & Adams (2012): wall pressure from the fluid with the hydrostatic /
        acceleration correction (walls here are unaccelerated, a_w = 0), wall density from
        the inverse EOS (written to ``state.rho``), and the no-slip velocity
        2 u_w - <u_f> for the viscous term on the wall rows (with the walls' own velocities)."""
        rows = self.rows_w
        if getattr(self, "_rest_pending", False):  # walls without fluid neighbours: background
            # pressure and its density, once per selection (the step leaves them so)
            rest = ~self.fluid_mask
            rest.index_fill_(0, rows, False)
            bg = torch.full_like(p, self.prm.background_pressure)
            p = torch.where(rest, bg, p)
            state.rho = torch.where(rest, self.inverse_eos(bg), state.rho)
            self._rest_pending = False
        sumW, sp, sv = self._fns["wall"](state.x, p, state.rho, v_eval, rows, self.nb_w,
                                         self.mask_w, g, self.kernel, self.h, self.domain)
        has = sumW > 0
        safe = torch.where(has, sumW, torch.ones_like(sumW))
        pw = torch.where(has, sp / safe, torch.full_like(sp, self.prm.background_pressure))
        state.rho = state.rho.index_copy_(0, rows, self.inverse_eos(pw)).view_as(state.rho)  # (in place, a new
        # object: caches that know the densities by identity see them as new; see step.renewed)
        v_w = v_eval.index_select(0, rows)
        u_wall = torch.where(has.unsqueeze(-1), 2.0 * v_w - sv / safe.unsqueeze(-1), v_w)
        return p.index_copy_(0, rows, pw), u_wall, v_w
