"""Which force moves the melt on the wire: for each snapshot of a deposition run (from
--t-min on) the state is loaded into the run's simulation and each momentum term (pressure,
viscous, body, surface tension, Marangoni, recoil) evaluated; prints the mass-weighted mean
vertical acceleration over the melt particles near the wire above the substrate, per
snapshot and averaged over the snapshots.

    python scripts/studies/wire_forces.py RUN_DIR [--t-min 0.06] [--r-max 1e-3] [--z-min 0.4e-3]
"""
from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]
sys.path.insert(0, str(ROOT))

import torch  # noqa: E402

from torchsph.io import checkpoint as ckpt  # noqa: E402
from torchsph.io.snapshots import read_snapshot  # noqa: E402
from torchsph.run.build import make_simulation  # noqa: E402
from torchsph.core.state import ParticleState, Phase  # noqa: E402


def main():
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("run", type=Path)
    ap.add_argument("--t-min", type=float, default=0.0, help="first snapshot time (s)")
    ap.add_argument("--r-max", type=float, default=1.0e-3, help="distance from the wire axis (m)")
    ap.add_argument("--z-min", type=float, default=0.4e-3, help="height above the substrate's top (m)")
    a = ap.parse_args()
    cfg = json.loads((a.run / "config.json").read_text())
    _, sim = make_simulation(cfg)
    # the checkpoint sets up the terms a running scene has built (the fluid's appear with melt)
    ckpt.restore(sim, ckpt.load(a.run / "checkpoint.pt"), cfg, str(a.run / "checkpoint.pt"))
    sim.active_set = None  # every particle in the pair list: the snapshots differ in size
    sums, count = {}, 0
    for path in sorted(a.run.glob("snap_*.h5")):
        d = read_snapshot(path)
        if float(d["time"]) < a.t_min:
            continue
        f = lambda k: torch.as_tensor(d[k], dtype=sim.state.dtype)  # noqa: E731
        st = ParticleState(x=f("position"), v=f("velocity"), rho=f("density"), m=f("mass"), p=f("pressure"),
                           T=f("temperature"), T_peak=f("peak_temperature"),
                           phase=torch.as_tensor(d["phase"], dtype=torch.int8),
                           id=torch.as_tensor(d["id"], dtype=torch.long), body=torch.as_tensor(d["body"], dtype=torch.long))
        sim.state = st
        sim.refresh_pairs(force=True)
        _, parts = sim.accelerations(st.v, terms=True)
        sel = (st.phase == Phase.FLUID) & (st.x[:, :2].norm(dim=1) < a.r_max) & (st.x[:, 2] > a.z_min)
        n = int(sel.sum())
        if not n:
            continue
        m = st.m[sel]
        az = {k: float((acc[sel, 2] * m).sum() / m.sum()) for k, acc in parts.items()}
        az["sum"] = sum(az.values())
        print(f"t = {float(d['time']):.3f} s, {n:3d} particles, mean u_z {float(st.v[sel, 2].mean()):+.3f} m/s: "
              + ", ".join(f"{k} {v:+.0f}" for k, v in az.items()), flush=True)
        for k, v in az.items():
            sums[k] = sums.get(k, 0.0) + v
        count += 1
    if count:
        print(f"mean over {count} snapshots (m/s^2, +z up): "
              + ", ".join(f"{k} {v / count:+.0f}" for k, v in sums.items()))

if __name__ == "__main__":
    main()
