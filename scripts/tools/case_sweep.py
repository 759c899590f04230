"""Every shipped case through the CLI, as a user runs it: on one process or on MPI ranks, a few
steps each, with the exit code and the run's last line (or its error) per case.

    python scripts/tools/case_sweep.py                       # one process, 5 steps each
    python scripts/tools/case_sweep.py --ranks 2 --steps 5   # mpirun -n 2 (mpirun from the venv)
    python scripts/tools/case_sweep.py --ranks 3 --set numerics.shifting=0.3 --only taylor_green_2d

A case that must be refused says why in its line; any other non-zero exit is a defect. Exits with
the number of cases that failed.
"""
from __future__ import annotations

import argparse
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--ranks", type=int, default=1)
    ap.add_argument("--steps", type=int, default=5)
    ap.add_argument("--set", dest="overrides", action="append", default=[])
    ap.add_argument("--only", nargs="*", default=None, help="case names (default: every case)")
    ap.add_argument("--timeout", type=float, default=600.0, help="per case, s")
    a = ap.parse_args()
    cases = sorted(p.parent.name for p in (ROOT / "cases").glob("*/case.toml"))
    cases = [c for c in cases if a.only is None or c in a.only]
    launch = [sys.executable]
    if a.ranks > 1:
        mpirun = shutil.which("mpirun", path=str(Path(sys.executable).parent)) or shutil.which("mpirun")
        if mpirun is None:
            sys.exit("no mpirun (pip install mpich)")
        launch = [mpirun, "-n", str(a.ranks), sys.executable]
    failed = 0
    print("| case | exit | wall s | last line |\n|---|---|---|---|")
    with tempfile.TemporaryDirectory() as tmp:
        for c in cases:
            cmd = launch + ["-m", "torchsph", str(ROOT / "cases" / c), "--steps", str(a.steps), "--quiet",
                            "--threads", "1", "--out", str(Path(tmp) / c)]
            for o in a.overrides:
                cmd += ["--set", o]
            t = time.perf_counter()
            try:
                r = subprocess.run(cmd, cwd=ROOT, capture_output=True, text=True, timeout=a.timeout)
                rc, out = r.returncode, (r.stdout + r.stderr).strip().splitlines()
            except subprocess.TimeoutExpired:
                rc, out = "timeout", []
            lines = [ln for ln in out if ln.startswith("torchsph")]
            last = (lines or out or [""])[-1 if rc == 0 else 0][:200].replace("|", "/")
            failed += rc != 0
            print(f"| {c} | {rc} | {time.perf_counter() - t:.1f} | {last} |", flush=True)
    sys.exit(failed)


if __name__ == "__main__":
    main()
