"""Strong scaling of the MPI slabs: the same case on 1 and on N ranks, side by side.

    python scripts/mpi_scaling.py [CASE] [--ranks 2] [--steps 300]

Runs ``mpiexec -n 1`` and ``mpiexec -n N`` one after the other (OMP_NUM_THREADS=1 per rank,
so N ranks use N cores), and prints wall time, particle-steps/s, the speed-up, the number of
migrations and the load imbalance (max / mean rank step time) from summary.json.
"""
from __future__ import annotations

import argparse
import json
import os
import shutil
import subprocess
import sys
import tempfile
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def main():
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("case", nargs="?", default=str(ROOT / "cases" / "sloshing_tank_3d"))
    ap.add_argument("--ranks", type=int, default=2)
    ap.add_argument("--steps", type=int, default=300)
    ap.add_argument("--set", action="append", default=[])
    a = ap.parse_args()
    mpiexec = shutil.which("mpiexec", path=str(Path(sys.executable).parent)) or shutil.which("mpiexec")
    env = {**os.environ, "OMP_NUM_THREADS": "1", "PYTHONPATH": str(ROOT)}
    rows = []
    with tempfile.TemporaryDirectory() as td:
        for n in (1, a.ranks):
            out = Path(td) / f"n{n}"
            cmd = [mpiexec, "-n", str(n), sys.executable, "-m", "torchsph", a.case, "--quiet", "--steps",
                   str(a.steps), "--out", str(out)] + [x for s in a.set for x in ("--set", s)]
            subprocess.run(cmd, cwd=ROOT, env=env, check=True)
            s = json.loads((out / "summary.json").read_text())
            rows.append((n, s))
    base = rows[0][1]["wall_s"]
    print(f"case {a.case}, {rows[0][1]['n_particles']} particles, {a.steps} steps")
    print("| ranks | wall s | particle-steps/s | speed-up | migrations | imbalance first / last |")
    print("|---|---|---|---|---|---|")
    for n, s in rows:
        li = s.get("load_imbalance") or {}
        f = li.get("first_migrations")
        last = li.get("last")
        imb = f"{f:.3f} / {last:.3f}" if f is not None and last is not None else "-"
        print(f"| {n} | {s['wall_s']:.1f} | {s['particle_steps_per_s']:.3g} | {base / s['wall_s']:.2f}x | "
              f"{s.get('migrations', 0)} | {imb} |")


if __name__ == "__main__":
    main()
