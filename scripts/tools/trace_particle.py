"""Follow one particle from a checkpoint, step by step: what moves it and what its neighbours are.

    python scripts/tools/trace_particle.py OUT/checkpoint.pt --id ID [--steps N] [--every K]
                                           [--set numerics.cfl=0.2 ...]

For a blow-up diagnosis (which names the particle): from the checkpoint (and the
``config.json`` beside it; ``--set`` changes step-control keys), every K steps it prints the
particle's position, velocity, density, pressure and temperature; its neighbours within the
kernel support by phase (fluid, solid) and how many solid ones lie below and above it; the
continuity sum split by neighbour phase (sum_j m_j u_ij . grad W_ij over fluid and over solid
neighbours: a particle pushed into solid raises its density only while the solid's part
exceeds the fluid's); and each force term's acceleration on it. It stops at N steps, at a
blow-up (printed), or when the particle is gone.
"""
from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import torch

sys.path.insert(0, str(Path(__file__).resolve().parents[2]))
from torchsph.physics.fluid import continuity_pairs, pair_geometry  # noqa: E402
from torchsph.step.limits import SimulationError  # noqa: E402
from torchsph.step.loop import run_steps  # noqa: E402
from torchsph.run.build import simulation_from_run  # noqa: E402
from torchsph.core.state import Phase  # noqa: E402


def report(sim, pid: int) -> str | None:
    s = sim.state
    at = torch.nonzero(s.id == pid).squeeze(1)
    if at.numel() == 0:
        return None
    r = int(at[0])
    m = sim.fluid_model
    d = s.x - s.x[r]
    dist = d.norm(dim=1)
    near = (dist < m.kernel.radius(m.h)) & (dist > 0)
    sol, fl = near & (s.phase == Phase.SOLID), near & (s.phase == Phase.FLUID)

    def continuity(sel):  # the model's own sum (3.7) over the neighbours ``sel`` (no diffusion)
        rows, nb = torch.tensor([r]), torch.nonzero(sel).squeeze(1).unsqueeze(0)
        dx, rr = pair_geometry(s.x, rows, nb, sim.domain, m.h)
        dWr = m.kernel.dwdr(rr, m.h) / rr
        return float(continuity_pairs(s.v, s.m, s.rho, rows, nb, dx, dWr, None, 0.0, 0.0, None, m.h, m.kernel,
                                      1.0, 0.0)[0][0])
    saved = s.clone()
    try:
        _, parts = sim.accelerations(s.v, terms=True)
    finally:
        sim.state = saved
    terms = " ".join(f"{k} {[round(v) for v in t[r].tolist()]}" for k, t in parts.items())
    below, above = int((sol & (d[:, 2] < 0)).sum()), int((sol & (d[:, 2] > 0)).sum())
    return (f"t {sim.t:.6f} s | x mm {[round(v * 1e3, 3) for v in s.x[r].tolist()]} v m/s "
            f"{[round(v, 3) for v in s.v[r].tolist()]} rho {float(s.rho[r]):.0f} p {float(s.p[r]):.0f} "
            f"T {float(s.T[r]):.0f} phase {int(s.phase[r])} | neighbours: fluid {int(fl.sum())}, solid "
            f"{int(sol.sum())} ({below} below, {above} above) | drho/dt from fluid {continuity(fl):.3g}, "
            f"from solid {continuity(sol):.3g} | a m/s^2: {terms}")


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("checkpoint", type=Path)
    ap.add_argument("--id", type=int, required=True, help="the particle id (a blow-up diagnosis names it)")
    ap.add_argument("--steps", type=int, default=2000)
    ap.add_argument("--every", type=int, default=25)
    ap.add_argument("--set", dest="overrides", action="append", default=[],
                    help="numerics.KEY=VALUE (step control only)")
    a = ap.parse_args()
    numerics = {}
    for o in a.overrides:
        key, _, val = o.partition("=")
        if not key.startswith("numerics."):
            ap.error(f"--set {o}: only numerics.* keys (the checkpoint holds the physics)")
        try:
            numerics[key[9:]] = json.loads(val)  # a number, true / false
        except json.JSONDecodeError:
            numerics[key[9:]] = val
    _, sim = simulation_from_run(a.checkpoint, numerics=numerics)
    if sim.fluid is None:
        ap.error("the case has no fluid: nothing moves a particle")
    for k in range(a.steps + 1):
        if k % a.every == 0:
            line = report(sim, a.id)
            if line is None:
                print(f"particle {a.id} is not in the state (removed, or no such id)")
                return
            print(line, flush=True)
        try:
            run_steps(sim, steps=1)
        except SimulationError as e:
            print(report(sim, a.id))
            print(f"stopped: {e}")
            return


if __name__ == "__main__":
    main()
