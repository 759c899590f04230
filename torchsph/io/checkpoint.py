"""Checkpoints: everything a run needs to continue exactly, written atomically.

A checkpoint holds every per-particle array of the registry (:mod:`torchsph.step.particles`:
the particle state, the rates carried between steps, the neighbour list's and the physics'
per-particle caches, under the registry's names), the clock (t, step), the energy bookkeeping, the neighbour list as it was (so that the
continued run rebuilds pairs at the same steps and sums in the same order: a float64
restart is bit-for-bit the uninterrupted run), the per-rebuild caches of the physics, the
torch RNG state, and a hash of the physics part of the case (scene, fluid, thermal,
beams, surface, numerics) that a restart must match. It is written to ``NAME.tmp`` and
renamed over ``NAME`` (atomic on POSIX), so a run killed while writing one leaves the
previous checkpoint intact.
"""
from __future__ import annotations

import hashlib
import io
import json
import os
import time
from pathlib import Path

import torch

from torchsph.core.neighbors import NeighbourTable
from torchsph.core.state import FIELDS
from torchsph.io.snapshots import written
from torchsph.physics.terms import available as available_terms
from torchsph.step.particles import declared, holders, lazy_caches, particle_arrays, set_particle_arrays

PHYSICS_SECTIONS = ("scene", "fluid", "thermal", "beam", "surface", "numerics")
FORMAT = 2  # 2: the per-particle arrays under the registry's names; 1 (read too): by owner


class CheckpointError(RuntimeError):
    """A checkpoint that cannot be used for this case (message: one line)."""


def physics_sections(cfg: dict) -> tuple[str, ...]:
    """The sections that define the physics: the core ones, and the composable terms' that
    the case (or the recorded physics) names."""
    return PHYSICS_SECTIONS + tuple(k for k in available_terms() if k in cfg)


def config_hash(cfg: dict) -> str:
    """Hash of the sections that define the physics (not [run]: a restart may change the end
    time, output interval or device)."""
    phys = physics(cfg)
    return hashlib.sha256(json.dumps(phys, sort_keys=True, default=str).encode()).hexdigest()[:16]


def physics(cfg: dict) -> dict:
    """The physics sections of a case as plain JSON data (what a checkpoint records); the
    beams are all the case's, its scene's derived ones included."""
    from torchsph.scenes.builders import case_beams

    phys = {k: cfg.get(k) for k in physics_sections(cfg)}
    phys["beam"] = case_beams(cfg) or cfg.get("beam")
    return json.loads(json.dumps(phys, sort_keys=True, default=str))


def _defaults(section: str, cfg: dict) -> dict:
    from torchsph.io import config as C
    from torchsph.scenes.builders import SCENES

    if section == "scene":
        spec = SCENES.get(cfg.get("scene", {}).get("type"))
        schema = spec.schema if spec is not None else {}
    else:
        schema = {"fluid": C.FLUID, "thermal": C.THERMAL, "surface": C.SURFACE, "numerics": C.NUMERICS,
                  **{k: term.schema for k, term in available_terms().items()}}.get(section, {})
    dflt = {k: key.default for k, key in schema.items() if key.default is not C.REQUIRED}
    if section == "numerics" and cfg.get("scene", {}).get("type") in SCENES:  # the scene's verified numerics
        dflt.update(SCENES[cfg["scene"]["type"]].numerics)
    return json.loads(json.dumps(dflt, default=str))


# Keys that say how the steps are taken, not what is simulated: a restart may change them
# (a run stopped by a blow-up goes on from its last checkpoint with a smaller CFL number).
# max_compression only says when a run is stopped as broken, not how it steps; partial_rebuild
# only how the same neighbour pairs are found.
STEP_CONTROL = ("numerics.cfl", "numerics.dt_s", "numerics.allow_unstable_dt", "numerics.compile",
                "numerics.rebalance_every", "numerics.max_compression", "numerics.partial_rebuild",
                "numerics.migration_slack_over_skin", "numerics.conduction_window", "numerics.conduction_window_below_K")


# Keys whose default changed after they were added: a checkpoint from before the key existed
# ran with the behaviour named here, not with today's default (so a restart of it under the
# new default is refused, naming the key, rather than continuing with other physics), where
# the key acts: (that value, whether it acts in the case's section).
ABSENT_MEANS = {"surface.band_curvature": (  # the default until stop 51; acts with the wetting model
    "beside", lambda sec: sec.get("contact_angle_deg") is not None and sec.get("wetting", True))}


def _changed(old: dict, cfg: dict) -> list[tuple[str, object, object]]:
    """(section.key, checkpoint's value, case's value) for each physics key that differs. A
    key the checkpoint lacks is not a difference when the case has it at its default (a key
    added by a newer version of the code that keeps the old behaviour by default), or at the
    value :data:`ABSENT_MEANS` names for it."""
    new, out = physics(cfg), []
    terms = sorted((set(physics_sections(old)) | set(physics_sections(new))) - set(PHYSICS_SECTIONS))
    for sec in PHYSICS_SECTIONS + tuple(terms):
        a, b = old.get(sec), new.get(sec)
        if isinstance(a, dict) and isinstance(b, dict):
            dflt = _defaults(sec, cfg)
            for k in sorted(set(a) | set(b)):
                legacy = ABSENT_MEANS.get(f"{sec}.{k}")
                if k not in a and legacy is not None and legacy[1](b):
                    a = {**a, k: legacy[0]}
                elif k not in a and k in dflt and dflt[k] == b[k]:
                    continue
                if a.get(k, "(absent)") != b.get(k, "(absent)"):
                    out.append((f"{sec}.{k}", a.get(k, "(absent)"), b.get(k, "(absent)")))
        elif a != b:
            out.append((f"[{sec}]", None, None))
    return out


def _say(key, a, b) -> str:
    return f"{key} differs" if a is None and b is None and key.startswith("[") else \
        f"{key} = {a} in the checkpoint, {b} now"


def differences(old: dict, cfg: dict) -> list[str]:
    """What differs between a checkpoint's recorded physics and a case, key by key."""
    return [_say(*c) for c in _changed(old, cfg)]


# What a branch (``--branch``: a checkpoint's state carried on with other physics) may not
# change: the keys that build the particle set, their kinematics, or the neighbour table's
# reach. The beams' keys of [scene] (source_*) may change.
BRANCH_FIXED = ("scene.type", "scene.dim", "scene.dx_m", "numerics.kernel", "numerics.h_over_dx",
                "numerics.skin_over_dx")


def _fixed_on_branch(key: str) -> bool:
    return key in BRANCH_FIXED or key.startswith("[scene") or (key.startswith("scene.")
                                                                and not key.startswith("scene.source_"))


def fresh_caches(sim, arrays: dict, branch: bool, changes: list) -> dict:
    """``arrays`` less the caches that follow from the physics (the registry's lazy ones) where
    a branch changed it: they are made again from the state, with the branch's physics."""
    if not (branch and changes):
        return arrays
    lazy = lazy_caches(sim)
    return {k: v for k, v in arrays.items() if k not in lazy}


def check_case(d: dict, cfg: dict, path: str, recorded: dict | None = None, branch: bool = False) -> list[str]:
    """Refuse a checkpoint written for other physics, naming what differs. ``recorded``: the
    physics of the run that wrote it, for checkpoints that do not carry their own (its
    ``config.json``); it is trusted only if it hashes to the checkpoint's hash. Changes of
    the :data:`STEP_CONTROL` keys are accepted; returns them (one line each). ``branch``: any
    physics key may change but those that build the scene (:data:`BRANCH_FIXED`, and [scene]
    but for its source_* keys); returns every change."""
    flag = "--branch" if branch else "--restart"
    allowed = ("a branch may change any physics key but [scene]'s (source_* excepted), "
               + ", ".join(k for k in BRANCH_FIXED if not k.startswith("scene.")) if branch else
               "only [run] and " + ", ".join(STEP_CONTROL) + " may change on a restart (--branch: other physics "
               "from this state)")
    if d.get("config_hash") == config_hash(cfg):
        return []
    old = d.get("physics") or recorded
    if old is not None and config_hash(old) == d.get("config_hash"):
        diff = _changed(old, cfg)
        bad = [_say(*c) for c in diff if (_fixed_on_branch(c[0]) if branch else c[0] not in STEP_CONTROL)]
        if bad:
            raise CheckpointError(f"{flag} {path}: written for a different case: " + "; ".join(bad[:6])
                                  + ("; ..." if len(bad) > 6 else "") + "; " + allowed)
        return [_say(*c) for c in diff]
    raise CheckpointError(f"{flag} {path}: written for a different case (physics hash "
                          f"{d.get('config_hash')} vs {config_hash(cfg)}, and no record of its physics to compare "
                          f"key by key); {allowed}")


def recorded_physics(restart: str | Path) -> dict | None:
    """The physics in the ``config.json`` next to a checkpoint (None if there is none)."""
    p = Path(restart).parent / "config.json"
    try:
        return physics(json.loads(p.read_text()))
    except (OSError, ValueError):
        return None


def _cpu(t):
    return t.detach().cpu() if isinstance(t, torch.Tensor) else t


def window_state(th, n: int) -> dict:
    """The conduction window's split as the run has it (per particle: the fast rows, the rows a
    step between windows integrates) and whether the next step integrates those only: a
    restart makes the same split and takes the same step."""
    op = th.op
    sp = op.split if op is not None else None
    out = {"partial_next": th.partial_next}
    if sp is not None:
        out["fast"] = _cpu(torch.zeros(n, dtype=torch.bool, device=op.rows.device).index_fill_(
            0, op.rows.index_select(0, torch.nonzero(sp.fast).squeeze(1)), True))
    if th.int_rows is not None and th.int_rows_for is th.rows:
        out["int_rows"] = _cpu(torch.zeros(n, dtype=torch.bool, device=th.rows.device).index_fill_(0, th.int_rows, True))
    return out


def restore_window(th, c: dict, to):
    """Put :func:`window_state` back (after the restore's selection)."""
    th.partial_next = bool(c.get("partial_next", False))
    th.restored_fast = to(c["fast"]) if c.get("fast") is not None else None
    if c.get("int_rows") is not None:
        keep = to(c["int_rows"])
        th.int_rows = th.rows.index_select(0, torch.nonzero(keep.index_select(0, th.rows)).squeeze(1))
        th.int_rows_for = th.rows
    else:
        th.partial_next = False


def stored_arrays(sim) -> dict:
    """The per-particle arrays a checkpoint stores: the registry's, those that belong to the
    neighbour table included (a restart continues with the same table), as CPU tensors."""
    case = {k for k, a in declared(sim).items() if a.from_case}
    return {k: _cpu(v) for k, v in particle_arrays(sim, with_table=True).items() if k not in case}


def snapshot(sim) -> dict:
    """The run's full state as a dict of CPU tensors and numbers."""
    d = {
        "format": FORMAT,
        "arrays": stored_arrays(sim),
        "t": sim.t, "step": sim.step,
        "energy": {k: _cpu(v) if isinstance(v, torch.Tensor) else v for k, v in sim.energy.items()},
        "heat": {k: _cpu(v) for k, v in getattr(sim, "heat_totals", {}).items()},
        "E0": getattr(sim, "E0", None),
        "body_velocity": _cpu(sim.body_velocity),
        "nl": {"table": {k: _cpu(v) if isinstance(v, torch.Tensor) else v
                         for k, v in sim.nl.table.state_dict().items()},
               "n_builds": sim.nl.n_builds, "n_partial": sim.nl.n_partial},
        "rng": torch.get_rng_state(),
        "stale": sim.stale,
        "plan": {"steps": sim.plan.steps, "sums": sim.plan.sums},
    }
    if sim.active_set is not None:
        d["active"] = {"n_refresh": sim.active_set.n_refresh, "age": sim.active_set.age}
    th = sim.thermal
    if th is not None:
        d["thermal"] = {"slow_mark": th.slow_mark, **window_state(th, sim.state.n)}
    return d


# format 1 (before the registry named every array): where each owner's arrays were kept
_LEGACY = {"thermal": ("th", {"zeta": "zeta_cache", "area": "area_cache"}), "surface": ("sf", {}),
           "active": ("as", {}), "nl": ("nl", {})}
_LEGACY_SCALARS = {"n_refresh", "age", "slow_mark", "partial_next", "fast", "int_rows", "table", "n_builds",
                   "n_partial"}


def arrays_of(d: dict) -> dict:
    """A checkpoint's per-particle arrays by registry name, whatever its format."""
    if d.get("format") == FORMAT or "arrays" in d:
        return d["arrays"]
    out = {f"state.{k}": v for k, v in d["state"].items()}
    out.update({k: d[k] for k in ("dvdt", "drhodt", "dTdt") if d.get(k) is not None})
    for sec, (prefix, renamed) in _LEGACY.items():
        for k, v in (d.get(sec) or {}).items():
            if isinstance(v, torch.Tensor) and k not in _LEGACY_SCALARS:
                out[f"{prefix}.{renamed.get(k, k)}"] = v
    out.update({k: v for k, v in d.get("terms", {}).items() if v is not None})
    return out


def state_arrays(d: dict) -> dict:
    """A checkpoint's particle state: field name -> CPU tensor."""
    a = arrays_of(d)
    return {k: a[f"state.{k}"] for k in FIELDS}


def save(sim, path: str | Path, cfg_hash: str, extra: dict | None = None, phys: dict | None = None):
    """Write a checkpoint atomically (temp file, fsync, rename)."""
    d = snapshot(sim)
    d["config_hash"] = cfg_hash
    d["physics"] = phys
    d["written"] = time.time()
    d["extra"] = extra or {}
    write(d, path)


ENVELOPE = "torchsph-checkpoint"  # the file: {ENVELOPE: 1, "sha256": digest of "data", "data": torch.save bytes}


def write(d: dict, path: str | Path):
    """Write a checkpoint dict atomically: serialised with its SHA-256, to ``NAME.tmp``,
    fsynced, renamed over ``NAME``; a damaged file is then told apart from a good one."""
    buf = io.BytesIO()
    torch.save(d, buf)
    data = buf.getvalue()

    def put(tmp):
        with open(tmp, "wb") as f:
            torch.save({ENVELOPE: 1, "sha256": hashlib.sha256(data).hexdigest(), "data": data}, f)
            f.flush()
            os.fsync(f.fileno())
            delay = float(os.environ.get("TORCHSPH_CHECKPOINT_TEST_DELAY_S", "0"))  # tests kill mid-write
            if delay > 0:
                time.sleep(delay)
    written(Path(path), put)  # (a failed write leaves the previous checkpoint as it was: OutputError)


def read(path: str | Path) -> dict:
    """A checkpoint file's dict (any format: the caller checks ``format``); a missing,
    unreadable or damaged file raises :class:`CheckpointError` in one line."""
    path = Path(path)
    if not path.exists():
        raise CheckpointError(f"--restart {path}: no such checkpoint")
    if path.is_dir():
        raise CheckpointError(f"--restart {path}: is a folder (give OUT/checkpoint.pt)")
    try:
        d = torch.load(path, map_location="cpu", weights_only=False)
    except Exception as e:  # noqa: BLE001 - a truncated, damaged or foreign file
        raise CheckpointError(f"--restart {path}: not a readable torchsph checkpoint "
                              f"({type(e).__name__}: {str(e).splitlines()[0] if str(e) else ''})") from None
    if isinstance(d, dict) and ENVELOPE in d:
        data = d.get("data")
        if not isinstance(data, bytes) or hashlib.sha256(data).hexdigest() != d.get("sha256"):
            raise CheckpointError(f"--restart {path}: damaged (its checksum does not match); use an "
                                  "earlier checkpoint or start the run again")
        try:
            d = torch.load(io.BytesIO(data), map_location="cpu", weights_only=False)
        except Exception as e:  # noqa: BLE001
            raise CheckpointError(f"--restart {path}: not a readable torchsph checkpoint ({type(e).__name__})") from None
    if not isinstance(d, dict):
        raise CheckpointError(f"--restart {path}: not a torchsph checkpoint")
    return d


def load(path: str | Path) -> dict:
    d = read(path)
    if d.get("format") not in (1, FORMAT):
        raise CheckpointError(f"--restart {path}: not a torchsph checkpoint of format {FORMAT} "
                              f"(format {d.get('format')!r})")
    return d


def restore(sim, d: dict, cfg: dict | None = None, path: str = "checkpoint", recorded: dict | None = None,
            branch: bool = False):
    """Put a loaded checkpoint into a simulation built from the same case (``cfg``: refused,
    naming what differs, if the checkpoint was written for other physics; see :func:`check_case`).
    ``branch``: the case's physics may differ (the caches that follow from the physics are
    made anew, from the state)."""
    changes = check_case(d, cfg, path, recorded, branch) if cfg is not None else []
    dev, dt = sim.state.device, sim.state.dtype
    arrays = arrays_of(d)
    x = arrays["state.x"]
    if x.shape[1] != sim.state.dim:
        raise CheckpointError(f"--restart {path}: dimension differs from the case")
    if x.dtype != dt:
        raise CheckpointError(f"--restart {path}: written in {x.dtype}, the run is {dt}")

    def to(t):
        return t.to(dev) if isinstance(t, torch.Tensor) else t

    known = declared(sim)
    arrays = {k: to(v) for k, v in fresh_caches(sim, arrays, branch, changes).items()
              if k in known and v is not None}  # (a term the case no longer names: its arrays left)
    # what the selection does not remake (the state, the rates, the table's and the active
    # set's arrays) goes in first; the per-selection caches are put back after the selection
    owners = holders(sim)
    later = tuple(f"{p}." for p, o in owners.items() if o.put_back_after_selection)
    for k in sim.nl.ARRAYS:  # the neighbour list's as the checkpoint has them (absent: none; older
        if f"nl.{k}" not in arrays:  # checkpoints: the next rebuild is a full one)
            sim.nl.set_array(k, None)
    set_particle_arrays(sim, {k: v for k, v in arrays.items() if not k.startswith(later)})
    sim.t, sim.step = d["t"], d["step"]
    sim.body_velocity = to(d["body_velocity"])
    nl = d["nl"]
    tab = nl.get("table", nl)  # (older checkpoints hold the dense (N, k) table as nl's nb / mask)
    sim.nl.table = NeighbourTable.from_state({k: to(v) if isinstance(v, torch.Tensor) else v
                                              for k, v in tab.items() if k in ("rows", "nb", "mask", "n")})
    sim.nl.n_builds = nl["n_builds"]
    # the partial rebuild's body set (absent in older checkpoints: the next rebuild is a full one)
    sim.nl.n_partial = nl.get("n_partial", 0)
    sim.stale = d.get("stale", False)
    if sim.active_set is not None and "active" in d:
        sim.active_set.n_refresh, sim.active_set.age = d["active"]["n_refresh"], d["active"].get("age", 0)
    th = sim.thermal
    if th is not None and th.k.shape[0] != sim.state.n:  # particles were added (a fed wire)
        th.k = torch.full((sim.state.n,), th.prm.conductivity, dtype=dt, device=dev)
    if "plan" in d:
        sim.plan.steps, sim.plan.sums = d["plan"]["steps"], d["plan"]["sums"]
    sim.energy = {k: to(v) for k, v in d["energy"].items()}
    if d.get("heat"):
        sim.heat_totals = {k: to(v) for k, v in d["heat"].items()}
    if d.get("E0") is not None:
        sim.E0 = d["E0"]
    if th is not None and "thermal" in d:
        th.slow_mark = d["thermal"].get("slow_mark")  # the slow rows' window, as it was
    # pair subsets anew (a function of the table and the phases), the caches as they were
    sim.rearm({k: v for k, v in arrays.items() if k.startswith(later)})
    if th is not None and "thermal" in d:
        restore_window(th, d["thermal"], to)
    torch.set_rng_state(d["rng"])
    sim.info = sim.measure()
    return {**d.get("extra", {}), "step_control_changes": changes}


__all__ = ["STEP_CONTROL", "CheckpointError", "arrays_of", "check_case", "config_hash", "differences", "load",
           "physics", "read", "recorded_physics", "restore", "save", "state_arrays", "write"]
