"""Where the sources' power lands in a deposition case: on the wire or on the substrate, for
a range of aim heights and wire-tip heights (the traced, shadowed beams of the solver at
t = 0), against the power the wire needs to melt at its feed speed.

The thesis does not say where on the wire axis the sources are aimed; this table is how a
case's ``scene.source_aim_height_m`` is chosen: enough on the wire to melt it as fast as it
is fed, the rest on the substrate to make a pool the melt can join.

    python scripts/studies/beam_split.py cases/perpendicular_350W --preview
    python scripts/studies/beam_split.py cases/along_250W --aims -0.9,-0.6,-0.3,0,0.25 --gaps 0,0.25
    python scripts/studies/beam_split.py cases/perpendicular_350W --preview --aims 0,-0.3 \
        --gaps 0.3,0.4,0.5,0.6,0.7,0.8 --standoff --set scene.dx_m=0.1e-3

With ``--standoff``, after the table: per aim, the tip height at which the wire takes just the
power its feed needs (linear between the listed tips where the wire's power falls through it),
and that height above the aim point. A tip fed more slowly than the beams melt it climbs to that
height and hangs there; melt leaves it for the pool only across that gap.
"""
from __future__ import annotations

import argparse
import math
import sys
from pathlib import Path

import torch

sys.path.insert(0, str(Path(__file__).resolve().parents[2]))
from torchsph.physics.beam import beam_power  # noqa: E402
from torchsph.io.config import load_case  # noqa: E402
from torchsph.scenes.deposition import WIRE  # noqa: E402
from torchsph.run.build import make_simulation  # noqa: E402
from torchsph.scenes.builders import case_beams  # noqa: E402


def melt_power(cfg: dict) -> float:
    """W to take the fed wire from the ambient temperature to the liquidus and melt it."""
    sc, th = cfg["scene"], cfg["thermal"]
    mdot = cfg["fluid"]["rho0_kg_m3"] * math.pi * sc["wire_diameter_m"] ** 2 / 4 * sc["wire_feed_m_s"]
    return mdot * (th["specific_heat_J_kgK"] * (th["liquidus_K"] - sc["temperature_K"]) + th["latent_heat_J_kg"])


def split(case: str, overrides: list[str], aim: float, gap: float, preview: bool = False) -> tuple[float, float]:
    """(W on the wire, W on the substrate) at t = 0 with the tip ``gap`` above the substrate."""
    _, cfg = load_case(case, overrides + [f"scene.wire_gap_m={gap}", f"scene.source_aim_height_m={aim}"], preview)
    scene, sim = make_simulation(cfg)
    st = sim.state
    every = torch.ones(st.n, dtype=torch.bool, device=st.x.device)
    P = sum(beam_power(st.x, every, b, 0.0, scene.dx) for b in sim.thermal.beams)
    wire = st.body == WIRE
    return float(P[wire].sum()), float(P[~wire].sum())


def main():
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("case")
    ap.add_argument("--preview", action="store_true", help="apply the case's [preview] overrides")
    ap.add_argument("--aims", default="-0.9,-0.6,-0.3,0,0.25", help="aim heights, mm (comma-separated)")
    ap.add_argument("--gaps", default="0,0.25", help="wire-tip heights above the substrate, mm")
    ap.add_argument("--set", action="append", default=[], help="extra overrides")
    ap.add_argument("--standoff", action="store_true", help="per aim, the tip height where the wire takes its melting power")
    a = ap.parse_args()
    over = list(a.set)
    _, cfg = load_case(a.case, over, a.preview)
    total = sum(b["power_W"] * b["efficiency"] for b in case_beams(cfg))
    print(f"{a.case}: absorbed power {total:.0f} W; melting the wire at "
          f"{cfg['scene']['wire_feed_m_s'] * 1e3:.0f} mm/s needs {melt_power(cfg):.0f} W")
    print("| tip height (mm) | aim height (mm) | on the wire (W) | on the substrate (W) |")
    print("|---|---|---|---|")
    gaps = [float(g) * 1e-3 for g in a.gaps.split(",")]
    aims = [float(v) * 1e-3 for v in a.aims.split(",")]
    on_wire = {}
    for gap in gaps:
        for aim in aims:
            w, s = split(a.case, over, aim, gap, a.preview)
            on_wire[aim, gap] = w
            print(f"| {gap * 1e3:.2f} | {aim * 1e3:+.2f} | {w:.0f} | {s:.0f} |", flush=True)
    if a.standoff:
        need = melt_power(cfg)
        print(f"\n| aim height (mm) | tip height where the wire takes {need:.0f} W (mm) | above the aim (mm) |")
        print("|---|---|---|")
        for aim in aims:
            z = standoff([(g, on_wire[aim, g]) for g in sorted(gaps)], need)
            print(f"| {aim * 1e3:+.2f} | {fmt_mm(z)} | {fmt_mm(z if isinstance(z, str) else z - aim)} |")


def standoff(points: list[tuple[float, float]], need: float) -> float | str:
    """The first tip height (ascending) at which the wire's power falls through ``need``,
    linear between the two listed tips around it; else where it lies, in words."""
    if points and points[0][1] < need:
        return "below the lowest tip listed"
    for (z0, p0), (z1, p1) in zip(points, points[1:]):
        if p0 >= need > p1:
            return z0 + (p0 - need) / (p0 - p1) * (z1 - z0)
    return "above the highest tip listed"


def fmt_mm(z) -> str:
    return z if isinstance(z, str) else f"{z * 1e3:.2f}"


if __name__ == "__main__":
    main()
