"""What each shipped case costs on this machine: `python -m torchsph CASE --estimate` for every
case folder (and the deposition cases' --preview), one after the other, one process, as a
markdown table (the README's cost table).

    python scripts/tools/cost_table.py [CASE ...] [--threads 1] [--against-run]

--against-run also runs each case to its end after the estimate (for cases that finish in
minutes) and adds the run's real wall time and the ratio projected / real.

Each row: particles, memory after set-up, steps to the end (from the time-step limits at
t = 0 and, where melt will flow, the melt's acoustic limit at 10 % Mach), snapshots on disk,
the probe (steps 2.. of the run, up to 20 steps or 15 s) and the projected wall time.
"""
from __future__ import annotations

import argparse
import contextlib
import io
import json
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import torch

ROOT = Path(__file__).resolve().parents[2]
sys.path.insert(0, str(ROOT))

from torchsph.io.config import load_case  # noqa: E402
from torchsph.run.progress import GB, hms  # noqa: E402
from torchsph.run.runner import run_case  # noqa: E402


def estimate(case: Path, preview: bool) -> dict:
    _, cfg = load_case(case, preview=preview)
    t0 = time.perf_counter()
    with tempfile.TemporaryDirectory() as td, contextlib.redirect_stderr(io.StringIO()):
        r = run_case(cfg, case, Path(td) / "out", progress=False, estimate=True)
    r["wall_s"] = time.perf_counter() - t0
    return r


def real_run(case: Path, preview: bool) -> float:
    """The stepping wall time of the whole run (no set-up), in this process."""
    _, cfg = load_case(case, preview=preview)
    with tempfile.TemporaryDirectory() as td, contextlib.redirect_stderr(io.StringIO()):
        s = run_case(cfg, case, Path(td) / "out", progress=False)
    return s["wall_last_leg_s"]


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("cases", nargs="*", type=Path)
    ap.add_argument("--threads", type=int, default=1)
    ap.add_argument("--against-run", action="store_true", help="run each case too: projected vs real wall")
    ap.add_argument("--one", action="store_true", help=argparse.SUPPRESS)  # one case in this process
    ap.add_argument("--preview", action="store_true", help=argparse.SUPPRESS)
    a = ap.parse_args(argv)
    torch.set_num_threads(a.threads)
    if a.one:  # a fresh process per case: its peak memory is the case's own
        r = estimate(a.cases[0], a.preview)
        if a.against_run:
            r["real_wall_s"] = real_run(a.cases[0], a.preview)
        print(json.dumps(r, default=float))
        return
    cases = a.cases or sorted(p.parent for p in (ROOT / "cases").glob("*/case.toml"))
    extra = " real wall | projected / real |" if a.against_run else ""
    print("| case | particles | memory | steps to the end (dt, binding) | snapshots | ms/step (probe) | "
          "projected wall | --estimate took |" + extra)
    print("|---|---|---|---|---|---|---|---|" + ("---|---|" if a.against_run else ""))
    for case in cases:
        variants = [False] + ([True] if "[preview]" in (case / "case.toml").read_text() else [])
        for pv in variants:
            t0 = time.perf_counter()
            out = subprocess.run([sys.executable, __file__, str(case), "--one", "--threads", str(a.threads)]
                                 + (["--preview"] if pv else []) + (["--against-run"] if a.against_run else []),
                                 capture_output=True, text=True, check=True)
            r = json.loads(out.stdout.strip().splitlines()[-1])
            r["wall_s"] = time.perf_counter() - t0  # the whole command: start, set-up, probe (and run)
            c = r["estimate"]
            name = case.name + (" --preview" if pv else "")
            print(f"| `{name}` | {c['n_all']:,} | {c['rss_gb']:.1f} GB | {c['steps_left']:,.0f} ({c['dt_s']:.2g} s, "
                  f"{c['dt_why']}) | {c['snapshots']} × {c['snapshot_bytes'] / 2**20:.1f} MB = "
                  f"{c['snapshots'] * c['snapshot_bytes'] / GB:.2f} GB | "
                  f"{1e3 * r['probe_wall_s'] / r['probe_steps']:.1f} | {hms(r['projected_wall_s'])} | "
                  f"{r['wall_s']:.0f} s |" + (f" {hms(r['real_wall_s'])} | {r['projected_wall_s'] / r['real_wall_s']:.2f} |"
                                               if a.against_run else ""), flush=True)


if __name__ == "__main__":
    main()
