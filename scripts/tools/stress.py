"""Stability stress test: run a drop and the cube with a fixed time step at multiples of
the automatic limit, and the cube at multiples of its power, and report where each run
blows up against the predicted limit, with the diagnosis the solver printed.

    python scripts/tools/stress.py            # both scenes (several minutes on 2 cores)
    python scripts/tools/stress.py --quick    # fewer factors
"""
from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import torch

ROOT = Path(__file__).resolve().parents[2]
sys.path.insert(0, str(ROOT))

from torchsph.io.config import load_case  # noqa: E402
from torchsph.run.build import make_simulation  # noqa: E402
from torchsph.step.loop import run_steps  # noqa: E402
from torchsph.step.simulation import SimulationError  # noqa: E402


def attempt(case, over, t_end=None, steps=None):
    """(outcome, steps done, diagnosis or peak numbers) of one run."""
    _, cfg = load_case(ROOT / "cases" / case, over)
    try:
        _, sim = make_simulation(cfg)
    except SimulationError as e:
        return "refused", 0, str(e)
    peak = {"T": 0.0, "v": 0.0}

    def cb(sim, info):
        peak["T"] = max(peak["T"], float(sim.state.T.max()))
        peak["v"] = max(peak["v"], info.vmax)

    t0 = time.perf_counter()
    try:
        run_steps(sim, t_end=t_end, steps=steps, callback=cb)
    except SimulationError as e:
        return "blew up", sim.step, str(e)
    return "stable", sim.step, (f"peak T {peak['T']:.0f} K, max |u| {peak['v']:.3g} m/s, "
                                f"{time.perf_counter() - t0:.0f} s")


def predicted(case, over):
    _, cfg = load_case(ROOT / "cases" / case, over)
    _, sim = make_simulation(cfg)
    return sim.binding_limit(), sim.limits()


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true")
    ap.add_argument("--scenes", nargs="*", default=["drop", "cube"], choices=["drop", "cube"])
    args = ap.parse_args()
    torch.set_num_threads(max(1, torch.get_num_threads()))
    factors = [1.0, 2.0, 4.0] if args.quick else [0.5, 1.0, 1.5, 2.0, 4.0, 8.0]
    rows = []
    # 1) a drop: mode-2 oscillation, 2-D, R = 10 dx
    drop = ["scene.dx_m=1e-4"]
    (name, lim), _ = predicted("oscillating_drop_2d", drop)
    for f in factors if "drop" in args.scenes else []:
        out, k, msg = attempt("oscillating_drop_2d", drop + [f"numerics.dt_s={f * lim}",
                                                             "numerics.allow_unstable_dt=true"], steps=round(600 / f))
        rows.append(("drop 2-D", f"dt = {f:g} x {name} limit {lim:.3g} s", out, k, msg))
    # 2) the cube (preview) for its first 20 ms (melting starts at ~14 ms). At t = 0 the cube
    # is solid and only the thermal limit applies; once it melts the acoustic limit
    # cfl h / (c0 + |u|) binds: the predicted limit is cfl h / c0.
    cube = ["run.t_end_s=0.02", "numerics.compile=true"]
    _, cfg = load_case(ROOT / "cases" / "cube_evaporation_preview", cube)
    name = "acoustic"
    lim = cfg["numerics"]["cfl"] * cfg["numerics"]["h_over_dx"] * cfg["scene"]["dx_m"] / cfg["fluid"]["c0_m_s"]
    for f in factors if "cube" in args.scenes else []:
        out, k, msg = attempt("cube_evaporation_preview", cube + [f"numerics.dt_s={f * lim}",
                                                                  "numerics.allow_unstable_dt=true"], t_end=0.02)
        rows.append(("cube 300 W", f"dt = {f:g} x {name} limit {lim:.3g} s", out, k, msg))
    powers = [1200.0, 4800.0] if args.quick else [600.0, 1200.0, 2400.0, 4800.0, 9600.0]
    for p in powers if "cube" in args.scenes else []:
        out, k, msg = attempt("cube_evaporation_preview", cube + [f"beam.power_W={p}"], t_end=0.02)
        rows.append(("cube", f"power {p:g} W, automatic dt", out, k, msg))
    print("| scene | run | outcome | steps | diagnosis / result |")
    print("|---|---|---|---|---|")
    for r in rows:
        print("| " + " | ".join(str(c) for c in r) + " |")


if __name__ == "__main__":
    main()
