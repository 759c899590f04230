"""Conduction estimate of the substrate's melt pool in a deposition case, before running it.

The sources' absorbed power minus what melting the fed wire takes (rho pi d^2/4 V_wire
[c_p (T_L - T0) + h_f]) heats the substrate; Rosenthal's quasi-steady solution for a thick
plate moving at V_sub, superposed over each source's Gaussian spot where its axis meets the
top face (torchsph/post/rosenthal.py), gives the T_L isotherm on the surface and below it.
Pass --wire-share 0 for the upper bound (all the power into the substrate). The wire's
shadow is not modelled: sources aimed at the wire put much of their power on it instead. Conduction only
(no flow, no latent heat, insulated surface), read 0.1 mm below the top face: a yardstick for whether the pool can take the
wire, not a prediction of the bead.

    python scripts/studies/pool_estimate.py cases/perpendicular_350W [--set scene.source_aim_height_m=-0.6e-3]
"""
from __future__ import annotations

import argparse
import math
import sys
from pathlib import Path

import torch

ROOT = Path(__file__).resolve().parents[2]
sys.path.insert(0, str(ROOT))

from torchsph.io.config import load_case  # noqa: E402
from torchsph.post.rosenthal import rosenthal_gaussian  # noqa: E402
from torchsph.scenes.builders import case_beams  # noqa: E402


def estimate(cfg, wire_share: float = 1.0, dx: float = 2.5e-5, depth: float = 1.0e-4) -> dict:
    """The isotherm is read ``depth`` below the top face (the point sources of the spot's
    superposition are singular on the face itself)."""
    sc, th, fl = cfg["scene"], cfg["thermal"], cfg["fluid"]
    T0, TL = sc["temperature_K"], th["liquidus_K"]
    rho, cp = fl["rho0_kg_m3"], th["specific_heat_J_kgK"]
    for key, want in (("conductivity_W_mK", 42.0), ("specific_heat_J_kgK", 450.0), ("liquidus_K", 1753.15)):
        if abs(th[key] - want) > 1e-9 * want:
            raise SystemExit(f"pool_estimate: torchsph/post/rosenthal.py is set up for steel (thermal.{key} = {want})")
    beams = case_beams(cfg)
    absorbed = sum(b["power_W"] * b["efficiency"] for b in beams)
    d, Vw = sc["wire_diameter_m"], sc["wire_feed_m_s"]
    wire = rho * math.pi * d * d / 4 * Vw * (cp * (TL - T0) + th["latent_heat_J_kg"])
    sub = max(absorbed - wire_share * wire, 0.0)
    V = sc["substrate_velocity_m_s"][0]
    ext = 4.0e-3
    a = torch.arange(-ext, ext + dx / 2, dx, dtype=torch.float64)
    X, Y = torch.meshgrid(a, a, indexing="ij")
    T = torch.full_like(X, T0)
    Z = torch.full_like(X, depth)
    spots = []
    for b in beams:
        e, p = b["direction"], b["aim_m"]
        s = -p[2] / e[2]  # where the axis meets z = 0
        cx, cy = p[0] + s * e[0], p[1] + s * e[1]
        spots.append((cx, cy))
        q = b["power_W"] * b["efficiency"] / absorbed * sub
        T = T + rosenthal_gaussian(X - cx, Y - cy, Z, q, V, b["radius_m"]) - T0
    melt = T > TL
    out = {"absorbed_W": absorbed, "wire_W": wire, "substrate_W": sub, "spots_mm": [(round(x * 1e3, 3), round(y * 1e3, 3)) for x, y in spots],
           "width_mm": 0.0, "length_mm": 0.0, "melt_under_wire": False}
    if bool(melt.any()):
        out["width_mm"] = float(Y[melt].max() - Y[melt].min()) * 1e3
        out["length_mm"] = float(X[melt].max() - X[melt].min()) * 1e3
        r = (X * X + Y * Y).sqrt()
        inside = r < d / 2
        out["melt_under_wire"] = bool(melt[inside].all())
        out["melt_fraction_under_wire"] = float(melt[inside].double().mean())
    out["peak_K"] = float(T.max())
    return out


def main():
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("case", type=Path)
    ap.add_argument("--set", action="append", default=[], help="case overrides")
    ap.add_argument("--wire-share", type=float, default=1.0,
                    help="fraction of the wire's melting power taken from the sources (0: upper bound)")
    a = ap.parse_args()
    _, cfg = load_case(a.case, a.set)
    r = estimate(cfg, a.wire_share)
    print(f"absorbed {r['absorbed_W']:.0f} W, melting the wire takes {r['wire_W']:.0f} W, "
          f"substrate gets {r['substrate_W']:.0f} W; spots (x, y) at {r['spots_mm']} mm")
    print(f"T_L isotherm 0.1 mm below the top face: width {r['width_mm']:.2f} mm, length {r['length_mm']:.2f} mm, "
          f"peak {r['peak_K']:.0f} K; wire diameter {cfg['scene']['wire_diameter_m'] * 1e3:g} mm, "
          f"melt under {100 * r.get('melt_fraction_under_wire', 0.0):.0f} % of the wire's footprint")


if __name__ == "__main__":
    main()
