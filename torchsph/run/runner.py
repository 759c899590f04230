"""Build a simulation from a validated case and run it with output and progress."""
from __future__ import annotations

import math
import sys
import time
from pathlib import Path

import torch

from torchsph.io import snapshots as sio
from torchsph.run.build import make_simulation, physics_plan, resume
from torchsph.run.progress import Progress, projection_lines
from torchsph.step import particles
from torchsph.step.loop import RunStats, expected_dt, run_steps
from torchsph.step.simulation import Simulation


def snapshot_due(sim: Simulation, every_steps: int | None, next_out: list, interval: float) -> bool:
    """Whether a snapshot is due after this step: every ``every_steps`` steps, or once the
    time passes ``next_out[0]`` (which then advances by ``interval``)."""
    if every_steps is not None:
        return sim.step % every_steps == 0
    if sim.t >= next_out[0] * (1 - 1e-9):
        next_out[0] += interval
        return True
    return False


def run_interruptible(sim: Simulation, flag: list, bar, **kw):
    """:func:`run_steps` with SIGINT only setting ``flag[0]`` (the callback finishes the step,
    checkpoints and stops); the old handler is restored and the progress bar closed."""
    import signal

    def on_sigint(signum, frame):
        flag[0] = True

    old = signal.signal(signal.SIGINT, on_sigint)
    try:
        run_steps(sim, **kw)
    finally:
        signal.signal(signal.SIGINT, old)
        bar.close()


def peak_rss_gb() -> float | None:
    try:
        import resource
        return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0**2  # KiB on Linux
    except (ImportError, OSError):
        return None


class SerialRun:
    """What the run loop needs of its processes, for one process (``parallel.run.SlabRun``
    is the MPI one): build, restore, checkpoint, the whole state for output, counts."""

    ranks = 1
    root = True

    def make(self, cfg):
        return make_simulation(cfg)

    def recorded(self, restart):
        from torchsph.io import checkpoint as ckpt
        return ckpt.recorded_physics(restart) if restart is not None else None

    def restore(self, sim, path, cfg, recorded, branch=False) -> dict:
        return resume(sim, path, cfg, recorded, branch)

    def save(self, sim, path, chash, extra, phys):
        from torchsph.io import checkpoint as ckpt
        extra = {**extra, **({"feeder": sim.feeder.state_dict()} if sim.feeder else {}),
                 **({"escape": sim.escape.state_dict()} if sim.escape else {})}
        ckpt.save(sim, path, chash, phys=phys, extra=extra)

    def state(self, sim, fields: dict | None = None):
        """(the whole state, ``fields``' arrays in its row order: :func:`torchsph.step.particles.output_fields`),
        in any row order (on the root; (None, None) elsewhere)."""
        return sim.state, particles.field_values(sim, fields or {})

    def deposit_counts(self, sim):
        """(welded kg, escaped kg) over processes, or (None, None): the feeder's own."""
        return None, None

    def counts(self, sim) -> tuple[int, int]:
        """(all particles, integrated particles) over processes."""
        return sim.state.n, sim.plan.n_active

    def any(self, flag: bool) -> bool:
        return flag

    def bcast(self, value):
        return value

    def summary(self, sim) -> dict:
        return {"n_fluid": sim.n_fluid, "n_pairs": sim.nl.table.n_pairs(),
                "neighbour_partial_builds": sim.nl.n_partial,
                "active_fraction": sim.plan.report(),
                "active_set_refreshes": sim.active_set.n_refresh if sim.active_set is not None else None,
                "peak_temperature_K": float(sim.state.T_peak.max()) if sim.thermal is not None else None,
                "escaped": sim.escape.state_dict() if sim.escape is not None else None}


STEP_MODE = torch.inference_mode  # a run steps without autograd: each operation ~1 us cheaper (preview: 10-15 %)


@STEP_MODE()
def run_case(cfg: dict, case_path: Path, out_dir: Path, t_end=None, steps=None, device=None,
             dtype=None, progress=True, checkpoint_every: int | None = None,
             restart: Path | None = None, procs=None, estimate: bool = False,
             announce: bool = True, threads: str | None = None, branch: bool = False) -> dict | None:
    """Run a case with snapshots every output interval; returns the summary dict (on the
    root process; None on the others).

    ``procs``: the processes (:class:`SerialRun`, or ``parallel.run.SlabRun`` under MPI);
    the loop is the same. Before stepping, the cost is printed (particles, memory, steps
    to the end, snapshot disk) and, after a short probe of the run's own first steps, the
    projected wall time (``announce=False``: neither, e.g. where an ``estimate`` call has
    said it already); ``estimate`` probes at the step of the regime the run will spend its
    steps in, prints the projection and stops there (nothing written). Checkpoints
    (``out_dir/checkpoint.pt``, atomic) are written every ``checkpoint_every`` steps, at the
    end, and when the run is interrupted (SIGINT/Ctrl-C: the step in progress is finished,
    the checkpoint and ``summary.json`` written, then KeyboardInterrupt raised). The run is made
    in ``torch.inference_mode`` (its tensors are inference tensors: a caller that changes them in
    place afterwards does so in that mode too).
    ``restart`` continues from a checkpoint of the same case; ``steps`` then counts the
    steps still to run, ``t_end`` stays the end time; the bar and the wall time go on
    from the checkpoint's. ``branch``: ``restart`` is a checkpoint of the same scene run with
    other physics (a what-if from a developed state: the changed keys are printed and go to
    ``summary.json``)."""
    from torchsph.io import checkpoint as ckpt

    procs = procs if procs is not None else SerialRun()
    root = procs.root
    run = cfg["run"]
    if device is not None:
        run["device"] = device
    if dtype is not None:
        run["dtype"] = dtype
    if t_end is None and steps is None:
        t_end, steps = run["t_end_s"], run["steps"]
    if run["device"] == "cuda" and not torch.cuda.is_available():
        from torchsph.io.config import CaseError
        raise CaseError("[run] device = \"cuda\": no CUDA device is available here (use cpu)")
    recorded = procs.recorded(restart)  # read before config.json is overwritten
    if root and not estimate:
        out_dir.mkdir(parents=True, exist_ok=True)
        if restart is None:  # a restart writes it once the checkpoint is accepted
            sio.write_json(out_dir / "config.json", {"case": str(case_path), **cfg})
    t_setup = time.perf_counter()
    scene, sim = procs.make(cfg)
    setup_s = time.perf_counter() - t_setup
    interval = run["output_interval_s"]
    if interval is None:
        interval = (t_end / 10.0) if t_end is not None else math.inf
    every_steps = max(steps // 10, 1) if (steps is not None and run["output_interval_s"] is None) else None
    snaps: list[tuple[float, str, int]] = []
    fdt = sim.state.x.detach().cpu().numpy().dtype
    chash = ckpt.config_hash(cfg)
    ck_path = out_dir / "checkpoint.pt"
    resumed = {}
    if restart is not None:
        resumed = procs.restore(sim, restart, cfg, recorded, branch)
        changes = resumed["step_control_changes"]  # (a branch's: every physics change)
        if branch:
            resumed["branch"] = {"from": str(restart), "changes": resumed.pop("step_control_changes")}
        if root and not estimate:
            sio.write_json(out_dir / "config.json", {"case": str(case_path), **cfg})
            for c in changes:
                print(f"torchsph: {'branch' if branch else 'restart'} from {restart}: {c}", file=sys.stderr,
                      flush=True)
        snaps = [tuple(x) for x in resumed.get("snaps", [])]
    deposit = list(resumed.get("deposit", []))  # deposition measures at each snapshot
    wall_before = float(resumed.get("wall_s", 0.0))  # the earlier legs' wall time

    fields = particles.output_fields(sim, run.get("fields", []))  # ([run] fields: refused here if unknown)
    # dataset -> (shape after the particle axis, dtype) of every snapshot written, earlier legs' too
    layout = {k: (tuple(v[0]), v[1]) for k, v in resumed.get("layout", {}).items()}

    def snapshot():
        welded, escaped = procs.deposit_counts(sim)
        st, extra = procs.state(sim, fields)
        if not root:
            return
        if "feeder" in scene.info:
            from torchsph.scenes.deposition import measure
            sc = cfg["scene"]
            deposit.append(measure(st, scene.info, sim.t, sc["substrate_velocity_m_s"][0], sc["wire_feed_m_s"],
                                   cfg["fluid"]["rho0_kg_m3"], cfg["thermal"]["liquidus_K"], scene.dx,
                                   welded_kg=welded, escaped_kg=escaped))
            sio.write_json(out_dir / "deposit.json", deposit)
        name = f"snap_{len(snaps):05d}.h5"
        layout.update(sio.write_snapshot(out_dir / name, st, sim.t, sim.step, extra))
        snaps.append((sim.t, name, st.n, tuple(extra)))
        sio.write_xdmf(out_dir / "particles.xdmf", snaps, fdt, layout)

    next_out = [resumed.get("next_out", interval)]
    if restart is None and not estimate:
        snapshot()
    # the cost, before stepping
    n_all, n_act = procs.counts(sim)
    dt_exp, dt_why = expected_dt(sim)
    if steps is not None:
        steps_left = float(steps)
    else:
        steps_left = max(t_end - sim.t, 0.0) / dt_exp
    n_snap = (int(steps_left // every_steps) if every_steps else
              int(max((t_end or sim.t) - sim.t, 0.0) / interval) if math.isfinite(interval) else 0) + 1
    snap_bytes = n_all * sum(a.nbytes for a in sio.snapshot_arrays(
        sim.state, particles.field_values(sim, fields)).values()) / max(sim.state.n, 1)
    cost = dict(n_all=n_all, n_active=n_act, rss_gb=peak_rss_gb(), ranks=procs.ranks, steps_left=steps_left,
                dt_s=dt_exp, dt_why=dt_why, snapshots=n_snap, snapshot_bytes=snap_bytes, threads=threads,
                disk_free=sio.free_bytes(out_dir))
    if root and announce and (progress or estimate):
        for line in projection_lines(**cost, probe=None):
            print(line, file=sys.stderr, flush=True)

    stats = RunStats()
    interrupted = [False]

    def write_checkpoint():
        procs.save(sim, ck_path, chash, {"snaps": snaps, "next_out": next_out[0], "deposit": deposit, "layout": layout,
                                         "wall_s": wall_before + time.perf_counter() - t0}, ckpt.physics(cfg))

    by_steps = steps is not None
    bar = Progress(total=steps if by_steps else t_end, start=0 if by_steps else sim.t, by_steps=by_steps,
                   enabled=progress and root and not estimate)
    step0 = sim.step
    # the probe: steps 2.. of the run (the first one warms up), up to PROBE_STEPS or PROBE_WALL s
    probe = {"t1": None, "shown": estimate or not announce}
    PROBE_STEPS, PROBE_WALL = (40, 30.0) if estimate else (20, 15.0)
    if estimate and sim.dt_fixed is None and dt_exp < sim.choose_dt()[0]:
        # the run will step at the melt's limit: the probe (thrown away) takes that step
        sim.dt_fixed = dt_exp

    def probe_done(done: int):
        if done == 1:
            probe["t1"] = time.perf_counter()
            return None
        k, wall = done - 1, time.perf_counter() - probe["t1"]
        return (k, wall) if (k >= PROBE_STEPS or wall >= PROBE_WALL) else None

    def callback(sim, info):
        done = sim.step - step0
        counts = procs.counts(sim) if done % 20 == 0 or done == 1 else None
        if counts is not None:
            callback.counts = counts
        bar.update(done if by_steps else sim.t, *callback.counts, text=(
            f"step {sim.step} t={sim.t:.4g}s dt={info.dt:.3g}({info.limit}) N={callback.counts[0]}"),
            refresh_text=counts is not None)
        # while the probe runs, rank 0's clock decides for every process (one broadcast a step)
        measured = procs.bcast(probe_done(done)) if (estimate or not probe["shown"]) else None
        if measured is not None and not probe["shown"]:
            probe["shown"] = True
            if root and progress:
                bar.bar.clear()
                for line in projection_lines(**cost, probe=measured)[2:]:
                    print(line, file=sys.stderr, flush=True)
        if estimate:
            if measured is not None:
                raise _ProbeDone(*measured)
            return
        if snapshot_due(sim, every_steps, next_out, interval):
            snapshot()
        if checkpoint_every and sim.step % checkpoint_every == 0:
            write_checkpoint()
        if procs.any(interrupted[0]):
            write_checkpoint()
            raise KeyboardInterrupt(f"interrupted at step {sim.step}; checkpoint {ck_path}")

    callback.counts = (n_all, n_act)
    t0 = time.perf_counter()
    try:
        run_interruptible(sim, interrupted, bar, t_end=t_end, steps=steps, callback=callback, stats=stats)
        if estimate:  # the run was shorter than the probe: what it took is the measure
            done = sim.step - step0
            raise _ProbeDone(max(done - 1, 1), time.perf_counter() - (probe["t1"] or t0))
    except _ProbeDone as e:
        if root:
            for line in projection_lines(**cost, probe=(e.steps, e.wall))[2:]:
                print(line, file=sys.stderr, flush=True)
        return {"estimate": cost, "probe_steps": e.steps, "probe_wall_s": e.wall,
                "projected_wall_s": e.wall / e.steps * steps_left} if root else None
    except KeyboardInterrupt:
        if estimate:
            raise
        _finish(procs, sim, cfg, case_path, out_dir, stats, snaps, setup_s, t0, wall_before, bar, step0,
                restart, resumed, interrupted=True)
        raise
    write_checkpoint()
    if procs.bcast(bool(snaps and snaps[-1][0] != sim.t) if root else None):
        snapshot()  # collective under MPI: every process gathers
    return _finish(procs, sim, cfg, case_path, out_dir, stats, snaps, setup_s, t0, wall_before, bar, step0,
                   restart, resumed, interrupted=False)


class _ProbeDone(Exception):
    """``--estimate``: the probe steps are done."""

    def __init__(self, steps: int, wall: float):
        super().__init__(f"probe of {steps} steps done")
        self.steps, self.wall = steps, wall


def _finish(procs, sim, cfg, case_path, out_dir, stats, snaps, setup_s, t0, wall_before, bar, step0,
            restart, resumed, interrupted: bool) -> dict | None:
    """summary.json (at the end and on SIGINT): every process takes part in its sums."""
    wall = time.perf_counter() - t0
    energy = sim.energy_balance()
    extra = procs.summary(sim)
    n_all, _ = procs.counts(sim)
    if not procs.root:
        return None
    binding = stats.limits.most_common(1)[0][0] if stats.limits else sim.choose_dt()[1]
    if binding == "fixed":
        binding = f"fixed ({sim.binding_limit()[0]} limit binds)"
    fm = sim.fluid_model
    summary = {
        "case": str(case_path), "ranks": procs.ranks, "n_particles": n_all, "steps": sim.step,
        "steps_last_leg": sim.step - step0, "t_final_s": sim.t, "interrupted": interrupted,
        "wall_s": wall_before + wall, "wall_last_leg_s": wall, "setup_s": setup_s,
        "particle_steps_per_s": bar.psteps_all / wall if wall > 0 else None,
        "active_particle_steps_per_s": bar.psteps_active / wall if wall > 0 else None,
        "device": str(sim.state.device), "dtype": str(sim.state.dtype).replace("torch.", ""),
        "dt_binding_limit": binding, "dt_limit_counts": dict(stats.limits),
        "dt_min_s": stats.dt_min if stats.dt_min < math.inf else None, "dt_max_s": stats.dt_max,
        "c0_m_s": fm.prm.c0 if fm is not None else None,
        "mach_max": stats.vmax / fm.prm.c0 if fm is not None and (sim.n_fluid > 0 or stats.vmax > 0) else None,
        "neighbour_builds": sim.nl.n_builds, "energy": energy, "physics_plan": physics_plan(sim),
        "snapshots": len(snaps), "torch": torch.__version__, **extra,
    }
    if "branch" in resumed:
        summary["branch"] = resumed["branch"]
    elif restart is not None:
        summary["restart_step_control_changes"] = resumed.get("step_control_changes", [])
    sio.write_json(out_dir / "summary.json", summary)
    return summary
