"""Melt held round the fed wire, and where the beams' power lands, over a deposition run.

    python scripts/studies/wire_collar.py RUN_DIR [RUN_DIR ...] [--t-min 0.3] [--every 1]
                                          [--radius-mm 1.5] [--above-mm 0.8] [--no-beams]

Per snapshot of each run (lab frame: the wire's axis is x = y = 0, the substrate's original
top z = 0): the **collar**, the melt within ``--radius-mm`` of the axis and more than
``--above-mm`` above the top (a bead of the nominal 2.26 mm^2 is ~1 mm high: melt above that,
round the wire, is held on the wire rather than laid on the substrate), in mm^3; all the
melt; the highest melt; the solid wire's lowest particle. With the beams (the solver's
traced, shadowed beams at the snapshot's positions), the absorbed power split four ways:
the solid wire, the collar, the other melt, the solid substrate and bead (W). From the run's
deposit.json: the wire fed so far over the nominal feed (%) and the time the feed has waited
on contact so far (s): a tip that rests on solid substrate starves the bead.

A collar that grows while the bead behind the pool thins is what made the 0.2 mm rung of
``perpendicular_350W`` short (docs/RESOLUTION.md, "Seventh pass").
"""
from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import h5py
import torch

sys.path.insert(0, str(Path(__file__).resolve().parents[2]))
from torchsph.physics.beam import beam_power  # noqa: E402
from torchsph.scenes.deposition import WIRE  # noqa: E402
from torchsph.post.analysis import nominal_wire_fed_kg  # noqa: E402
from torchsph.run.build import make_simulation  # noqa: E402
from torchsph.core.state import Phase  # noqa: E402


def _feed_record(run: Path, cfg: dict) -> list[tuple[float, float, float]]:
    """(t, wire fed over the nominal feed in %, feed wait so far in s) per record of deposit.json."""
    path = run / "deposit.json"
    if not path.exists():
        return []
    out = []
    for e in json.loads(path.read_text()):
        nominal = nominal_wire_fed_kg(cfg, e["t_s"])
        out.append((e["t_s"], 100 * e["wire_fed_kg"] / nominal if nominal > 0 else 100.0, e["wire_stalled_s"]))
    return out


def _fmt(col: str, row: dict) -> str:
    if col not in row:
        return "–"
    if col in ("t_s", "waited_s"):
        return f"{row[col]:.3f}"
    return f"{row[col]:.0f}" if col.endswith("_W") else f"{row[col]:.2f}"


def collar_rows(run: Path, t_min: float, every: int, radius: float, above: float, beams: bool):
    cfg = json.loads((run / "config.json").read_text())
    cfg.pop("case", None)
    rho0 = cfg["fluid"]["rho0_kg_m3"]
    traced = None
    if beams:
        scene, sim = make_simulation(cfg)
        traced = (sim.thermal.beams, scene.dx)
    feed = _feed_record(run, cfg)
    snaps = sorted(run.glob("snap_*.h5"))
    for i, path in enumerate(snaps):
        with h5py.File(path) as f:
            t = float(f.attrs["time"])
            if t < t_min or (i % every and i != len(snaps) - 1):
                continue
            x = torch.as_tensor(f["position"][:])
            body = torch.as_tensor(f["body"][:])
            phase = torch.as_tensor(f["phase"][:])
            m = torch.as_tensor(f["mass"][:])
        melt = phase == Phase.FLUID
        collar = melt & (x[:, :2].norm(dim=1) < radius) & (x[:, 2] > above)
        wire = (body == WIRE) & ~melt
        row = {"t_s": t, "collar_mm3": float(m[collar].sum()) / rho0 * 1e9, "melt_mm3": float(m[melt].sum()) / rho0 * 1e9,
               "top_of_melt_mm": float(x[melt, 2].max()) * 1e3 if melt.any() else float("nan"),
               "wire_tip_mm": float(x[wire, 2].min()) * 1e3 if wire.any() else float("nan")}
        if feed:
            rec = min(feed, key=lambda e: abs(e[0] - t))
            row |= {"fed_pct": rec[1], "waited_s": rec[2]}
        if traced is not None:
            every_row = torch.ones(x.shape[0], dtype=torch.bool)
            P = sum(beam_power(x, every_row, b, t, traced[1]) for b in traced[0])
            row |= {"P_wire_W": float(P[wire].sum()), "P_collar_W": float(P[collar].sum()),
                    "P_other_melt_W": float(P[melt & ~collar].sum()), "P_solid_W": float(P[~melt & ~wire].sum())}
        yield row


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("runs", type=Path, nargs="+")
    ap.add_argument("--t-min", type=float, default=0.0, help="first snapshot time (s)")
    ap.add_argument("--every", type=int, default=1, help="every n-th snapshot (and the last)")
    ap.add_argument("--radius-mm", type=float, default=1.5, help="distance from the wire's axis (mm)")
    ap.add_argument("--above-mm", type=float, default=0.8, help="height above the substrate's top (mm)")
    ap.add_argument("--no-beams", action="store_true", help="skip the beams' power split (faster)")
    a = ap.parse_args(argv)
    cols = ["t_s", "collar_mm3", "melt_mm3", "top_of_melt_mm", "wire_tip_mm", "fed_pct", "waited_s"]
    if not a.no_beams:
        cols += ["P_wire_W", "P_collar_W", "P_other_melt_W", "P_solid_W"]
    for run in a.runs:
        print(f"\n{run}: collar = melt within {a.radius_mm} mm of the wire's axis, > {a.above_mm} mm above the top")
        print("| " + " | ".join(cols) + " |")
        print("|" + "---|" * len(cols))
        for r in collar_rows(run, a.t_min, a.every, a.radius_mm * 1e-3, a.above_mm * 1e-3, not a.no_beams):
            print("| " + " | ".join(_fmt(c, r) for c in cols) + " |", flush=True)


if __name__ == "__main__":
    main()
