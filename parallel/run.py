"""``mpirun -n K python -m torchsph CASE``: the run loop over MPI ranks.

Same CLI, outputs and checkpoints as one process: rank 0 writes one HDF5 file per snapshot
(the owned particles of all ranks gathered in id order) and one XDMF, ``summary.json`` with
the load imbalance (max / mean over ranks of the work: step time less communication) before and after cost-weighted balancing,
and one progress bar. Checkpoints are global (every per-particle array gathered by id,
plus the clock, energy totals and RNG): a run restarts from one on any number of ranks,
the neighbour tables rebuilt at the positions of the last rebuild (so the continued run
rebuilds at the same steps). GPU: each rank takes ``cuda:(rank % device_count)``.
"""
from __future__ import annotations

import math
import os
import sys
import time
from pathlib import Path

import numpy as np
import torch

from torchsph import io as sio
from torchsph.checkpoint import CheckpointError, check_case, config_hash, physics, recorded_physics
from torchsph.runner import RunStats, make_simulation, physics_plan, run_interruptible, snapshot_due
from torchsph.state import ParticleState

from .slab import install_abort_hook, make_comm

FORMAT = "global-1"
GLOBAL_SUMS = ("energy", "heat", "E0")  # per-rank partial sums: a checkpoint holds their totals


def _state_from(arrays: dict) -> ParticleState:
    return ParticleState(**{k[6:]: torch.as_tensor(v) for k, v in arrays.items() if k.startswith("state.")})


def save_global(sim, comm, path: Path, chash: str, extra: dict, phys: dict | None = None):
    """Gather everything by particle id on rank 0 and write it atomically there."""
    arrays = comm.gather_owned(sim)
    sums = comm.sum([float(v) for v in sim.energy.values()] + [float(v) for v in sim._heat.values()]
                    + [float(sim._E0)]) if sim.thermal is not None else []
    feeder = None
    if sim.feeder is not None:  # the contact counts are each rank's own: the checkpoint holds the totals
        feeder = sim.feeder.state_dict()
        feeder["welded_kg"], feeder["n_welded"] = comm.sum([sim.feeder.welded_kg, sim.feeder.n_welded])
        feeder["n_welded"] = int(feeder["n_welded"])
    escape = None
    if sim.escape is not None:  # each rank books what it owned: the checkpoint holds the totals
        n, kg = comm.sum([sim.escape.n, sim.escape.kg])
        escape = {"n": int(n), "kg": kg}
    if comm.rank != 0:
        return
    ek, hk = list(sim.energy), list(sim._heat) if sim.thermal is not None else []
    d = {"format": FORMAT, "config_hash": chash, "physics": phys, "t": sim.t, "step": sim.step,
         "arrays": {k: torch.as_tensor(v) for k, v in arrays.items()},
         "energy": dict(zip(ek, sums[:len(ek)])), "heat": dict(zip(hk, sums[len(ek):len(ek) + len(hk)])),
         "E0": sums[-1] if sums else None, "t_cond": getattr(sim.thermal, "t_cond", None),
         "n_builds": sim.nl.n_builds, "rng": torch.get_rng_state(), "extra": extra, "written": time.time(),
         "body_velocity": sim.body_velocity.cpu(), "stale": sim._stale,
         "feeder": feeder, "escape": escape}
    tmp = path.with_name(path.name + ".tmp")
    with open(tmp, "wb") as f:
        torch.save(d, f)
        f.flush()
        os.fsync(f.fileno())
    os.replace(tmp, path)


def restore_global(sim, comm, d: dict, cfg: dict, path: str, recorded: dict | None = None):
    if d.get("format") != FORMAT:
        raise CheckpointError(f"--restart {path}: not a global (MPI) checkpoint; restart it without mpirun")
    changes = check_case(d, cfg, path, recorded)
    dev, dt = sim.state.device, sim.state.dtype
    comm.bounds = None  # equal shares of the checkpoint's particles on this run's ranks
    local = comm.distribute({k: v for k, v in d["arrays"].items()}, first=True)
    local = {k: v.to(dev) for k, v in local.items()}
    sim.set_particle_arrays(local)
    comm.table_at_reference(sim)  # the neighbour table as the last rebuild made it
    sim.nl.n_builds = d["n_builds"]
    if "body_velocity" in d:
        sim.body_velocity = d["body_velocity"].to(device=dev, dtype=dt)
        sim._stale = d["stale"]
    if sim.feeder is not None and d.get("feeder") is not None:
        sim.feeder.load_state_dict(d["feeder"])
        if comm.rank != 0:  # the totals stay on rank 0; each rank counts its own from here
            sim.feeder.welded_kg, sim.feeder.n_welded = 0.0, 0
    if sim.escape is not None and d.get("escape") is not None:
        sim.escape.load_state_dict(d["escape"] if comm.rank == 0 else {})
    sim.t, sim.step = d["t"], d["step"]
    caches = {k: v for k, v in local.items() if k.startswith(("th.", "sf."))}
    sim._select()
    sim.set_particle_arrays(caches)
    first = comm.rank == 0  # the totals go to rank 0, the others hold zero: the sums are kept
    if sim.thermal is not None:
        z = torch.zeros((), dtype=dt)
        sim.energy = {k: torch.tensor(v, dtype=dt) if first else z for k, v in d["energy"].items()}
        sim._heat = {k: torch.tensor(v, dtype=dt) if first else z for k, v in d["heat"].items()}
        sim._E0 = d["E0"] if first else 0.0
        sim.thermal.t_cond = d["t_cond"]
    if sim.fluid is not None:
        saved = sim.dvdt
        sim.fluid.momentum(sim.state, sim.state.v)
        sim.dvdt = saved
    torch.set_rng_state(d["rng"])
    sim.info = sim._measure()
    return {**d.get("extra", {}), "step_control_changes": changes}


def run_case_mpi(cfg: dict, case_path: Path, out_dir: Path, t_end=None, steps=None, device=None,
                 dtype=None, progress=True, checkpoint_every: int | None = None,
                 restart: Path | None = None) -> dict | None:
    """As :func:`torchsph.runner.run_case`, on the ranks of MPI.COMM_WORLD; rank 0 returns the
    summary, the others None."""
    from tqdm import tqdm

    install_abort_hook()
    run = cfg["run"]
    if dtype is not None:
        run["dtype"] = dtype
    if device is not None:
        run["device"] = device
    comm = make_comm(cfg)
    if run["device"] == "cuda":
        if not torch.cuda.is_available():
            from torchsph.config import CaseError
            raise CaseError("[run] device = \"cuda\": no CUDA device is available here (use cpu)")
        run["device"] = f"cuda:{comm.rank % torch.cuda.device_count()}"
    if t_end is None and steps is None:
        t_end, steps = run["t_end_s"], run["steps"]
    root = comm.rank == 0
    # the physics the checkpoint's run recorded, read before config.json is overwritten
    recorded = comm.c.bcast(recorded_physics(restart) if root and restart is not None else None, root=0)
    if root:
        out_dir.mkdir(parents=True, exist_ok=True)
        if restart is None:  # a restart writes it once the checkpoint is accepted
            sio.write_json(out_dir / "config.json", {"case": str(case_path), **cfg})
    t_setup = time.perf_counter()
    scene, sim = make_simulation(cfg, comm=comm)
    setup_s = time.perf_counter() - t_setup
    chash = config_hash(cfg)
    ck_path = out_dir / "checkpoint.pt"
    snaps: list = []
    deposit: list = []  # deposition measures at each snapshot (a deposition scene)
    interval = run["output_interval_s"] or ((t_end / 10.0) if t_end is not None else math.inf)
    every_steps = max(steps // 10, 1) if (steps is not None and run["output_interval_s"] is None) else None
    next_out = [interval]
    if restart is not None:
        try:
            d = torch.load(restart, map_location="cpu", weights_only=False)
        except Exception as e:  # noqa: BLE001
            raise CheckpointError(f"--restart {restart}: not a readable checkpoint ({e})") from None
        extra = restore_global(sim, comm, d, cfg, str(restart), recorded)
        if root:
            sio.write_json(out_dir / "config.json", {"case": str(case_path), **cfg})
            for c in extra["step_control_changes"]:
                print(f"torchsph: restart from {restart}: {c}", file=sys.stderr, flush=True)
        snaps = [tuple(s) for s in extra.get("snaps", [])]
        next_out = [extra.get("next_out", interval)]
        deposit[:] = extra.get("deposit", [])
    fdt = np.dtype(str(sim.state.dtype).replace("torch.", ""))

    def snapshot():
        g = comm.gather_owned(sim, [f"state.{f}" for f in ("x", "v", "rho", "m", "p", "T", "T_peak", "phase",
                                                              "id", "body")])
        welded = comm.sum([sim.feeder.welded_kg])[0] if sim.feeder is not None else None
        escaped = comm.sum([sim.escape.kg])[0] if sim.escape is not None else None
        if not root:
            return
        st = _state_from(g)
        if "feeder" in scene.info:
            from torchsph.deposition import measure
            sc = cfg["scene"]
            deposit.append(measure(st, scene.info, sim.t, sc["substrate_velocity_m_s"][0], sc["wire_feed_m_s"],
                                   cfg["fluid"]["rho0_kg_m3"], cfg["thermal"]["liquidus_K"], scene.dx,
                                   welded_kg=welded, escaped_kg=escaped))
            sio.write_json(out_dir / "deposit.json", deposit)
        name = f"snap_{len(snaps):05d}.h5"
        sio.write_snapshot(out_dir / name, st, sim.t, sim.step)
        snaps.append((sim.t, name, st.n))
        sio.write_xdmf(out_dir / "particles.xdmf", snaps, fdt)

    def write_checkpoint():
        save_global(sim, comm, ck_path, chash, {"snaps": snaps, "next_out": next_out[0], "deposit": deposit},
                    phys=physics(cfg))

    if restart is None:
        snapshot()
    imb_before = None
    stats = RunStats()
    interrupted = [False]
    n_total = int(comm.sum([comm.n_owned])[0])
    bar = tqdm(total=steps if steps is not None else t_end, disable=not (progress and root),
               unit="step" if steps is not None else "s", dynamic_ncols=True, mininterval=0.5)
    t0 = time.perf_counter()

    fail_rank = int(os.environ.get("TORCHSPH_TEST_RAISE_RANK", "-1"))  # tests: one rank raises

    def callback(sim, info):
        if comm.rank == fail_rank and sim.step >= 3:
            raise RuntimeError(f"test failure injected on rank {comm.rank} at step {sim.step}")
        bar.update(1 if steps is not None else info.dt)
        if root and sim.step % 20 == 0:
            el = time.perf_counter() - t0
            bar.set_postfix_str(f"step {sim.step} t={sim.t:.4g}s dt={info.dt:.3g}({info.limit}) N={n_total} "
                                f"ranks={comm.size} {n_total * stats_steps[0] / max(el, 1e-9):.3g} p-steps/s",
                                refresh=False)
        stats_steps[0] += 1
        if snapshot_due(sim, every_steps, next_out, interval):
            snapshot()
        if checkpoint_every and sim.step % checkpoint_every == 0:
            write_checkpoint()
        if comm.any(interrupted[0]):
            write_checkpoint()
            raise KeyboardInterrupt(f"interrupted at step {sim.step}; checkpoint {ck_path}")

    stats_steps = [0]
    run_interruptible(sim, interrupted, bar, t_end=t_end, steps=steps, callback=callback, stats=stats)
    write_checkpoint()
    wall = time.perf_counter() - t0
    if comm.c.bcast(bool(snaps and snaps[-1][0] != sim.t) if root else None, root=0):
        snapshot()  # collective: every rank gathers
    energy = sim.energy_balance()
    imb = comm.imbalance
    if imb:
        k = max(comm.rebalance_every, 1)
        imb_before = float(np.mean(imb[:k]))
    escaped = None
    if sim.escape is not None:
        n_esc, kg_esc = comm.sum([sim.escape.n, sim.escape.kg])
        escaped = {"n": int(n_esc), "kg": kg_esc}
    if not root:
        return None
    summary = {
        "case": str(case_path), "ranks": comm.size, "n_particles": n_total, "steps": sim.step,
        "t_final_s": sim.t, "wall_s": wall, "setup_s": setup_s,
        "particle_steps_per_s": n_total * stats_steps[0] / wall if wall > 0 else None,
        "device": str(sim.state.device), "dtype": str(sim.state.dtype).replace("torch.", ""),
        "dt_binding_limit": stats.limits.most_common(1)[0][0] if stats.limits else None,
        "dt_limit_counts": dict(stats.limits), "neighbour_builds": sim.nl.n_builds,
        "c0_m_s": sim.fluid_model.prm.c0 if sim.fluid_model is not None else None,
        "mach_max": (stats.vmax / sim.fluid_model.prm.c0) if sim.fluid_model is not None else None,
        "migrations": comm.n_migrations, "slab_bounds_m": [float(b) for b in comm.bounds[1:-1]],
        "load_imbalance": {"first_migrations": imb_before,
                           "last": float(np.mean(imb[-max(comm.rebalance_every, 1):])) if imb else None,
                           "rebalance_every": comm.rebalance_every, "history": [float(v) for v in imb]},
        "energy": energy, "physics_plan": physics_plan(sim), "snapshots": len(snaps), "torch": torch.__version__,
        "escaped": escaped,
    }
    if restart is not None:
        summary["restart_step_control_changes"] = extra["step_control_changes"]
    sio.write_json(out_dir / "summary.json", summary)
    return summary
