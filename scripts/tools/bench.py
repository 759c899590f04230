"""Run time against error: the 2-D Taylor-Green vortex on exactly the work the established
SPH codes were measured on (../shared/PERF.md): unit periodic box, Re = 100, U = 1,
rho0 = 1, c0 = 10 U, lattice start, t_end = 1, nx in {50, 100, 200}.

    python scripts/tools/bench.py            # all rows, float64 and float32 (CUDA rows when present)
    python scripts/tools/bench.py --quick    # nx = 50 only
    python scripts/tools/bench.py --deposition [--ref b14e316]   # the deposition step against a commit
    python scripts/tools/bench.py --deposition --mpi [--mpi-steps N] [--developed CK] [--case DIR] [--set k=v]
        # one process on 1 thread, on 2 threads, and 2 ranks of 1 thread (scripts/tools/bench_mpi.py):
        # ms/step, the speed-ups, owned and ghost particles per rank, halo, bytes sent per step,
        # imbalance; on the case's first steps and, with --developed, from that checkpoint

linf = |max|u|(t_end) / (U exp(-8 pi^2 t / Re)) - 1|;
L1 = mean | |u_i| - |u_exact(x_i)| | / mean |u_exact(x_i)|.
"loop wall" times the time loop only; "setup" (scene, first neighbour build, and the
torch.compile of the pair loops when on) is reported separately.
"""
from __future__ import annotations

import argparse
import math
import sys
import time
from pathlib import Path

import torch

sys.path.insert(0, str(Path(__file__).resolve().parents[2]))

from torchsph.io.config import load_case  # noqa: E402
from torchsph.run.build import make_simulation  # noqa: E402
from torchsph.step.loop import run_steps  # noqa: E402
from torchsph.core.analytic import taylor_green_exact  # noqa: E402

CASE = Path(__file__).resolve().parents[2] / "cases" / "taylor_green_2d"


def tg_errors(sim, info, t):
    s = sim.state
    exact_max = info["U"] * math.exp(-8.0 * math.pi**2 * info["nu"] * t / info["L"] ** 2)
    speed = torch.sqrt((s.v * s.v).sum(-1))
    ue = taylor_green_exact(s.x, t, info["L"], info["U"], info["nu"])
    se = torch.sqrt((ue * ue).sum(-1))
    linf = abs(float(speed.max()) / exact_max - 1.0)
    l1 = float((speed - se).abs().mean() / se.mean())
    return linf, l1


def run_tg(nx, dtype, device, t_end, compile, overrides=()):
    _, cfg = load_case(CASE, [f"scene.nx={nx}", *overrides])
    t0 = time.perf_counter()
    scene, sim = make_simulation(cfg, dtype=dtype, device=device, compile=compile)
    if compile:  # compile outside the timed loop: two throw-away steps on a copy (the
        _, warm = make_simulation(cfg, dtype=dtype, device=device, compile=True)  # compiled
        run_steps(warm, steps=2)  # code is cached on the functions and reused by ``sim``)
    if device == "cuda":
        torch.cuda.synchronize()
    setup = time.perf_counter() - t0
    t1 = time.perf_counter()
    run_steps(sim, t_end=t_end)
    if device == "cuda":
        torch.cuda.synchronize()
    wall = time.perf_counter() - t1
    linf, l1 = tg_errors(sim, scene.info, t_end)
    return dict(nx=nx, N=sim.state.n, steps=sim.step, wall=wall, setup=setup,
                pss=sim.state.n * sim.step / wall, linf=linf, l1=l1)


def run_conduction(nx, dtype, device, compile):
    """1-D transient conduction (cases/conduction_1d): L2 error / (T_face - T0) vs erfc."""
    from torchsph.core.analytic import conduction_1d_exact
    from torchsph.core.state import Phase

    _, cfg = load_case(CASE.parent / "conduction_1d", [f"scene.nx={nx}"])
    t0 = time.perf_counter()
    scene, sim = make_simulation(cfg, dtype=dtype, device=device, compile=compile)
    setup = time.perf_counter() - t0
    t1 = time.perf_counter()
    run_steps(sim, t_end=cfg["run"]["t_end_s"])
    if device == "cuda":
        torch.cuda.synchronize()
    wall = time.perf_counter() - t1
    s, i = sim.state, scene.info
    m = s.phase == Phase.SOLID
    Te = conduction_1d_exact(s.x[m, 0], sim.t, i["alpha"], i["T_face"], i["T0"])
    err = float(torch.sqrt(((s.T[m] - Te) ** 2).mean()) / (i["T_face"] - i["T0"]))
    return dict(nx=nx, N=s.n, steps=sim.step, wall=wall, setup=setup, pss=s.n * sim.step / wall, l2=err)


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--quick", action="store_true", help="nx = 50 rows only")
    ap.add_argument("--nx", type=int, nargs="*", default=None)
    ap.add_argument("--t-end", type=float, default=1.0)
    ap.add_argument("--no-compile", action="store_true", help="eager mode (no torch.compile)")
    ap.add_argument("--dtype", choices=("float64", "float32"), nargs="*", default=["float64", "float32"])
    ap.add_argument("--device", nargs="*", default=None)
    ap.add_argument("--set", dest="overrides", action="append", default=[])
    ap.add_argument("--conduction-only", action="store_true", help="only the conduction table")
    ap.add_argument("--deposition", action="store_true",
                    help="the deposition step against --ref (scripts/tools/bench_deposition.py)")
    ap.add_argument("--ref", default="b14e316", help="reference commit for --deposition")
    ap.add_argument("--steps", type=int, default=100, help="--deposition: timed steps on the preview state")
    ap.add_argument("--full-steps", type=int, default=50, help="--deposition: timed first steps of the full scene")
    ap.add_argument("--repeat", type=int, default=3,
                    help="--deposition: rounds on the preview state, the two codes taking turns (the median round is shown)")
    ap.add_argument("--states", nargs="*", default=["preview", "full", "developed"], choices=("preview", "full", "developed"))
    ap.add_argument("--t-developed", type=float, default=0.003,
                    help="--deposition: the full scene's developed state, run to this time by the reference (s)")
    ap.add_argument("--mpi", action="store_true", help="--deposition: one process against 2 ranks")
    ap.add_argument("--mpi-steps", type=int, default=200,
                    help="--mpi: timed steps (~566 a ms of process in the full scene: 5700 for its first 10 ms)")
    ap.add_argument("--developed", type=Path, default=None, help="--mpi: a checkpoint of the case to time from too")
    ap.add_argument("--case", type=Path, default=Path(__file__).resolve().parents[2] / "cases" / "perpendicular_350W")
    a = ap.parse_args(argv)
    if a.deposition and a.mpi:
        mpi_table(a)
        return
    if a.deposition:
        from bench_deposition import run

        run(a.ref, a.steps, a.full_steps, a.states, t_developed=a.t_developed, repeat=a.repeat)
        return
    nxs = a.nx or ([50] if a.quick else [50, 100, 200])
    devices = a.device or (["cpu", "cuda"] if torch.cuda.is_available() else ["cpu"])
    compile = not a.no_compile
    print(f"# torchsph Taylor-Green benchmark: t_end = {a.t_end}, torch {torch.__version__}, "
          f"{torch.get_num_threads()} threads, compile = {compile}")
    if not a.conduction_only:
        taylor_green_table(a, nxs, devices, compile)
    print("\n# 1-D transient conduction (cases/conduction_1d, 2-D prism), L2 error vs erfc at t = 0.3 s")
    print("| device | dtype | nx | N | steps | loop wall s | setup s | particle-steps/s | L2 / dT |")
    print("|---|---|---|---|---|---|---|---|---|")
    for device in devices:
        for dt in a.dtype:
            for nx in ([50] if a.quick else [25, 50, 100, 200]):
                r = run_conduction(nx, getattr(torch, dt), device, False)
                print(f"| {device} | {dt} | {r['nx']} | {r['N']} | {r['steps']} | {r['wall']:.2f} | "
                      f"{r['setup']:.2f} | {r['pss']:.3g} | {r['l2']:.5f} |", flush=True)


def mpi_table(a):
    """``--deposition --mpi``: scripts/tools/bench_mpi.py in three configurations per state."""
    import json
    import os
    import shutil
    import subprocess

    here = Path(__file__).resolve().parent
    mpiexec = shutil.which("mpiexec", path=str(Path(sys.executable).parent)) or shutil.which("mpiexec")
    sets = [x for s in a.overrides for x in ("--set", s)]
    states = [("first steps", [])] + ([(f"from {a.developed}", ["--restart", str(a.developed)])] if a.developed else [])
    print(f"# {a.case.name}: {a.mpi_steps} timed steps after 5 of warm-up; wall ms per step (the slowest rank)")
    print("| state | run | ms/step | speed-up | particles | owned per rank | ghosts per rank | halo mm | "
          "MB sent per step per rank | imbalance |")
    print("|---|---|---|---|---|---|---|---|---|---|")
    for state, extra in states:
        base = None
        for name, ranks, threads in (("1 process, 1 thread", 1, 1), ("1 process, 2 threads", 1, 2),
                                     ("2 ranks, 1 thread each", 2, 1)):
            cmd = ([mpiexec, "-n", str(ranks)] if ranks > 1 else []) + [
                sys.executable, str(here / "bench_mpi.py"), str(a.case), "--steps", str(a.mpi_steps)] + extra + sets
            env = {**os.environ, "OMP_NUM_THREADS": str(threads)}  # (torch takes its threads from it)
            r = subprocess.run(cmd, env=env, capture_output=True, text=True)
            if r.returncode != 0:
                print(f"| {state} | {name} | failed: {r.stderr.strip().splitlines()[-1] if r.stderr.strip() else r.returncode} "
                      "| | | | | | | |", flush=True)
                continue
            d = json.loads(r.stdout.strip().splitlines()[-1])
            base = d["ms_per_step"] if base is None else base
            pr = d["per_rank"]
            owned = ", ".join(str(p["owned"]) for p in pr)
            ghosts = ", ".join(str(p["ghosts"]) for p in pr)
            sent = ", ".join(f"{p['sent_bytes_per_step'] / 1e6:.2f}" for p in pr)
            print(f"| {state} | {name} | {d['ms_per_step']:.1f} | {base / d['ms_per_step']:.2f} | {d['particles']} | "
                  f"{owned} | {ghosts} | {1e3 * d['halo_m']:.2f} | {sent} | {d['imbalance']:.2f} |", flush=True)


def taylor_green_table(a, nxs, devices, compile):
    print("| device | dtype | nx | N | steps | loop wall s | setup s | particle-steps/s | linf | L1 |")
    print("|---|---|---|---|---|---|---|---|---|---|")
    for device in devices:
        for dt in a.dtype:
            for nx in nxs:
                r = run_tg(nx, getattr(torch, dt), device, a.t_end, compile, a.overrides)
                print(f"| {device} | {dt} | {r['nx']} | {r['N']} | {r['steps']} | {r['wall']:.1f} | "
                      f"{r['setup']:.1f} | {r['pss']:.3g} | {r['linf']:.4f} | {r['l1']:.4f} |", flush=True)


if __name__ == "__main__":
    main()
