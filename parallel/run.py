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
from mpi4py import MPI

from torchsph.core.state import ParticleState
from torchsph.io.checkpoint import FORMAT as ckpt_format
from torchsph.io.checkpoint import CheckpointError, check_case, fresh_caches, read, recorded_physics, write
from torchsph.run.build import make_simulation
from torchsph.run.runner import SerialRun, run_case
from torchsph.step.particles import field_values, particle_arrays

from .setup import install_abort_hook, make_comm

FORMAT = "global-1"
GLOBAL_SUMS = ("energy", "heat", "E0")  # per-rank partial sums: a checkpoint holds their totals


def _state_from(arrays: dict) -> ParticleState:
    return ParticleState(**{k[6:]: torch.as_tensor(v) for k, v in arrays.items() if k.startswith("state.")})


def save_global(sim, comm, path: Path, chash: str, extra: dict, phys: dict | None = None):
    """Gather everything by particle id on rank 0 and write it atomically there."""
    arrays = comm.gather_owned(sim)
    ek, hk = (comm.union_keys(sim.energy), comm.union_keys(sim.heat_totals)) if sim.thermal is not None else ([], [])
    sums = comm.sum([float(sim.energy.get(k, 0.0)) for k in ek] + [float(sim.heat_totals.get(k, 0.0)) for k in hk]
                    + [float(sim.E0)]) if sim.thermal is not None else []
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
    d = {"format": FORMAT, "config_hash": chash, "physics": phys, "t": sim.t, "step": sim.step,
         "arrays": {k: torch.as_tensor(v) for k, v in arrays.items()},
         "energy": dict(zip(ek, sums[:len(ek)])), "heat": dict(zip(hk, sums[len(ek):len(ek) + len(hk)])),
         "E0": sums[-1] if sums else None,
         "n_builds": sim.nl.n_builds, "rng": torch.get_rng_state(), "extra": extra, "written": time.time(),
         "body_velocity": sim.body_velocity.cpu(), "stale": sim.stale,
         "active_age": sim.active_set.age if sim.active_set is not None else 0,
         "feeder": feeder, "escape": escape}
    write(d, path)


def global_from_single(d: dict, cfg: dict, path: str, recorded: dict | None = None, branch: bool = False) -> dict:
    """A one-process checkpoint as a global one: restored into a one-process simulation of
    the same case (every rank alike), its per-particle arrays and totals taken from there.
    A run started in one process continues on any number of ranks."""
    from torchsph.io import checkpoint as ckpt

    _, one = make_simulation(cfg)
    extra = ckpt.restore(one, d, cfg, path, recorded, branch)
    for name, obj in (("feeder", one.feeder), ("escape", one.escape)):
        if obj is not None and name in extra:
            obj.load_state_dict(extra[name])
    g = {"format": FORMAT, "config_hash": d.get("config_hash"), "physics": d.get("physics"),
         "t": one.t, "step": one.step, "arrays": {k: v.cpu() for k, v in one.particle_arrays().items()},
         "energy": {k: float(v) for k, v in one.energy.items()},
         "heat": {k: float(v) for k, v in getattr(one, "heat_totals", {}).items()},
         "E0": float(one.E0) if getattr(one, "E0", None) is not None else None,
         "n_builds": one.nl.n_builds, "rng": d["rng"], "body_velocity": one.body_velocity.cpu(),
         "stale": one.stale, "active_age": one.active_set.age if one.active_set is not None else 0,
         "feeder": one.feeder.state_dict() if one.feeder is not None else None,
         "escape": one.escape.state_dict() if one.escape is not None else None,
         "extra": {k: v for k, v in extra.items() if k not in ("feeder", "escape", "step_control_changes")}}
    del one
    return g


def restore_global(sim, comm, d: dict, cfg: dict, path: str, recorded: dict | None = None, branch: bool = False):
    if d.get("format") == ckpt_format:  # written by one process
        d = global_from_single(d, cfg, path, recorded, branch)
    if d.get("format") != FORMAT:
        raise CheckpointError(f"--restart {path}: not a torchsph checkpoint (format {d.get('format')!r})")
    changes = check_case(d, cfg, path, recorded, branch)
    dev, dt = sim.state.device, sim.state.dtype
    comm.bounds = None  # equal shares of the checkpoint's particles on this run's ranks
    local = comm.distribute(fresh_caches(sim, dict(d["arrays"]), branch, changes), first=True)
    local = {k: v.to(dev) for k, v in local.items()}
    sim.rearm(local, table=lambda: comm.table_at_reference(sim))  # the table as the last rebuild made it
    comm.mark(sim)
    sim.nl.n_builds = d["n_builds"]
    if "body_velocity" in d:
        bv = d["body_velocity"].to(device=dev, dtype=dt)
        if bv.shape[0] < sim.body_velocity.shape[0]:  # (written before every rank held every body's row)
            bv = torch.cat([bv, sim.body_velocity[bv.shape[0]:]])
        sim.body_velocity = bv
        sim.stale = d["stale"]
        if sim.active_set is not None:
            sim.active_set.age = d.get("active_age", 0)
    if sim.feeder is not None and d.get("feeder") is not None:
        sim.feeder.load_state_dict(d["feeder"])
        if comm.rank != 0:  # the totals stay on rank 0; each rank counts its own from here
            sim.feeder.welded_kg, sim.feeder.n_welded = 0.0, 0
    if sim.escape is not None and d.get("escape") is not None:
        sim.escape.load_state_dict(d["escape"] if comm.rank == 0 else {})
    sim.t, sim.step = d["t"], d["step"]
    first = comm.rank == 0  # the totals go to rank 0, the others hold zero: the sums are kept
    if sim.thermal is not None:
        z = torch.zeros((), dtype=dt)
        sim.energy = {k: torch.tensor(v, dtype=dt) if first else z for k, v in d["energy"].items()}
        sim.heat_totals = {k: torch.tensor(v, dtype=dt) if first else z for k, v in d["heat"].items()}
        sim.E0 = d["E0"] if first else 0.0
    torch.set_rng_state(d["rng"])
    sim.info = sim.measure()
    return {**d.get("extra", {}), "step_control_changes": changes}


class SlabRun(SerialRun):
    """The run loop's processes over MPI ranks (:func:`torchsph.run.runner.run_case` with
    ``procs=SlabRun(...)``): rank 0 writes, every rank takes part in the collectives."""

    def __init__(self, cfg: dict):
        self.comm = make_comm(cfg)
        self.ranks = self.comm.size
        self.root = self.comm.rank == 0

    def make(self, cfg):
        if self.root and self.ranks > 1 and cfg["numerics"].get("conduction_window", 0.0) > 0:
            print("torchsph: numerics.conduction_window is one process's: the ranks sum every conducting row at "
                  "every step (the same physics within the window's error, without its saving)", file=sys.stderr)
        return make_simulation(cfg, comm=self.comm)

    def recorded(self, restart):
        return self.comm.c.bcast(recorded_physics(restart) if self.root and restart is not None else None, root=0)

    def restore(self, sim, path, cfg, recorded, branch=False) -> dict:
        return restore_global(sim, self.comm, read(path), cfg, str(path), recorded, branch)

    def save(self, sim, path, chash, extra, phys):
        save_global(sim, self.comm, path, chash, extra, phys=phys)

    def state(self, sim, fields: dict | None = None):
        """Rank 0: the owned particles of all ranks (and ``fields``' arrays, NaN where a rank
        does not hold one at this moment), in particle-id order; (None, None) elsewhere."""
        n = self.comm.n_owned
        mine = {k: v[:n].cpu().numpy() for k, v in particle_arrays(sim).items() if k.startswith("state.")}
        mine.update({f"field.{k}": v[:n].cpu().numpy() for k, v in field_values(sim, fields or {}).items()})
        got = self.comm.c.gather(mine, root=0)
        if not self.root:
            return None, None
        g = {k: np.concatenate([r[k] for r in got]) for k in mine}
        order = np.argsort(g["state.id"], kind="stable")
        g = {k: v[order] for k, v in g.items()}
        return _state_from(g), {k[6:]: torch.as_tensor(v) for k, v in g.items() if k.startswith("field.")}

    def deposit_counts(self, sim):
        welded = self.comm.sum([sim.feeder.welded_kg])[0] if sim.feeder is not None else None
        escaped = self.comm.sum([sim.escape.kg])[0] if sim.escape is not None else None
        return welded, escaped

    def counts(self, sim) -> tuple[int, int]:
        n, a = self.comm.sum([self.comm.n_owned, sim.plan.n_active])
        return int(n), int(a)

    def any(self, flag: bool) -> bool:
        return self.comm.any(flag)

    def bcast(self, value):
        return self.comm.c.bcast(value, root=0)

    def summary(self, sim) -> dict:
        comm = self.comm
        fluid = int((sim.fluid_mask[: comm.n_owned]).sum())
        n_fluid, n_pairs = (int(v) for v in comm.sum([fluid, int(sim.nl.table.mask[sim.nl.table.rows < comm.n_owned].sum())]))
        peak = comm.c.allreduce(float(sim.state.T_peak[: comm.n_owned].max()) if sim.thermal is not None
                                and comm.n_owned else -math.inf, op=MPI.MAX)
        escaped = None
        if sim.escape is not None:
            n_esc, kg_esc = comm.sum([sim.escape.n, sim.escape.kg])
            escaped = {"n": int(n_esc), "kg": kg_esc}
        imb = comm.imbalance
        k = max(comm.rebalance_every, 1)
        return {"n_fluid": n_fluid, "n_pairs": n_pairs,
                "peak_temperature_K": peak if sim.thermal is not None else None, "escaped": escaped,
                "migrations": comm.n_migrations, "slab_bounds_m": [float(b) for b in comm.bounds[1:-1]],
                "load_imbalance": {"first_migrations": float(np.mean(imb[:k])) if imb else None,
                                   "last": float(np.mean(imb[-k:])) if imb else None,
                                   "rebalance_every": comm.rebalance_every, "history": [float(v) for v in imb]}}


def run_case_mpi(cfg: dict, case_path: Path, out_dir: Path, device=None, **kw) -> dict | None:
    """:func:`torchsph.run.runner.run_case` on the ranks of MPI.COMM_WORLD; rank 0 returns the
    summary, the others None. GPU: each rank takes ``cuda:(rank % device_count)``."""
    install_abort_hook()
    run = cfg["run"]
    if device is not None:
        run["device"] = device
    procs = SlabRun(cfg)
    if run["device"] == "cuda":
        if not torch.cuda.is_available():
            from torchsph.io.config import CaseError
            raise CaseError("[run] device = \"cuda\": no CUDA device is available here (use cpu)")
        run["device"] = f"cuda:{procs.comm.rank % torch.cuda.device_count()}"
    fail_rank = int(os.environ.get("TORCHSPH_TEST_RAISE_RANK", "-1"))  # tests: one rank raises
    if fail_rank == procs.comm.rank:  # the interrupt check runs once a step: fail at the third
        calls, any_ = [0], procs.any

        def failing_any(flag):
            calls[0] += 1
            if calls[0] >= 3:
                raise RuntimeError(f"test failure injected on rank {procs.comm.rank} at step {calls[0]}")
            return any_(flag)
        procs.any = failing_any
    return run_case(cfg, case_path, out_dir, procs=procs, **kw)
