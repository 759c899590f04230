"""The CLI runs a case and writes HDF5 snapshots, an XDMF that names them, and summary.json."""
import json
import subprocess
import sys
import xml.etree.ElementTree as ET

import h5py
import numpy as np
import pytest
from conftest import CASES, ROOT

from torchsph.io.snapshots import read_snapshot

DATASETS = {"position", "velocity", "density", "pressure", "mass", "temperature", "peak_temperature", "phase", "id", "body"}  # (torchsph.core.state.FIELDS)


def test_cli_run_writes_outputs(tmp_path):
    out = tmp_path / "out"
    r = subprocess.run([sys.executable, "-m", "torchsph", str(CASES / "poiseuille_2d"), "--out", str(out),
                        "--steps", "30", "--dtype", "float32", "--set", "run.output_interval_s=0.005"],
                       cwd=ROOT, capture_output=True, text=True, timeout=300)
    assert r.returncode == 0, r.stderr
    summary = json.loads((out / "summary.json").read_text())
    for key in ("n_particles", "steps", "t_final_s", "wall_s", "particle_steps_per_s", "device", "dtype",
                "dt_binding_limit"):
        assert key in summary
    assert summary["steps"] == 30 and summary["dtype"] == "float32" and summary["device"] == "cpu"
    assert summary["dt_binding_limit"] == "viscous"
    snaps = sorted(out.glob("snap_*.h5"))
    assert len(snaps) >= 2
    snap = read_snapshot(snaps[-1])
    assert snap["step"] == 30 and snap["dim"] == 2 and snap["position"].shape[1] == 3
    with h5py.File(snaps[-1]) as f:
        assert set(f.keys()) == DATASETS
        n = summary["n_particles"]
        assert f["position"].shape == (n, 3) and f["velocity"].shape == (n, 3)
        assert f["density"].dtype == np.float32
        assert np.all(np.diff(f["id"][()]) == 1)  # written in id order
        assert abs(f.attrs["time"] - summary["t_final_s"]) < 1e-12
    tree = ET.parse(out / "particles.xdmf")
    grids = tree.getroot().findall(".//Grid[@GridType='Uniform']")
    assert len(grids) == len(snaps)
    for g in grids:
        for item in g.iter("DataItem"):
            fname, path = item.text.split(":")
            assert (out / fname).exists()
            with h5py.File(out / fname) as f:
                assert path.lstrip("/") in f
                assert list(f[path.lstrip("/")].shape) == [int(d) for d in item.get("Dimensions").split()]
    assert not list(out.glob("*.tmp"))


@pytest.mark.parametrize("every", [None, 1])
def test_cli_reports_blow_up_as_one_line(tmp_path, every):
    """One line of diagnosis; where a checkpoint was written it names it and how to go on."""
    r = subprocess.run([sys.executable, "-m", "torchsph", str(CASES / "taylor_green_2d"), "--out", str(tmp_path),
                        "--steps", "300", "--quiet", "--set", "scene.nx=20", "--set", "numerics.dt_s=0.02",
                        "--set", "numerics.allow_unstable_dt=true"]
                       + ([] if every is None else ["--checkpoint-every", str(every)]),
                       cwd=ROOT, capture_output=True, text=True, timeout=300)
    assert r.returncode == 3
    lines = r.stderr.strip().splitlines()
    assert len(lines) == 1 and "blow-up at step" in lines[0] and "largest term" in lines[0]
    assert ("--restart" in lines[0]) == (every is not None)


def test_cli_thermal_run_reports_energy_balance(tmp_path):
    r = subprocess.run([sys.executable, "-m", "torchsph", str(CASES / "beam_plate"), "--out", str(tmp_path),
                        "--steps", "5", "--quiet", "--set", "thermal.emissivity=0.4"],
                       cwd=ROOT, capture_output=True, text=True, timeout=300)
    assert r.returncode == 0, r.stderr
    assert "balance residual" in r.stdout
    e = json.loads((tmp_path / "summary.json").read_text())["energy"]
    assert e["beam_J"] > 0 and e["radiation_J"] < 0
    assert abs(e["residual_J"]) < 1e-9 * e["beam_J"]


def test_estimate_projects_the_steps_of_the_run(tmp_path):
    """--estimate counts the steps the run then takes (from the time-step limits, to within one),
    writes nothing, and projects its probe's time per step over those steps. How close the
    projected wall time comes to the real one is measured, not tested (tests assert no wall-clock
    times): `python scripts/tools/cost_table.py cases/poiseuille_2d --against-run`."""
    from torchsph.io.config import load_case
    from torchsph.run.runner import run_case

    _, cfg = load_case(CASES / "poiseuille_2d", ["scene.n_height=40"])
    est = run_case(cfg, CASES / "poiseuille_2d", tmp_path / "est", t_end=0.03, progress=False, estimate=True)
    assert not (tmp_path / "est").exists()  # an estimate writes nothing
    _, cfg = load_case(CASES / "poiseuille_2d", ["scene.n_height=40"])
    s = run_case(cfg, CASES / "poiseuille_2d", tmp_path / "run", t_end=0.03, progress=False)
    assert abs(est["estimate"]["steps_left"] - s["steps"]) <= 1
    assert est["probe_steps"] >= 1 and est["probe_wall_s"] > 0
    assert est["projected_wall_s"] == pytest.approx(
        est["probe_wall_s"] / est["probe_steps"] * est["estimate"]["steps_left"], rel=1e-12)


def test_the_cost_block_says_when_the_snapshots_outgrow_the_free_disk(tmp_path):
    """The cost block gives the disk's free space beside the snapshots' size, and warns (once,
    before the probe) when they need more than there is."""
    from torchsph.io import snapshots as sio
    from torchsph.run.progress import projection_lines

    free = sio.free_bytes(tmp_path / "not" / "made" / "yet")  # (the nearest existing folder's disk)
    assert free is not None and free > 0
    kw = dict(n_all=1000, n_active=1000, rss_gb=0.1, ranks=1, steps_left=100.0, dt_s=1e-4, dt_why="acoustic limit",
              snapshots=10, snapshot_bytes=2**30)
    ok = projection_lines(**kw, probe=None, disk_free=20 * 2**30)
    assert "10 snapshots, ~10.00 GB on disk (20.00 GB free there)" in ok[1]
    assert not any("more than the free disk" in line for line in ok)
    short = projection_lines(**kw, probe=None, disk_free=5 * 2**30)
    assert any("more than the free disk" in line and "output_interval_s" in line for line in short)
    assert not any("more than the free disk" in line for line in projection_lines(**kw, probe=(10, 1.0), disk_free=5 * 2**30))


def test_the_projection_says_it_is_a_lower_bound_where_melt_is_to_come():
    """A probe taken before the melt (the step limit is the melt's, "once melt flows") or
    where heat will spread over more particles projects too little: the line says why."""
    from torchsph.run.progress import projection_lines

    kw = dict(n_all=1000, n_active=1000, rss_gb=0.1, ranks=1, steps_left=100.0, dt_s=1e-4, snapshots=1,
              snapshot_bytes=1.0, probe=(10, 1.0))
    plain = projection_lines(**kw, dt_why="acoustic limit")[2]
    assert "lower bound" not in plain and "projected wall time 10 s" in plain
    melt = projection_lines(**kw, dt_why="acoustic limit, once melt flows")[2]
    assert "(a lower bound: the probe ran before the melt" in melt
    both = projection_lines(**{**kw, "n_active": 100}, dt_why="acoustic limit, once melt flows")[2]
    assert "before the melt" in both and "10x as many particles may come to work" in both
