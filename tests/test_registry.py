"""The per-particle array registry (torchsph.step.particles): every array a checkpoint, a
migration, a ghost refresh or a snapshot carries is one it declares, and a term's own array
travels through all of them with no edit outside the term's module (tests/tally_term.py)."""
import json
import os
import shutil
import subprocess
import sys
from pathlib import Path

import h5py
import numpy as np
import pytest
import torch
from conftest import CASES

from torchsph.core.schema import CaseError
from torchsph.core.state import FIELDS, ParticleState
from torchsph.io import checkpoint as ckpt
from torchsph.io.config import load_case
from torchsph.run.build import make_simulation
from torchsph.step import particles
from torchsph.step.loop import run_steps

ROOT = Path(__file__).resolve().parents[1]
MPIEXEC = shutil.which("mpiexec", path=str(Path(sys.executable).parent)) or shutil.which("mpiexec")
ENV = {**os.environ, "PYTHONPATH": str(ROOT), "OMP_NUM_THREADS": "1"}
# a tank whose body force drives the fluid along x through the slab boundaries
TANK = ["fluid.body_force_m_s2=[3.0, 0.0, 0.0]", "numerics.migration_slack_over_skin=0"]  # (every rebuild migrates)


def cli(args, n=1):
    pre = [MPIEXEC, "-n", str(n)] if n > 1 else []
    r = subprocess.run(pre + [sys.executable, str(ROOT / "tests" / "tally_term.py")] + args, cwd=ROOT, env=ENV,
                       capture_output=True, text=True, timeout=600)
    assert r.returncode == 0, r.stderr[-3000:]
    return r


def last_snapshot(out: Path) -> dict:
    with h5py.File(sorted(out.glob("snap_*.h5"))[-1], "r") as f:
        return {k: f[k][()] for k in f} | {"step": int(f.attrs["step"])}


def test_the_state_fields_are_declared_once():
    """The state's dataclass, its conversions and the snapshot's datasets all come from FIELDS."""
    from dataclasses import fields
    assert [f.name for f in fields(ParticleState)] == list(FIELDS)
    src = "".join(p.read_text() for p in (ROOT / "torchsph").rglob("*.py")) + (ROOT / "parallel" / "run.py").read_text()
    for name in ("DATASETS", "FLOAT_FIELDS", "INT_FIELDS", "LAZY_CACHES"):  # the hand-kept lists that went
        assert name not in src, name


def test_every_array_held_is_declared_and_a_checkpoint_stores_exactly_the_registry(tmp_path):
    """The deposition preview (beams, losses, surface forces, the fed wire, the active set):
    each per-particle array the simulation holds has a declaration, and a checkpoint stores
    the registry's arrays, no other per-particle array, all of them under their registry names."""
    _, cfg = load_case(CASES / "perpendicular_350W", [], preview=True)
    _, sim = make_simulation(cfg)
    run_steps(sim, steps=30)
    held = particles.particle_arrays(sim, with_table=True)
    dec = particles.declared(sim)
    assert set(held) <= set(dec)
    assert {"sf.kappa", "th.area_cache", "as.work", "nl.x_ref", "dTdt"} <= set(held)
    d = ckpt.snapshot(sim)
    case = {k for k, a in dec.items() if a.from_case}
    assert set(d["arrays"]) == set(held) - case
    n = sim.state.n

    def per_particle(obj, path=""):  # no per-particle tensor outside "arrays"
        if isinstance(obj, dict):
            return [p for k, v in obj.items() if k != "arrays" for p in per_particle(v, f"{path}.{k}")]
        return [path] if isinstance(obj, torch.Tensor) and obj.ndim >= 1 and obj.shape[0] == n else []
    stray = [p for p in per_particle(d) if not p.startswith((".nl.table", ".thermal.fast", ".thermal.int_rows"))]
    assert stray == []


def test_fields_names_an_unknown_array_in_one_line(tmp_path):
    _, cfg = load_case(CASES / "radiating_slab", [])
    _, sim = make_simulation(cfg)
    with pytest.raises(CaseError, match=r"\[run\] fields = \['curvature'\]: no per-particle array 'curvature'.*"
                                        r"allowed: .*enthalpy_rate"):
        particles.output_fields(sim, ["curvature"])  # (a slab has no surface forces)
    assert particles.output_fields(sim, ["enthalpy_rate", "th.zeta_cache"]) == {"enthalpy_rate": "dTdt",
                                                                                 "th.zeta_cache": "th.zeta_cache"}


def test_the_snapshot_holds_the_fields_a_case_names(tmp_path):
    """``[run] fields``: the free surface's curvature and normals and the enthalpy rate of the
    oscillating drop written beside the state, described in the XDMF; the curvature is the
    surface model's own array (by id), zero off the surface."""
    out = tmp_path / "drop"
    r = subprocess.run([sys.executable, "-m", "torchsph", str(CASES / "oscillating_drop_2d"), "--quiet", "--steps",
                        "20", "--out", str(out), "--set", 'run.fields=["curvature", "surface_normal", "acceleration"]'],
                       cwd=ROOT, env=ENV, capture_output=True, text=True, timeout=600)
    assert r.returncode == 0, r.stderr[-2000:]
    s = last_snapshot(out)
    assert s["step"] == 20 and s["curvature"].shape == s["density"].shape and s["surface_normal"].shape[1] == 3
    kappa = s["curvature"]
    assert (kappa != 0).sum() > 0 and (kappa == 0).sum() > 0  # on the surface only
    _, cfg = load_case(CASES / "oscillating_drop_2d", [])
    _, sim = make_simulation(cfg)
    run_steps(sim, steps=20)
    order = sim.state.id.argsort()
    assert np.array_equal(kappa, sim.surface_model.kappa[order].numpy())
    xdmf = (out / "particles.xdmf").read_text()
    assert 'Attribute Name="curvature" AttributeType="Scalar"' in xdmf
    assert 'Attribute Name="surface_normal" AttributeType="Vector"' in xdmf


@pytest.mark.skipif(MPIEXEC is None, reason="no mpiexec (pip install mpich)")
def test_a_new_terms_array_travels_through_checkpoints_migration_and_snapshots(tmp_path):
    """The test's own term (tests/tally_term.py, no edit of the solver) through the CLI: run
    in one process, on 2 ranks (migrations and ghost refreshes), and restarted from a
    one-process checkpoint on 3 ranks. Its ``count`` reaches K + 1 on every fluid particle in
    all three (an array left behind, or another particle's taken, stops counting), and the
    snapshots hold it by its output name and its ``tag`` by its registry name."""
    case = tmp_path / "case"
    case.mkdir()
    (case / "case.toml").write_text((CASES / "hydrostatic_tank_3d" / "case.toml").read_text() + "\n[tally]\n")
    K = 150
    sets = ["--quiet", "--set", 'run.fields=["tally_count", "tally.tag"]'] + [a for s in TANK for a in ("--set", s)]
    cli([str(case), "--steps", str(K), "--out", str(tmp_path / "one")] + sets)
    cli([str(case), "--steps", str(K), "--out", str(tmp_path / "two")] + sets, n=2)
    cli([str(case), "--steps", str(K // 2), "--out", str(tmp_path / "half")] + sets)
    cli([str(case), "--steps", str(K // 2), "--out", str(tmp_path / "three"), "--restart",
         str(tmp_path / "half" / "checkpoint.pt")] + sets, n=3)
    ref = last_snapshot(tmp_path / "one")
    fluid = ref["phase"] == 0
    assert ref["step"] == K and fluid.sum() > 0
    assert np.all(ref["tally_count"][fluid] == K + 1) and np.all(ref["tally_count"][~fluid] == 0)
    assert np.array_equal(ref["tally.tag"][fluid], ref["id"][fluid])
    for run in ("two", "three"):
        assert json.loads((tmp_path / run / "summary.json").read_text())["migrations"] >= 2
        got = last_snapshot(tmp_path / run)
        assert got["step"] == K and np.array_equal(got["id"], ref["id"])
        assert np.array_equal(got["tally_count"], ref["tally_count"]), run
        assert np.array_equal(got["tally.tag"], ref["tally.tag"]), run
        assert np.abs(got["position"] - ref["position"]).max() < 1e-10 * np.abs(ref["position"]).max()
