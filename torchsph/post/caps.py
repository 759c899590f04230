"""Measuring drops: a liquid cap on a flat plate (its contact angle, from a circle (2-D) or
sphere (3-D) fitted to its free surface away from the plate, with the fitted radius and
centre), and a pendant drop (the mass that falls off a wire, and the load it fell at)."""
from __future__ import annotations

import math

import torch

from torchsph.core.state import ParticleState, Phase


def surface_particles(x: torch.Tensor, others: torch.Tensor, dx: float, chunk: int = 4096) -> torch.Tensor:
    """Mask of the particles ``x`` on their body's free surface: fewer than 80 % of the
    median count of particles (``x`` and ``others``, e.g. the plate) within 2 dx."""
    pts = torch.cat([x, others])
    counts = torch.cat([(torch.cdist(x[k:k + chunk], pts) < 2.0 * dx).sum(1)
                        for k in range(0, x.shape[0], chunk)])
    return counts < 0.8 * counts.median()


def fit_sphere(p: torch.Tensor):
    """Least-squares circle/sphere |p - c|^2 = R^2 through the points ``p`` (n, d) (the
    algebraic fit: linear in c and R^2 - |c|^2): (centre, R)."""
    A = torch.cat([2.0 * p, torch.ones_like(p[:, :1])], dim=1)
    b = (p * p).sum(1, keepdim=True)
    sol = torch.linalg.lstsq(A, b).solution.squeeze(1)
    c = sol[:-1]
    return c, math.sqrt(float(sol[-1] + (c * c).sum()))


def contact_angle(state: ParticleState, dx: float, plate_top: float = 0.0, clearance: float = 2.0) -> dict:
    """The contact angle (deg) of the fluid resting on a plate whose top face is at
    ``plate_top`` on the last axis: a circle/sphere fitted to the fluid's surface particles
    more than ``clearance`` dx above the plate; the surface lies dx/2 outside the outermost
    particles' centres, so the surface's radius is the fit's plus dx/2, and
    cos(theta) = (plate_top - z_centre) / R. Also the fit's radius, its centre, and the
    number of surface points."""
    fluid = state.phase == Phase.FLUID
    x = state.x[fluid].double()
    surf = surface_particles(x, state.x[~fluid].double(), dx)
    pts = x[surf & (x[:, -1] > plate_top + clearance * dx)]
    if pts.shape[0] < state.dim + 2:
        raise ValueError(f"contact_angle: {pts.shape[0]} surface points above the plate, too few to fit")
    c, R = fit_sphere(pts)
    R = R + 0.5 * dx
    cos_t = max(-1.0, min(1.0, (plate_top - float(c[-1])) / R))
    return {"angle_deg": math.degrees(math.acos(cos_t)), "R": R, "centre": c.tolist(), "points": int(pts.shape[0])}



def settle(case, overrides=(), t_from: float = 0.014, t_end: float = 0.020, every: float = 1.0e-3,
           checkpoint=None) -> dict:
    """Run a sessile-drop case (``case``: its folder, with ``overrides``) to ``t_end`` and
    sample, every ``every`` s from ``t_from``, the fitted contact angle (deg) and the melt's
    centre-of-mass speed (m/s): ``{"angles", "speeds", "particles", "wall_s"}``.

    ``checkpoint`` (a file path): written atomically every ``every`` s of process with the
    samples so far, and continued from when it exists, so a fine drop runs in legs; one
    written for other physics is refused, naming what differs."""
    import time
    from pathlib import Path

    from torchsph.io import checkpoint as ckpt
    from torchsph.io.config import load_case
    from torchsph.run.build import make_simulation, resume
    from torchsph.step.loop import run_steps

    _, cfg = load_case(case, list(overrides) + [f"run.t_end_s={t_end}"])
    scene, sim = make_simulation(cfg)
    angles, speeds, wall0 = [], [], 0.0
    if checkpoint is not None and Path(checkpoint).exists():
        extra = resume(sim, checkpoint, cfg)
        angles, speeds, wall0 = list(extra["angles"]), list(extra["speeds"]), float(extra["wall_s"])
    t0 = time.perf_counter()
    # stops: every ``every`` s up to t_from (checkpoints only), then the samples t_from + j every
    n_pre = int(math.floor(t_from / every * (1 + 1e-9)))
    stops = [i * every for i in range(1, n_pre + 1) if i * every < t_from * (1 - 1e-9)]
    stops += [t_from + j * every for j in range(int(math.floor((t_end - t_from) / every * (1 + 1e-9))) + 1)]
    for t_k in stops:
        if sim.t >= t_k * (1 - 1e-12):
            continue  # done before the restart
        run_steps(sim, t_end=t_k)
        s = sim.state
        if t_k >= t_from * (1 - 1e-9):
            angles.append(contact_angle(s, scene.dx)["angle_deg"])
            fl = s.phase == Phase.FLUID
            speeds.append(float(((s.m[fl, None] * s.v[fl]).sum(0) / s.m[fl].sum()).norm()))
        if checkpoint is not None:
            ckpt.save(sim, checkpoint, ckpt.config_hash(cfg), {
                "angles": angles, "speeds": speeds, "wall_s": wall0 + time.perf_counter() - t0}, ckpt.physics(cfg))
    return {"angles": angles, "speeds": speeds, "particles": sim.state.n, "wall_s": wall0 + time.perf_counter() - t0}


def fallen_mass(z: torch.Tensor, m: torch.Tensor, dx: float, min_fraction: float = 0.1) -> tuple[float, float | None]:
    """The liquid (heights ``z``, masses ``m``) cut by its highest empty layer wider than
    2 dx with at least ``min_fraction`` of the mass below it (a stray particle does not count):
    (the mass below, the gap's middle height), or (0, None) while the liquid is one piece
    along z. Satellite drops below the cut count with the falling drop, as in a drop-weight
    measurement."""
    zs, order = torch.sort(z, descending=True)
    ms = m.index_select(0, order)
    below = ms.sum() - torch.cumsum(ms, 0)[:-1]  # mass below each gap
    gap = zs[:-1] - zs[1:]
    cut = torch.nonzero((gap > 2.0 * dx) & (below >= min_fraction * ms.sum())).flatten()
    if cut.numel() == 0:
        return 0.0, None
    i = int(cut[0])
    return float(below[i]), float(0.5 * (zs[i] + zs[i + 1]))


# The pendant drop's liquids (overrides of cases/pendant_drop, for scripts/studies/
# calibrate_surface_tension.py and tests/test_pendant.py): the case's viscous water-like liquid,
# and Table 1's steel (sigma, rho). The load a drop falls at, slowly loaded, does not depend on
# the viscosity; steel's own (1-5 mPa s, Ohnesorge number ~1e-3) left the drop ringing and the
# measured load to the start-up: with Table 1's 0.001 Pa s the melt that climbed the wire's side
# at dx = 0.2 mm tore at 13 ms; with 0.005 Pa s the drop fell at 0.70-1.12 of pi d sigma as the
# settling drag lasted 10 or 3 ms, and at 0.38 during the drag at alpha = 1.09 sigma. So the
# steel drop is given 0.5 Pa s (Ohnesorge 0.14, the water-like case's 0.22): quasi-static
# loading, the same static answer. c0 keeps the Laplace pressure 2 sigma / R = 3.3 kPa below
# 0.5 % compression; gravity reaches 1 000 m/s^2 over 0.22 s (the drop falls at ~150 m/s^2,
# ~34 ms: 15 capillary times sqrt(rho R^3 / sigma) = 2.2 ms); the settling drag acts over the
# first 10 ms (g below a third of the load). Loaded twice as fast (0.11 s) the drop fell 2-4 ms
# after the drag ended, at a load that fell as alpha rose (dx = 0.2 mm: 127 m/s^2 at alpha =
# sigma, 114 at 1.09 sigma): the drag's release, not a static limit (docs/VERIFICATION.md 5.1,
# stop 33). A neck may stretch to 60 % as it pinches.
PENDANT_LIQUIDS = {
    "water-like": {"sigma": 0.05, "rho": 1000.0, "over": ["run.t_end_s=0.1"]},  # the whole ramp
    "steel": {"sigma": 1.63, "rho": 7890.0, "over": [
        "fluid.rho0_kg_m3=7890.0", "fluid.viscosity_Pa_s=0.5", "fluid.c0_m_s=10.0",
        "fluid.gravity_m_s2=[0.0, 0.0, -1000.0]", "fluid.gravity_ramp_s=0.22", "run.t_end_s=0.22",
        "numerics.damping_time_s=0.01", "numerics.max_compression=0.6"]},
}


def detach(case, overrides=(), every: float = 2.0e-4, t_end: float | None = None) -> dict:
    """Run a pendant-drop case (``case``: its folder, with ``overrides``; gravity ramped by
    ``[fluid] gravity_ramp_s``) until a part of the drop has fallen off (:func:`fallen_mass`,
    checked every ``every`` s) or ``t_end``: ``{"detached", "t", "g", "m_fallen", "m_drop",
    "particles", "steps", "wall_s"}``; ``g`` is the gravity's magnitude at the check that saw
    the cut (the pinch-off lies at most ``every`` earlier)."""
    import time

    from torchsph.io.config import load_case
    from torchsph.run.build import make_simulation
    from torchsph.step.loop import run_steps

    _, cfg = load_case(case, list(overrides))
    t_end = cfg["run"]["t_end_s"] if t_end is None else t_end
    scene, sim = make_simulation(cfg)
    fl = cfg["fluid"]
    g_full = math.sqrt(sum(c * c for c in fl["gravity_m_s2"]))
    ramp = fl["gravity_ramp_s"]
    t0 = time.perf_counter()
    k, fallen, t = 1, 0.0, 0.0
    while k * every <= t_end * (1 + 1e-9):
        run_steps(sim, t_end=k * every)
        t = sim.t
        fluid = sim.state.phase == Phase.FLUID
        fallen, _ = fallen_mass(sim.state.x[fluid, 2], sim.state.m[fluid], scene.dx)
        if fallen > 0:
            break
        k += 1
    return {"detached": fallen > 0, "t": t, "g": g_full * (min(t / ramp, 1.0) if ramp > 0 else 1.0),
            "m_fallen": fallen, "m_drop": scene.info["mass"], "particles": sim.state.n, "steps": sim.step,
            "wall_s": time.perf_counter() - t0}


__all__ = ["PENDANT_LIQUIDS", "contact_angle", "detach", "fallen_mass", "fit_sphere", "settle", "surface_particles"]
