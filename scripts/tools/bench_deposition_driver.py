"""One measurement of ``scripts/tools/bench.py --deposition`` in one process, on the code of the
tree ``--tree`` (this repository, or a reference commit's worktree). Prints one JSON line.

    python scripts/tools/bench_deposition_driver.py --tree DIR preview --checkpoint CK [--steps N]
        (any run's checkpoint: the preview's, or the full scene's developed state)
    python scripts/tools/bench_deposition_driver.py --tree DIR full [--steps N] [--set key=value ...]

It uses only what every version since b14e316 offers (``load_case``, ``make_simulation``,
``simulation_from_run``, ``run_steps``) and counts host synchronisations with this
repository's :mod:`torchsph.core.syncs`, loaded by file path (so the reference code is counted
the same way). One thread.
"""
from __future__ import annotations

import argparse
import contextlib
import importlib.util
import json
import os
import resource
import statistics
import sys
import time
import warnings
from pathlib import Path

HERE = Path(__file__).resolve().parents[2]


def load_counter():
    spec = importlib.util.spec_from_file_location("_bench_syncs", HERE / "torchsph" / "core" / "syncs.py")
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod.SyncCounter


def refreshes(sim) -> int | None:
    """Refreshes of the active set so far (None: a code that does not count them)."""
    return getattr(getattr(sim, "active_set", None), "n_refresh", None)


def timed_steps(sim, run_steps, n):
    """Per-step wall times, whether each step rebuilt the neighbour list, and whether that
    rebuild refreshed the active set (the heated zone reached its edge: new rows everywhere)."""
    out = []
    for _ in range(n):
        b, f = sim.nl.n_builds, refreshes(sim)
        t = time.perf_counter()
        run_steps(sim, steps=1)
        rebuilt = sim.nl.n_builds > b
        out.append((time.perf_counter() - t, rebuilt, rebuilt and f is not None and refreshes(sim) != f))
    return out


def summary(sim, times, setup_s, syncs_plain, syncs_rebuild, n0):
    plain = [t for t, r, _ in times if not r]
    reb = [t for t, r, _ in times if r]
    nbr = [t for t, r, f in times if r and not f]  # neighbour rebuilds that kept the active set
    fresh = [t for t, _, f in times if f]  # and those that refreshed it
    med = statistics.median(plain) if plain else float("nan")
    total = sum(t for t, _, _ in times)
    extra = lambda v: 1e3 * (statistics.mean(v) - med) if v else None  # noqa: E731
    return {
        "particles": n0, "steps": len(times), "ms_per_step": 1e3 * total / len(times),
        "ms_plain_step": 1e3 * med,
        "rebuilds": len(reb),
        "rebuild_ms": extra(reb),
        "neighbour_rebuilds": len(nbr), "neighbour_rebuild_ms": extra(nbr),
        "refreshes": len(fresh), "refresh_ms": extra(fresh),
        "particle_steps_per_s": n0 * len(times) / total,
        "peak_rss_GB": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 2**20,
        "syncs_per_plain_step": syncs_plain, "syncs_per_rebuild_step": syncs_rebuild,
        "setup_s": setup_s, "t": sim.t,
    }


def count_syncs(sim, run_steps, Counter, steps=10):
    """Mean syncs over ``steps`` steps, split into steps without and with a rebuild."""
    plain, reb = [], []
    for _ in range(steps):
        b = sim.nl.n_builds
        with Counter() as c:
            run_steps(sim, steps=1)
        (reb if sim.nl.n_builds > b else plain).append(c.total)
    m = lambda v: statistics.mean(v) if v else None  # noqa: E731
    return m(plain), m(reb)


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--tree", type=Path, required=True)
    ap.add_argument("what", choices=("preview", "full"))
    ap.add_argument("--checkpoint", type=Path, default=None)
    ap.add_argument("--steps", type=int, default=100)
    ap.add_argument("--set", dest="overrides", action="append", default=[], help="full: a case key, key=value")
    a = ap.parse_args()
    os.environ["OMP_NUM_THREADS"] = "1"
    sys.path.insert(0, str(a.tree.resolve()))
    warnings.filterwarnings("ignore")
    import torch

    torch.set_num_threads(1)
    try:  # this layout (torchsph/io, run, step), or a commit's from before it (a flat torchsph/)
        from torchsph.io.config import SURFACE, load_case
        from torchsph.run import runner
        from torchsph.run.build import make_simulation, simulation_from_run
        from torchsph.step.loop import run_steps
    except ImportError:
        from torchsph import runner
        from torchsph.config import SURFACE, load_case
        from torchsph.runner import make_simulation, run_steps, simulation_from_run

    # each tree steps in the mode its CLI runs in (this code: inference mode, runner.STEP_MODE)
    with getattr(runner, "STEP_MODE", contextlib.nullcontext)():
        Counter = load_counter()
        t0 = time.perf_counter()
        if a.what == "preview":
            _, sim = simulation_from_run(a.checkpoint)
            # a neighbour build now, as after a restart from another version's checkpoint
            if hasattr(sim, "rebuild"):  # (this code: the pairs, and the rates evaluated on them)
                sim.rebuild()
            else:
                (getattr(sim, "refresh_pairs", None) or getattr(sim, "_refresh_pairs"))(force=True)
        else:
            # the reference's physics: no wetting model (as b14e316)
            case = a.tree / "cases" / "perpendicular_350W"
            ov = (["surface.wetting=false"] if "wetting" in SURFACE else []) + (
                ["solid_contact.enabled=false"] if "[solid_contact]" in (case / "case.toml").read_text() else [])
            _, cfg = load_case(case, ov + a.overrides)
            _, sim = make_simulation(cfg)
        setup = time.perf_counter() - t0
        n0 = sim.state.n
        if a.what == "preview":  # warm up, then time; syncs counted on steps after the timed ones
            run_steps(sim, steps=5)
            times = timed_steps(sim, run_steps, a.steps)
            sp, sr = count_syncs(sim, run_steps, Counter)
        else:  # the first steps: count syncs on steps 2..11, time the rest
            run_steps(sim, steps=1)
            sp, sr = count_syncs(sim, run_steps, Counter)
            times = timed_steps(sim, run_steps, a.steps)
        print(json.dumps(summary(sim, times, setup, sp, sr, n0)))


if __name__ == "__main__":
    main()
