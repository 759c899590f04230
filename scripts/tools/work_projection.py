"""How a fine run's work set grows, projected from a coarse run of the same scene.

    python scripts/tools/work_projection.py COARSE_RUN_DIR [--dx 0.1e-3] [--every 5]
        [--cost-a MS --cost-b MS_PER_1000] [--steps-per-ms 566]

The active set (``torchsph.step.active``) is the heated zone (|T - ambient| > the case's
``active_tolerance_K``, or melt) grown by margins of the kernel support and the Verlet
skin. Where heat has diffused (a 1 K rise), the temperature field is set by conduction over
millimetres and hardly depends on the resolution; the margins do (3.5 dx). So the coarse
run's snapshots give the fine run's sets: each snapshot's seeds are grown with the *fine*
resolution's radii (`torchsph.step.active.dilate` on the coarse particles), and the counts are
scaled by (dx_coarse / dx_fine)^3 (particles per volume).

With a cost model ``ms/step = a + b * work / 1000`` (``--cost-a``, ``--cost-b``, measured on
the fine scene, e.g. by ``scripts/tools/step_cost.py``), it prints the projected run time:
the integral of the step cost over the run at ``--steps-per-ms`` steps per millisecond of
process (to ``--t-end``, the last snapshot's cost held beyond it). Rows are printed as a table (t, seeds, conducting, work, projected ms/step).
"""
from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np
import torch

sys.path.insert(0, str(Path(__file__).resolve().parents[2]))
from torchsph.step.active import dilate  # noqa: E402
from torchsph.io.snapshots import read_snapshot  # noqa: E402
from torchsph.core.kernels import make_kernel  # noqa: E402
from torchsph.post.analysis import load_run  # noqa: E402
from torchsph.core.state import Phase  # noqa: E402


def fine_sets(snap: dict, tol: float, ambient: float, support: float, search: float) -> tuple[int, int, int]:
    """Seeds, active (conducting) and work counts of one coarse snapshot, grown with the
    fine radii (the coarse run's own counts)."""
    x = torch.from_numpy(np.ascontiguousarray(snap["position"]))
    seed = torch.from_numpy((snap["phase"] == int(Phase.FLUID)) | (np.abs(snap["temperature"] - ambient) > tol))
    core = dilate(x, seed, search)
    active = dilate(x, core, support)
    work = dilate(x, active, search)
    return int(seed.sum()), int(active.sum()), int(work.sum())


def main():
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("run", type=Path, help="a coarse run's output folder (config.json, snap_*.h5)")
    ap.add_argument("--dx", type=float, default=None, help="the fine resolution, m (default: the case's own)")
    ap.add_argument("--case", type=Path, default=None, help="the fine case folder (for --dx's default)")
    ap.add_argument("--every", type=int, default=1, help="every n-th snapshot")
    ap.add_argument("--cost-a", type=float, default=None, help="ms per step at no work (the fit's intercept)")
    ap.add_argument("--cost-b", type=float, default=None, help="ms per step per 1000 working particles")
    ap.add_argument("--steps-per-ms", type=float, default=None, help="steps per millisecond of process (fine run)")
    ap.add_argument("--t-end", type=float, default=None,
                    help="project to this time (s), the last snapshot's cost held beyond it (a lower bound: the work only grows)")
    a = ap.parse_args()
    cfg, snaps = load_run(a.run)
    dx_c = float(cfg["scene"]["dx_m"])
    dx_f = a.dx
    if dx_f is None:
        if a.case is None:
            ap.error("give --dx or --case")
        import tomllib
        dx_f = float(tomllib.loads((a.case / "case.toml").read_text())["scene"]["dx_m"])
    nm = cfg["numerics"]
    kernel = make_kernel(nm["kernel"], 3)
    support = kernel.radius(nm["h_over_dx"] * dx_f)
    search = support + nm["skin_over_dx"] * dx_f
    tol, ambient = float(nm["active_tolerance_K"]), float(cfg["thermal"]["ambient_K"])
    scale = (dx_c / dx_f) ** 3
    print(f"coarse run dx = {dx_c * 1e3:g} mm, fine dx = {dx_f * 1e3:g} mm: counts x {scale:.1f}; "
          f"fine support {support * 1e3:.3f} mm, search {search * 1e3:.3f} mm, tolerance {tol:g} K")
    cost = a.cost_a is not None and a.cost_b is not None
    print("| t (ms) | coarse particles | fine: seeds | fine: conducting | fine: work |"
          + (" ms/step |" if cost else ""))
    print("|---|---|---|---|---|" + ("---|" if cost else ""))
    rows = []
    for t, p in snaps[::max(a.every, 1)]:
        s = read_snapshot(p)
        n_seed, n_act, n_work = (round(v * scale) for v in fine_sets(s, tol, ambient, support, search))
        ms = a.cost_a + a.cost_b * n_work / 1000 if cost else None
        rows.append((t, n_work, ms))
        print(f"| {t * 1e3:.0f} | {s['position'].shape[0]} | {n_seed} | {n_act} | {n_work} |"
              + (f" {ms:.0f} |" if cost else ""))
    if cost and a.steps_per_ms and len(rows) > 1:
        t = np.array([r[0] for r in rows])
        ms = np.array([r[2] for r in rows])
        if a.t_end is not None and a.t_end > t[-1]:
            t, ms = np.append(t, a.t_end), np.append(ms, ms[-1])
        hours = np.trapezoid(ms, t * 1e3) * a.steps_per_ms / 1e3 / 3600
        print(f"projected: {hours:.1f} h for t = {t[0] * 1e3:.0f}..{t[-1] * 1e3:.0f} ms "
              f"({a.steps_per_ms:g} steps per ms, ms/step = {a.cost_a:g} + {a.cost_b:g} x work/1000)")


if __name__ == "__main__":
    main()
