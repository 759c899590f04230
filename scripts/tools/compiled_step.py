"""The step between rebuilds compiled whole, against eager, on a run's checkpoint.

    python scripts/tools/compiled_step.py CHECKPOINT [--backend inductor] [--mode reduce-overhead] [--steps 200]

``torch.compile(fullgraph=True, dynamic=True)`` of the step's three traced parts
(:mod:`torchsph.step.integrator`: ``first_half``, ``close_momentum``, ``close_energy``), then ``--steps``
timed steps after 5 warm-up steps (which compile), against the same steps eager in a second
simulation from the same checkpoint. Prints ms per step, the median plain step and the mean
rebuild step of each. On a GPU, ``--mode reduce-overhead`` captures the parts as CUDA graphs.
One thread on the CPU."""
from __future__ import annotations

import argparse
import statistics
import sys
import time
from pathlib import Path

import torch

sys.path.insert(0, str(Path(__file__).resolve().parents[2]))
sys.path.insert(0, str(Path(__file__).resolve().parent))
from bench_deposition_driver import timed_steps  # noqa: E402
from torchsph.step import integrator as step  # noqa: E402
from torchsph.step.loop import run_steps  # noqa: E402
from torchsph.run.build import simulation_from_run  # noqa: E402

PARTS = ("first_half", "close_momentum", "close_energy")


def timed(sim, n):
    out = timed_steps(sim, run_steps, n)
    plain = [t for t, r, _ in out if not r]
    reb = [t for t, r, _ in out if r]
    return {"ms_per_step": 1e3 * sum(t for t, _, _ in out) / n,
            "plain_ms": 1e3 * statistics.median(plain) if plain else float("nan"),
            "rebuilds": len(reb), "rebuild_step_ms": 1e3 * statistics.mean(reb) if reb else float("nan")}


def main():
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("checkpoint", type=Path)
    ap.add_argument("--backend", default="inductor")
    ap.add_argument("--mode", default=None)
    ap.add_argument("--steps", type=int, default=200)
    a = ap.parse_args()
    torch.set_num_threads(1)
    rows = {}
    for name in ("eager", "compiled"):
        _, sim = simulation_from_run(a.checkpoint)
        if name == "compiled":
            originals = {p: getattr(step, p) for p in PARTS}
            for p in PARTS:
                setattr(step, p, torch.compile(originals[p], fullgraph=True, dynamic=True, backend=a.backend,
                                               mode=a.mode))
        t = time.perf_counter()
        run_steps(sim, steps=5)
        warm = time.perf_counter() - t
        rows[name] = timed(sim, a.steps) | {"warm_up_s": warm}
        if name == "compiled":
            for p in PARTS:
                setattr(step, p, originals[p])
    for name, r in rows.items():
        print(f"{name:9s} " + "  ".join(f"{k} {v:.4g}" for k, v in r.items()))


if __name__ == "__main__":
    main()
