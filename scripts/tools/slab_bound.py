"""The most two slab ranks can gain on a run's state: the best cut along an axis, each rank
computing its side plus a halo of the other.

    python scripts/tools/slab_bound.py OUT/checkpoint.pt [--axis 0] [--halo-mm 2.3 0.35 ...]

Reads a one-process checkpoint and the ``config.json`` beside it. A particle's per-step work
is weighted as the decomposition's load balance weighs it: fluid 4, working (active) solid 1,
idle solid 0 (the step does not touch it). For a cut at c, rank 0 computes what lies below
c + halo and rank 1 what lies above c - halo (ghosts are computed as owned rows are); the
bound is the total work over the larger side at the best c, before any communication. The
case's own halo (``parallel.setup.halo_parts``) is always one of the rows.
"""
from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[2]))
from torchsph.io.checkpoint import arrays_of, load, state_arrays  # noqa: E402


def best_cut(x: np.ndarray, w: np.ndarray, halo: float, cuts: int = 800):
    """(bound, cut, work below, work above) at the best of ``cuts`` cuts across the worked span."""
    span = x[w > 0]
    order = np.argsort(x)
    xs, cw = x[order], np.concatenate([[0.0], np.cumsum(w[order])])
    best = None
    for c in np.linspace(span.min(), span.max(), cuts):
        lo = cw[np.searchsorted(xs, c + halo, side="left")]
        hi = cw[-1] - cw[np.searchsorted(xs, c - halo, side="left")]
        if best is None or max(lo, hi) < max(best[2], best[3]):
            best = (cw[-1] / max(lo, hi), c, lo, hi)
    return best


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("checkpoint", type=Path)
    ap.add_argument("--axis", type=int, default=0, help="0 = x (the decomposition's), 1 = y, 2 = z")
    ap.add_argument("--halo-mm", type=float, nargs="*", default=[], help="other halos to try, mm")
    a = ap.parse_args()
    d = load(a.checkpoint)
    cfg = json.loads((a.checkpoint.parent / "config.json").read_text())
    from parallel.setup import halo_parts

    own = halo_parts(cfg)["halo"]
    st, arrays = state_arrays(d), arrays_of(d)
    x = st["x"][:, a.axis].double().numpy()
    fluid = (st["phase"] == 0).numpy()
    active = arrays["as.active"].numpy() if "as.active" in arrays else np.ones_like(fluid)
    w = np.where(fluid, 4.0, np.where(active, 1.0, 0.0))
    print(f"# {a.checkpoint}: t = {d['t']:.4g} s, {x.size} particles, {int(active.sum())} active, {int(fluid.sum())} fluid; "
          f"worked span along axis {a.axis}: {x[w > 0].min() * 1e3:.2f} .. {x[w > 0].max() * 1e3:.2f} mm")
    print("| halo mm | best cut mm | work below | work above | total | bound on the 2-rank speed-up |")
    print("|---|---|---|---|---|---|")
    for halo in [own] + [v * 1e-3 for v in a.halo_mm]:
        b, c, lo, hi = best_cut(x, w, halo)
        tag = " (the case's)" if halo == own else ""
        print(f"| {halo * 1e3:.2f}{tag} | {c * 1e3:.2f} | {lo:.0f} | {hi:.0f} | {w.sum():.0f} | {b:.2f} |")


if __name__ == "__main__":
    main()
