"""Checkpoints: a restart continues a run bit for bit; Ctrl-C leaves a loadable checkpoint;
a run killed while writing one leaves the previous checkpoint intact."""
import json
import math
import os
import signal
import subprocess
import sys
import time

import pytest
import torch
from conftest import CASES, ROOT

from torchsph.io import checkpoint as ckpt
from torchsph.io.config import load_case
from torchsph.run.runner import run_case


def final_state(path):
    return ckpt.state_arrays(ckpt.load(path))


@pytest.mark.parametrize("case,over,K", [
    ("poiseuille_2d", ["scene.n_height=20"], 60),             # fluid + walls, Verlet rebuilds
    ("oscillating_drop_2d", ["scene.dx_m=1e-4"], 40),          # free surface forces + shifting off
    ("beam_plate", ["run.t_end_s=0.02"], 30),                  # beam, latent heat, conduction
    ("preheated_block", ["heating.t_end_s=0.004"], 10),       # a composed term ([heating]) switching off
    ("pendant_drop", ["scene.dx_m=2e-4", "scene.wire_diameter_m=1.2e-3", "fluid.gravity_ramp_s=2e-4",
                      "numerics.compile=false"], 20),         # gravity ramped (restart mid-ramp), wetting
])
def test_restart_is_bit_for_bit(tmp_path, case, over, K):
    """float64: K steps == K/2 steps + checkpoint + restart + K/2 steps, every field equal."""
    _, cfg = load_case(CASES / case, over)
    run_case(cfg, CASES / case, tmp_path / "full", steps=K, progress=False)
    _, cfg = load_case(CASES / case, over)
    run_case(cfg, CASES / case, tmp_path / "half", steps=K // 2, progress=False)
    _, cfg = load_case(CASES / case, over)
    s = run_case(cfg, CASES / case, tmp_path / "half", steps=K - K // 2, progress=False,
                 restart=tmp_path / "half" / "checkpoint.pt")
    assert s["steps"] == K
    a, b = final_state(tmp_path / "full" / "checkpoint.pt"), final_state(tmp_path / "half" / "checkpoint.pt")
    for k in a:
        assert torch.equal(a[k], b[k]), k
    full, half = ckpt.load(tmp_path / "full" / "checkpoint.pt"), ckpt.load(tmp_path / "half" / "checkpoint.pt")
    assert full["t"] == half["t"] and full["step"] == half["step"]


def test_restart_refuses_a_different_case(tmp_path):
    _, cfg = load_case(CASES / "poiseuille_2d", ["scene.n_height=20"])
    run_case(cfg, CASES / "poiseuille_2d", tmp_path, steps=3, progress=False)
    _, cfg = load_case(CASES / "poiseuille_2d", ["scene.n_height=20", "fluid.viscosity_Pa_s=0.002"])
    with pytest.raises(ckpt.CheckpointError, match=r"different case: fluid.viscosity_Pa_s = 0.001 in the checkpoint, "
                                                   r"0.002 now"):
        run_case(cfg, CASES / "poiseuille_2d", tmp_path, steps=3, progress=False,
                 restart=tmp_path / "checkpoint.pt")


def test_restart_may_change_the_step_control_and_says_so(tmp_path):
    """A run stopped by a blow-up goes on from its last checkpoint with a smaller CFL number:
    the restart is accepted, takes steps of the new size (the acoustic limit binds: dt scales
    with the CFL number) and records the change; a physics change next to it is still
    refused, by name."""
    _, cfg = load_case(CASES / "taylor_green_2d", ["numerics.cfl=0.25"])
    s1 = run_case(cfg, CASES / "taylor_green_2d", tmp_path, steps=3, progress=False)
    assert s1["dt_binding_limit"] == "acoustic"
    _, cfg = load_case(CASES / "taylor_green_2d", ["numerics.cfl=0.05",
                                                 "fluid.viscosity_Pa_s=0.5"])
    with pytest.raises(ckpt.CheckpointError, match=r"different case: fluid.viscosity_Pa_s = 0.01 in the "
                                                   r"checkpoint, 0.5 now; only \[run\] and numerics.cfl"):
        run_case(cfg, CASES / "taylor_green_2d", tmp_path / "b", steps=3, progress=False,
                 restart=tmp_path / "checkpoint.pt")
    _, cfg = load_case(CASES / "taylor_green_2d", ["numerics.cfl=0.05"])
    s2 = run_case(cfg, CASES / "taylor_green_2d", tmp_path / "c", steps=2, progress=False,
                  restart=tmp_path / "checkpoint.pt")
    assert s2["steps"] == 5
    assert s2["restart_step_control_changes"] == ["numerics.cfl = 0.25 in the checkpoint, 0.05 now"]
    # cfl h / (c0 + |u|max): |u|max is ~1 % of c0 and decays by ~1e-4 over these steps
    assert s2["dt_max_s"] == pytest.approx(s1["dt_min_s"] * 0.2, rel=1e-3)
    # and the new checkpoint carries the new value: restarting it with 0.05 changes nothing
    s3 = run_case(cfg, CASES / "taylor_green_2d", tmp_path / "c", steps=1, progress=False,
                  restart=tmp_path / "c" / "checkpoint.pt")
    assert s3["restart_step_control_changes"] == []


@pytest.mark.parametrize("carried", [True, False])
def test_restart_accepts_a_checkpoint_from_before_a_key_was_added_at_its_default(tmp_path, carried):
    """A newer version adds a physics key whose default keeps the old behaviour: a checkpoint
    written without it (its recorded physics carried inside, or, for checkpoints that carry
    none, in the run's config.json next to it) still restarts; the same key at another value
    is refused by name."""
    import json

    _, cfg = load_case(CASES / "poiseuille_2d", ["scene.n_height=20"])
    run_case(cfg, CASES / "poiseuille_2d", tmp_path, steps=3, progress=False)
    path = tmp_path / "checkpoint.pt"
    d = ckpt.load(path)
    old = ckpt.physics(cfg)
    del old["numerics"]["active_tolerance_K"]  # "the older version had no such key"
    d["config_hash"] = ckpt.config_hash(old)
    if carried:
        d["physics"] = old
    else:
        d.pop("physics")
        rec = json.loads((tmp_path / "config.json").read_text())
        del rec["numerics"]["active_tolerance_K"]
        (tmp_path / "config.json").write_text(json.dumps(rec))
    torch.save(d, path)
    _, cfg = load_case(CASES / "poiseuille_2d", ["scene.n_height=20", "numerics.active_tolerance_K=2.0"])
    with pytest.raises(ckpt.CheckpointError, match=r"numerics.active_tolerance_K = \(absent\) in the checkpoint, 2.0 now"):
        ckpt.check_case(d, cfg, str(path), None if carried else ckpt.recorded_physics(path))
    _, cfg = load_case(CASES / "poiseuille_2d", ["scene.n_height=20"])
    s = run_case(cfg, CASES / "poiseuille_2d", tmp_path, steps=2, progress=False, restart=path)
    assert s["steps"] == 5


def test_a_checkpoint_from_before_a_default_changed_is_not_continued_with_the_new_default():
    """surface.band_curvature came in with 'beside' as its default and turned 'clear' later: a
    checkpoint written before the key existed ran 'beside', so with the wetting model on its
    restart under the new default is refused by name, and accepted with 'beside' set; where
    the key does nothing (no contact angle) its absence is no difference."""
    def old_checkpoint(cfg):
        old = ckpt.physics(cfg)
        del old["surface"]["band_curvature"]
        return {"config_hash": ckpt.config_hash(old), "physics": old}

    _, cfg = load_case(CASES / "sessile_drop_2d", ["surface.band_curvature=beside"])
    d = old_checkpoint(cfg)
    _, now = load_case(CASES / "sessile_drop_2d", [])
    assert now["surface"]["band_curvature"] == "clear"
    with pytest.raises(ckpt.CheckpointError, match="surface.band_curvature = beside in the checkpoint, clear now"):
        ckpt.check_case(d, now, "old.pt")
    assert ckpt.check_case(d, cfg, "old.pt") == []
    _, dry = load_case(CASES / "sessile_drop_2d", ["surface.wetting=false"])
    assert ckpt.check_case(old_checkpoint(dry), dry, "old.pt") == []


def _start(args, env=None):
    return subprocess.Popen([sys.executable, "-m", "torchsph", *args], cwd=ROOT, env=env,
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)


def _wait_for(path, proc, timeout=120):
    t0 = time.time()
    while not path.exists():
        if proc.poll() is not None or time.time() - t0 > timeout:
            raise AssertionError(f"{path} never appeared: {proc.communicate()}")
        time.sleep(0.1)


def test_sigint_leaves_a_loadable_checkpoint(tmp_path):
    p = _start([str(CASES / "poiseuille_2d"), "--out", str(tmp_path), "--steps", "1000000", "--quiet",
                "--set", "scene.n_height=20"])
    _wait_for(tmp_path / "snap_00000.h5", p)
    time.sleep(2.0)
    p.send_signal(signal.SIGINT)
    _, err = p.communicate(timeout=120)
    assert p.returncode == 130, err
    assert "checkpoint" in err
    d = ckpt.load(tmp_path / "checkpoint.pt")
    assert d["step"] > 0
    # summary.json is written on SIGINT too, saying so, with the wall time of the run
    s1 = json.loads((tmp_path / "summary.json").read_text())
    assert s1["interrupted"] is True and s1["steps"] == d["step"] and s1["wall_s"] == s1["wall_last_leg_s"] > 0
    # and the run continues from it
    r = subprocess.run([sys.executable, "-m", "torchsph", str(CASES / "poiseuille_2d"), "--out", str(tmp_path),
                        "--steps", "5", "--quiet", "--set", "scene.n_height=20",
                        "--restart", str(tmp_path / "checkpoint.pt")],
                       cwd=ROOT, capture_output=True, text=True, timeout=300, check=False)
    assert r.returncode == 0, r.stderr
    assert ckpt.load(tmp_path / "checkpoint.pt")["step"] == d["step"] + 5
    s2 = json.loads((tmp_path / "summary.json").read_text())  # the wall time over both legs, and the last
    assert s2["interrupted"] is False and s2["steps"] == d["step"] + 5 and s2["steps_last_leg"] == 5
    # the wall time of the first leg as its checkpoint recorded it (a little before its summary)
    assert 0 < d["extra"]["wall_s"] <= s1["wall_s"]
    assert s2["wall_s"] == pytest.approx(d["extra"]["wall_s"] + s2["wall_last_leg_s"], rel=1e-12)


def test_sigkill_while_writing_keeps_the_previous_checkpoint(tmp_path):
    base = [str(CASES / "poiseuille_2d"), "--out", str(tmp_path), "--quiet", "--set", "scene.n_height=20"]
    r = subprocess.run([sys.executable, "-m", "torchsph", *base, "--steps", "4"], cwd=ROOT,
                       capture_output=True, text=True, timeout=300, check=False)
    assert r.returncode == 0, r.stderr
    before = ckpt.load(tmp_path / "checkpoint.pt")
    env = dict(os.environ, TORCHSPH_CHECKPOINT_TEST_DELAY_S="60")
    p = _start([*base, "--steps", "100", "--checkpoint-every", "2", "--restart",
                str(tmp_path / "checkpoint.pt")], env=env)
    _wait_for(tmp_path / "checkpoint.pt.tmp", p)  # the next checkpoint is being written
    p.send_signal(signal.SIGKILL)
    p.communicate(timeout=60)
    after = ckpt.load(tmp_path / "checkpoint.pt")
    assert after["step"] == before["step"] == 4
    for k, v in ckpt.state_arrays(before).items():
        assert torch.equal(v, ckpt.state_arrays(after)[k])


@pytest.mark.parametrize("where", ["checkpoint", "snapshot"])
def test_a_full_disk_stops_the_run_in_one_line_and_keeps_the_last_checkpoint(tmp_path, monkeypatch, capsys, where):
    """The disk fills while a checkpoint (or a snapshot) is written: the run stops with exit 4
    and one line naming the file, the operating system's reason and the checkpoint to go on
    from; no temporary file is left; the previous checkpoint loads as it was; and the run goes
    on from it once there is room."""
    import errno

    import h5py

    from torchsph.__main__ import main
    from torchsph.io import snapshots as sio

    base = [str(CASES / "poiseuille_2d"), "--out", str(tmp_path), "--quiet", "--set", "scene.n_height=20",
            "--set", "run.output_interval_s=1e-5"]
    assert main([*base, "--steps", "4"]) == 0
    before = ckpt.load(tmp_path / "checkpoint.pt")
    full = OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))
    if where == "checkpoint":  # the disk fills after the temporary file was written, before its rename
        def fsync(fd):
            raise full
        monkeypatch.setattr(ckpt.os, "fsync", fsync)
    else:  # the snapshot's file cannot be made
        real = h5py.File

        def File(name, mode="r", *a, **k):
            if mode == "w":
                raise full
            return real(name, mode, *a, **k)
        monkeypatch.setattr(sio.h5py, "File", File)
    capsys.readouterr()
    code = main([*base, "--steps", "40", "--checkpoint-every", "2", "--restart", str(tmp_path / "checkpoint.pt")])
    err = capsys.readouterr().err.strip().splitlines()
    assert code == 4
    assert len(err) == 1, err
    line = err[0]
    assert "could not write" in line and os.strerror(errno.ENOSPC) in line
    assert ("checkpoint.pt" if where == "checkpoint" else ".h5") in line.split("(")[0]
    assert f"--restart {tmp_path / 'checkpoint.pt'}" in line
    assert not list(tmp_path.glob("*.tmp"))
    after = ckpt.load(tmp_path / "checkpoint.pt")
    assert after["step"] == before["step"] == 4
    for k, v in ckpt.state_arrays(before).items():
        assert torch.equal(v, ckpt.state_arrays(after)[k])
    monkeypatch.undo()  # room again: the run goes on from the checkpoint
    assert main([*base, "--steps", "2", "--restart", str(tmp_path / "checkpoint.pt")]) == 0
    assert ckpt.load(tmp_path / "checkpoint.pt")["step"] == 6


def _kinetic(path):
    s = final_state(path)
    return 0.5 * float((s["m"] * (s["v"] ** 2).sum(1)).sum())


def test_a_branch_goes_on_from_a_state_with_other_physics(tmp_path):
    """``--branch``: a Taylor-Green vortex run with viscosity 0.01 Pa s goes on from its
    checkpoint with 0.02. Its kinetic energy then decays at the rate of the new viscosity,
    4 nu k^2 (twice the restart's, each within 5 % of the analytic rate: 3.2 % and 0.1 % fast; 1.94 times), the change is
    recorded in summary.json, and the same change is refused as a restart; a branch with no
    change is the restart, bit for bit; a key that builds the scene may not change."""
    case, base = CASES / "taylor_green_2d", ["scene.nx=30"]
    _, cfg = load_case(case, base)
    run_case(cfg, case, tmp_path / "a", steps=40, progress=False)
    ck = tmp_path / "a" / "checkpoint.pt"
    e0, t0 = _kinetic(ck), ckpt.load(ck)["t"]
    rates = {}
    for nu in (0.01, 0.02):
        _, cfg = load_case(case, base + [f"fluid.viscosity_Pa_s={nu}"])
        out = tmp_path / f"nu{nu}"
        s = run_case(cfg, case, out, steps=80, progress=False, restart=ck, branch=True)
        rates[nu] = math.log(e0 / _kinetic(out / "checkpoint.pt")) / (s["t_final_s"] - t0)
        assert rates[nu] == pytest.approx(4 * nu * (2 * math.pi) ** 2, rel=0.05), nu
    assert rates[0.02] / rates[0.01] == pytest.approx(2.0, rel=0.05)  # measured 1.94 (nx = 30)
    assert s["branch"] == {"from": str(ck), "changes": ["fluid.viscosity_Pa_s = 0.01 in the checkpoint, 0.02 now"]}
    with pytest.raises(ckpt.CheckpointError, match=r"--restart .*viscosity_Pa_s = 0.01 in the checkpoint, 0.02 now"):
        run_case(cfg, case, tmp_path / "r", steps=2, progress=False, restart=ck)
    _, cfg = load_case(case, base)
    run_case(cfg, case, tmp_path / "same", steps=10, progress=False, restart=ck, branch=True)
    _, cfg = load_case(case, base)
    run_case(cfg, case, tmp_path / "restart", steps=10, progress=False, restart=ck)
    a, b = final_state(tmp_path / "same" / "checkpoint.pt"), final_state(tmp_path / "restart" / "checkpoint.pt")
    assert all(torch.equal(a[k], b[k]) for k in a)
    _, cfg = load_case(case, ["scene.nx=30", "scene.U_m_s=2.0"])
    with pytest.raises(ckpt.CheckpointError, match=r"--branch .*scene.U_m_s = 1.0 in the checkpoint, 2.0 now; "
                                                   r"a branch may change any physics key but \[scene\]"):
        run_case(cfg, case, tmp_path / "u", steps=2, progress=False, restart=ck, branch=True)
