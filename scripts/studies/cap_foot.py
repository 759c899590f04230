"""Wetting (SPEC 3b): where a settling 3-D cap's line and body are, sample by sample.

Runs ``cases/sessile_drop_3d`` at theta_eq (``--angle``) from a cap started at ``--start``
degrees and prints, every ``--every`` s: the fitted contact angle (caps.contact_angle), the
angle the wetting force reads at the contact band (acos(cos theta_eq - drive) over the band
particles: mean, median, range), and the foot (the largest distance from the drop's axis in
its lowest layer, in dx). At the end, per layer of the melt: its largest distance from the axis
(the drop's profile), its mean pressure and speed, its surface particles (those in the contact
band) and the surface force's curvature there. Receding and advancing caps of the same
theta_eq compared so: docs/VERIFICATION.md.

    python scripts/studies/cap_foot.py --start 105          # R/8, to 14 ms: ~4 min
    python scripts/studies/cap_foot.py --start 135
    python scripts/studies/cap_foot.py --start 105 --set numerics.shifting=0.5 --t-end 0.02
"""
from __future__ import annotations

import argparse
import math
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]
sys.path.insert(0, str(ROOT))

import torch  # noqa: E402

from torchsph.post.caps import contact_angle  # noqa: E402
from torchsph.io.config import load_case  # noqa: E402
from torchsph.run.build import make_simulation  # noqa: E402
from torchsph.step.loop import run_steps  # noqa: E402
from torchsph.core.state import Phase  # noqa: E402


def axis_distance(state, dx: float):
    """The melt's positions, their distances from its vertical axis (in dx) and their layer
    numbers counted from the lowest (layers of dx)."""
    x = state.x[state.phase == Phase.FLUID]
    r = (x[:, :2] - x[:, :2].mean(0)).norm(dim=1) / dx
    layer = torch.round((x[:, 2] - x[:, 2].min()) / dx).long()
    return r, layer


def main():
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--angle", type=float, default=120.0, help="theta_eq, deg")
    ap.add_argument("--start", type=float, default=105.0, help="the cap's starting angle, deg")
    ap.add_argument("--dx", type=float, default=6.25e-5, help="spacing, m (the case's R = 0.5 mm: R/8)")
    ap.add_argument("--t-end", type=float, default=0.014)
    ap.add_argument("--every", type=float, default=0.002)
    ap.add_argument("--set", action="append", default=[], metavar="KEY=VALUE", help="more case overrides")
    a = ap.parse_args()
    torch.set_num_threads(1)
    _, cfg = load_case(str(ROOT / "cases" / "sessile_drop_3d"), [
        f"surface.contact_angle_deg={a.angle}", f"scene.initial_angle_deg={a.start}", f"scene.dx_m={a.dx}",
        f"run.t_end_s={a.t_end}", *a.set])
    scene, sim = make_simulation(cfg)
    wet = sim.surface_model.wetting
    cos_eq = math.cos(math.radians(a.angle))
    print("| t ms | fitted deg | read at the band: mean, median [min, max] deg | band particles | foot dx |")
    print("|---|---|---|---|---|")
    with torch.inference_mode():
        for k in range(1, int(math.floor(a.t_end / a.every * (1 + 1e-9))) + 1):
            run_steps(sim, t_end=k * a.every)
            fit = contact_angle(sim.state, scene.dx)["angle_deg"]
            r, layer = axis_distance(sim.state, scene.dx)
            seen = wet.drive != 0
            th = torch.rad2deg(torch.acos((cos_eq - wet.drive[seen]).clamp(-1.0, 1.0)))
            read = (f"{th.mean():.1f}, {th.median():.1f} [{th.min():.1f}, {th.max():.1f}]" if th.numel() else "-")
            print(f"| {1e3 * k * a.every:.0f} | {fit:.2f} | {read} | {int(seen.sum())} | {r[layer == 0].max():.2f} |",
                  flush=True)
        r, layer = axis_distance(sim.state, scene.dx)
        s = sim.state
        fl = s.phase == Phase.FLUID
        p, speed = sim.fluid.eos(s.rho[fl]), s.v[fl].norm(dim=1)
        surf = sim.surface_model
        kappa = surf.kappa[fl]  # the surface force's curvature (0 off the surface)
        band = torch.zeros(s.n, dtype=torch.bool, device=s.x.device).index_copy_(0, surf.rows_f, wet.band)[fl]
        fit = contact_angle(s, scene.dx)
    print(f"the fitted sphere's 2/R: {2.0 / fit['R']:.0f} 1/m")
    print("| layer from the plate | largest distance from the axis, dx | pressure, mean Pa | speed, mean mm/s "
          "| surface particles (band) | their curvature, mean 1/m |")
    print("|---|---|---|---|---|---|")
    for L in range(int(layer.max()) + 1):
        sel = layer == L
        on = sel & (kappa != 0)
        if bool(sel.any()):
            k = f"{kappa[on].mean():.0f}" if bool(on.any()) else "-"
            print(f"| {L} | {r[sel].max():.2f} | {p[sel].mean():.1f} | {1e3 * speed[sel].mean():.2f} "
                  f"| {int(on.sum())} ({int((on & band).sum())}) | {k} |")


if __name__ == "__main__":
    main()
