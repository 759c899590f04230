"""Strong scaling of the MPI slabs: the same case on 1 and on N ranks, side by side.

    python scripts/tools/mpi_scaling.py [CASE] [--ranks 2] [--steps 300 | --t-end T] [--preview]
                                  [--balance]

Runs ``mpiexec -n 1`` and ``mpiexec -n N`` one after the other (OMP_NUM_THREADS=1 per rank,
so N ranks use N cores), and prints wall time, particle-steps/s, the speed-up, the number of
migrations and the load imbalance (max / mean over ranks of the work, i.e. step time less
communication) from summary.json. With
``--balance`` it also runs N ranks with cost-weighted rebalancing off
(``numerics.rebalance_every = 0``: the equal-count slabs of the start are kept), so the
imbalance with and without it is measured side by side.
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

ROOT = Path(__file__).resolve().parents[2]


def main():
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("case", nargs="?", default=str(ROOT / "cases" / "sloshing_tank_3d"))
    ap.add_argument("--ranks", type=int, default=2)
    ap.add_argument("--steps", type=int, default=300)
    ap.add_argument("--t-end", type=float, default=None, help="process time instead of --steps")
    ap.add_argument("--preview", action="store_true", help="the case's [preview] (deposition cases)")
    ap.add_argument("--balance", action="store_true", help="also N ranks without rebalancing")
    ap.add_argument("--set", action="append", default=[])
    a = ap.parse_args()
    mpiexec = shutil.which("mpiexec", path=str(Path(sys.executable).parent)) or shutil.which("mpiexec")
    env = {**os.environ, "OMP_NUM_THREADS": "1", "PYTHONPATH": str(ROOT)}
    rows = []
    with tempfile.TemporaryDirectory() as td:
        runs = [(1, []), (a.ranks, [])] + ([(a.ranks, ["numerics.rebalance_every=0"])] if a.balance else [])
        for i, (n, extra) in enumerate(runs):
            out = Path(td) / f"run{i}"
            length = ["--t-end", str(a.t_end)] if a.t_end is not None else ["--steps", str(a.steps)]
            cmd = ([mpiexec, "-n", str(n), sys.executable, "-m", "torchsph", a.case, "--quiet", "--out", str(out)]
                   + length + (["--preview"] if a.preview else []) + [x for s in a.set + extra for x in ("--set", s)])
            subprocess.run(cmd, cwd=ROOT, env=env, check=True)
            s = json.loads((out / "summary.json").read_text())
            rows.append((n, "off" if extra else "on", s))
    base = rows[0][2]["wall_s"]
    s0 = rows[0][2]
    print(f"case {a.case}{' (preview)' if a.preview else ''}, {s0['n_particles']} particles at the start, "
          f"{s0['steps']} steps to t = {s0['t_final_s']:.4g} s")
    print("| ranks | rebalancing | wall s | particle-steps/s | speed-up | migrations | imbalance: first "
          "migrations / last / mean | slab bounds mm |")
    print("|---|---|---|---|---|---|---|---|")
    for n, bal, s in rows:
        li = s.get("load_imbalance") or {}
        f, last, hist = li.get("first_migrations"), li.get("last"), li.get("history") or []
        imb = f"{f:.3f} / {last:.3f} / {sum(hist) / len(hist):.3f}" if f is not None and hist else "-"
        bounds = ", ".join(f"{b * 1e3:.2f}" for b in s.get("slab_bounds_m", [])) or "-"
        print(f"| {n} | {bal if n > 1 else '-'} | {s['wall_s']:.1f} | {s['particle_steps_per_s']:.3g} | "
              f"{base / s['wall_s']:.2f}x | {s.get('migrations', 0)} | {imb} | {bounds} |")


if __name__ == "__main__":
    main()
