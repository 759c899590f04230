"""float32 against float64 on the deposition scene: what the precision changes, what it
costs, and which quantities lose a step's increment in float32.

    python scripts/studies/precision.py [CASE] [--t 0.01 0.02] [--preview/--full]

Runs the case (default perpendicular_350W, preview resolution) from t = 0 in float64 and in
float32, one after the other, one thread, and prints at each time of ``--t``: the highest
temperature, the melt volume, the energy balance residual relative to the flows, and the
wall time per step. Then, from the float64 run's last step, for the particles the step
integrates: how a step's increment of specific enthalpy (dh = dt dh/dt) and of position
(dx = dt v) compares with the float32 spacing of the value it is added to (ulp): the
fraction of particles whose increment is below one ulp (lost entirely) or below 100 ulps
(kept to worse than 1 %), in float32 and in float64.
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
from torchsph.core.state import Phase  # noqa: E402


def run(case: Path, preview: bool, dtype: str, times: list[float]):
    _, cfg = load_case(case, [f"run.dtype=\"{dtype}\""], preview=preview)
    _, sim = make_simulation(cfg)
    rows = []
    for t in times:
        s0, w0 = sim.step, time.perf_counter()
        run_steps(sim, t_end=t)
        wall = time.perf_counter() - w0
        st = sim.state
        fluid = st.phase == Phase.FLUID
        rows.append({"t": t, "T_max": float(st.T.max()), "melt_mm3": float((st.m / st.rho)[fluid].sum()) * 1e9,
                     "residual": sim.energy_balance()["residual_rel"], "ms_step": 1e3 * wall / max(sim.step - s0, 1),
                     "steps": sim.step})
    return sim, rows


def ulp32(v: torch.Tensor) -> torch.Tensor:
    """The float32 spacing at |v| (numerically: nextafter toward +inf minus the value)."""
    a = v.abs().to(torch.float32)
    return (torch.nextafter(a, torch.full_like(a, float("inf"))) - a).double()


def increments(sim, dt: float) -> dict:
    th, st = sim.thermal, sim.state
    rows = th.rows
    h = th.to_enthalpy(st.T.index_select(0, rows)).double()
    dh = (dt * sim.dTdt.index_select(0, rows)).abs().double()
    moving = rows[(st.phase.index_select(0, rows) == Phase.FLUID) | (st.v.index_select(0, rows).abs().sum(-1) > 0)]
    x = st.x.index_select(0, moving).double()
    dxs = (dt * st.v.index_select(0, moving)).abs().double()
    out = {}
    for name, val, inc in (("enthalpy", h, dh), ("position", x, dxs)):
        keep = inc > 0
        if val.dim() > 1:
            keep = keep.reshape(-1)
            val, inc = val.reshape(-1), inc.reshape(-1)
        r = inc[keep] / ulp32(val[keep])
        r64 = r * 2.0 ** 29  # float64 has 29 more mantissa bits: its ulp is 2^-29 of float32's
        out[name] = {"n": int(keep.sum()), "lost32": float((r < 1).double().mean()),
                     "under100_32": float((r < 100).double().mean()), "under100_64": float((r64 < 100).double().mean()),
                     "median_ulps32": float(r.median())}
    return out


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("case", nargs="?", type=Path, default=ROOT / "cases" / "perpendicular_350W")
    ap.add_argument("--t", type=float, nargs="+", default=[0.01, 0.02])
    ap.add_argument("--full", action="store_true", help="the case's own resolution (default: its preview)")
    a = ap.parse_args(argv)
    torch.set_num_threads(1)
    res = {}
    for dtype in ("float64", "float32"):
        sim, rows = run(a.case, not a.full, dtype, a.t)
        res[dtype] = rows
        if dtype == "float64":
            inc = increments(sim, sim.choose_dt()[0])
    print("| t (s) | quantity | float64 | float32 | relative difference |")
    print("|---|---|---|---|---|")
    for r64, r32 in zip(res["float64"], res["float32"]):
        for k, label in (("T_max", "highest T (K)"), ("melt_mm3", "melt volume (mm³)"),
                         ("residual", "energy residual / flows"), ("ms_step", "ms per step"), ("steps", "steps")):
            a64, a32 = r64[k], r32[k]
            rel = abs(a32 - a64) / abs(a64) if a64 else float("nan")
            print(f"| {r64['t']:g} | {label} | {a64:.6g} | {a32:.6g} | {rel:.2e} |")
    print()
    print("| increment per step | particles | median (float32 ulps) | lost in float32 (< 1 ulp) | "
          "< 100 ulps in float32 | < 100 ulps in float64 |")
    print("|---|---|---|---|---|---|")
    for name, d in inc.items():
        print(f"| {name} | {d['n']} | {d['median_ulps32']:.3g} | {100 * d['lost32']:.1f} % | "
              f"{100 * d['under100_32']:.1f} % | {100 * d['under100_64']:.2f} % |")


if __name__ == "__main__":
    main()
