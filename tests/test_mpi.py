"""MPI domain decomposition with real ranks (mpiexec from the mpich wheel): decomposed runs
equal the single-process run, migration conserves particles and mass, checkpoints restart
on other rank counts, and an exception on one rank ends the whole run."""
import json
import os
import shutil
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

from torchsph.io.config import load_case
from torchsph.io.snapshots import read_snapshot
from torchsph.run.build import make_simulation
from torchsph.step.loop import run_steps

pytest.importorskip("mpi4py")
ROOT = Path(__file__).resolve().parents[1]
MPIEXEC = shutil.which("mpiexec", path=str(Path(sys.executable).parent)) or shutil.which("mpiexec")
pytestmark = pytest.mark.skipif(MPIEXEC is None, reason="no mpiexec (pip install mpich)")
ENV = {**os.environ, "PYTHONPATH": str(ROOT), "OMP_NUM_THREADS": "1"}

# a sloshing tank: the body force drives a flow along x through the slab boundaries
FLUID = (ROOT / "cases" / "hydrostatic_tank_3d", ["fluid.body_force_m_s2=[3.0, 0.0, 0.0]"], 150)
# conduction with melting (fluid particles appear) and fixed-temperature walls
THERMAL = (ROOT / "cases" / "stefan_1d", [], 150)
# an oscillating drop: surface tension (normals, curvature) across the slab boundary
SURFACE = (ROOT / "cases" / "oscillating_drop_2d", [], 150)
# a cap spreading on a plate: the contact line (wetting) across the slab boundary at x = 0
WETTING = (ROOT / "cases" / "sessile_drop_2d", ["surface.contact_angle_deg=30.0", "scene.dx_m=5e-5",
                                                 "scene.initial_angle_deg=60.0"], 600)
# the deposition scene, small: two beams (global shadowing), the fed wire (layers inserted on
# the owning rank, copied as ghosts), the active set, melting; the slab boundary cuts the wire
DEPOSITION = (ROOT / "cases" / "perpendicular_350W",
              ["scene.dx_m=2.5e-4", "scene.substrate_size_m=[3.0e-3, 3.0e-3, 1.0e-3]", "scene.wire_offset_m=1.5e-3",
               "scene.wire_length_m=1.0e-3", "scene.wire_gap_m=1.5e-3", "scene.wire_feed_m_s=0.1",
               "numerics.conduction_window=0.0"], 300)  # (one process's: the ranks sum every row every step)

# the deposition scene at its full substrate, coarse: a re-armed rank's losses once took the colour
# stage's gradient of rows asked for before the re-arm (the 2-rank run failed within 35 steps, 124
# rows against 0, up to 2d75fd6)
WIDE = (ROOT / "cases" / "perpendicular_350W", ["scene.dx_m=2.5e-4", "numerics.conduction_window=0.0"], 60)

# periodic along x, the slabs' axis: the end slabs are each other's neighbours (ghosts through
# the periodic images); the vortex without shifting (shifted, the lattice the flow deforms
# amplifies a rounding difference 1e5x within 80 steps in one process alone, even at a stable
# coefficient: the sums' order on ranks is then all the comparison would see)
PERIODIC = (ROOT / "cases" / "taylor_green_2d", ["numerics.shifting=0.0"], 100)
# a channel flow through the periodic ends: particles leave at x = L and enter at 0 (94 of 234
# within 400 steps), on a domain shorter than the halo (every particle is every rank's ghost)
CHANNEL = (ROOT / "cases" / "poiseuille_2d", ["fluid.body_force_m_s2=[2000.0, 0.0]"], 400)
# particle shifting: a ghost's shift reads neighbours beyond the outer ghosts, so the fluid
# ghosts take their owners' drifted positions (before that fix 0.008 of the tank off in x)
SHIFTING = (FLUID[0], FLUID[1] + ["numerics.shifting=0.5"], 40)
# a free drop with the discrete forces' resultant removed: a sum over the whole surface
RESULTANT = (ROOT / "cases" / "marangoni_drop_titanium", ["scene.dx_m=0.4e-3"], 60)

# the case names [solid_contact] (melt repelled from solid across the slab boundary; a rank may own
# no melt: its contact pairs are empty), against approach only; here the spring alone, whose force
# at rest reads no velocity
CONTACT = (DEPOSITION[0], DEPOSITION[1] + ["solid_contact.approach_over_c0=0.0"], 300)

# the wire stalls on the substrate (no sources: it arrives unmelted and rests there); the
# stall is decided on every rank together
STALL = (ROOT / "cases" / "perpendicular_350W",
         DEPOSITION[1][:4] + ["numerics.conduction_window=0.0", "scene.wire_gap_m=0.1e-3", "scene.wire_feed_m_s=0.03", "scene.source_layout=\"none\"",
                              "scene.wire_stall=true"], 20)


def mpirun(n, args, env=ENV, timeout=600):
    return subprocess.run([MPIEXEC, "-n", str(n), sys.executable] + args, cwd=ROOT, env=env,
                          capture_output=True, text=True, timeout=timeout)


def serial(case, overrides, steps):
    _, cfg = load_case(case, overrides)
    _, sim = make_simulation(cfg)
    run_steps(sim, steps=steps)
    s = sim.state
    o = s.id.argsort()
    return {k: getattr(s, k)[o].numpy() for k in ("id", "x", "v", "rho", "T", "m", "phase")}, sim


def rel(a, b):
    scale = max(float(np.abs(a).max()), 1e-300)
    return float(np.abs(a - b).max()) / scale


@pytest.mark.parametrize("which", ["fluid", "thermal", "surface", "wetting", "deposition", "contact", "stall",
                                   "periodic", "channel", "shifting", "resultant", "wide"])
def test_decomposed_run_equals_single_process(tmp_path, which):
    """After K steps on 2 and 3 ranks the state gathered by id equals the single-process run to
    1e-10 relative (float64); particle count and total mass are exactly conserved. On 2 ranks
    a rebuild migrates only when some particle has moved half the halo's slack (the default);
    on 3 every rebuild migrates (no slack)."""
    case, ov, K = {"fluid": FLUID, "thermal": THERMAL, "surface": SURFACE, "wetting": WETTING, "deposition": DEPOSITION,
                   "contact": CONTACT, "stall": STALL, "periodic": PERIODIC, "channel": CHANNEL, "shifting": SHIFTING,
                   "resultant": RESULTANT, "wide": WIDE}[which]
    ref, sim = serial(case, ov, K)
    if which == "stall":
        assert sim.feeder.stalled and sim.feeder.stall_s > 0
    if which == "contact":  # melt is near solid: the repulsion acts
        assert sum(t.pi.numel() for t in sim.terms) > 0
    if which == "resultant":
        assert sim.surface.prm.zero_net_force and sim.surface.n_surface > 0
    if which == "channel":  # the fastest particles crossed the periodic end (half the final speed over the run)
        assert 0.5 * float(sim.state.v[:, 0].max()) * sim.t > sim.domain.length[0]
    if which == "deposition":  # what the case must exercise
        assert sim.feeder.n_fed >= 2 and (ref["phase"] == 0).sum() > 0 and sim.active_set is not None
        assert 0 < float(sim.thermal.lit.sum())
    for n, slack in ((2, []), (3, ["numerics.migration_slack_over_skin=0"])):
        out = tmp_path / f"r{n}.npz"
        r = mpirun(n, ["-m", "parallel.driver", str(case), str(K), str(out)] + ov + slack)
        assert r.returncode == 0, r.stderr[-3000:]
        g = np.load(out)
        assert int(g["step"]) == K and float(g["t"]) == pytest.approx(sim.t, rel=1e-12)
        assert np.array_equal(g["state_id"], ref["id"])  # every particle once: none lost or doubled
        assert g["state_m"].sum() == ref["m"].sum()
        if slack:
            assert int(g["kept"]) == 0
            if which not in ("thermal", "stall", "resultant", "wide"):  # (few rebuilds: the drop, the wide scene)
                assert int(g["migrations"]) >= 2  # particles did cross the slab boundaries
        elif which in ("fluid", "deposition"):  # rebuilds that kept the decomposition (its ghosts)
            assert int(g["kept"]) >= 1, (int(g["kept"]), int(g["migrations"]))
        for k in ("x", "v", "rho", "T"):
            if np.abs(ref[k]).max() > 0:
                assert rel(g[f"state_{k}"], ref[k]) < 1e-10, (n, k, rel(g[f"state_{k}"], ref[k]))


# the deposition scene with a cold half, checkpointed at the end of a step in which a particle
# melted: the phase change re-selects the pairs after the conduction evaluation, which drops the
# lazily built conduction normalisation (zeta) until the next evaluation, so the checkpoint does
# not carry it (b14e316 restored it from the freshly built t = 0 state: zeta = 0 on rows made
# active since, infinite conduction; at full size a blow-up ~20 steps after the restart).
# The substrate is long enough that rank 0's slab and halo hold no wire particle: 8848d6c gave
# each rank only the velocities of the bodies it held, so rank 0 failed when the feed set the
# wire's velocity, and a checkpoint (rank 0's copy) lost the wire's row
COLD_HALF = (ROOT / "cases" / "perpendicular_350W",
             ["scene.dx_m=2.5e-4", "scene.substrate_size_m=[14.0e-3, 3.0e-3, 1.0e-3]", "scene.wire_offset_m=1.25e-3",
              "scene.wire_length_m=1.0e-3", "scene.wire_gap_m=0.5e-3", "scene.wire_feed_m_s=0.05",
              "numerics.conduction_window=0.0"], 0)


@pytest.mark.parametrize("which", ["fluid", "deposition", "cold_half"])
def test_checkpoint_restarts_on_other_rank_counts(tmp_path, which):
    """A checkpoint written by 2 ranks restarts on 1 and on 3 (2 for the cold half) and
    continues to the state of the uninterrupted run (the deposition scene: a wire layer
    enters in each half)."""
    from torchsph.io.checkpoint import read

    case, ov, _ = {"fluid": FLUID, "deposition": DEPOSITION, "cold_half": COLD_HALF}[which]
    K = {"fluid": 120, "deposition": 100, "cold_half": 88}[which]
    sets = [a for o in ov for a in ("--set", o)]
    base = ["-m", "torchsph", str(case), "--quiet"] + sets
    r = mpirun(2, base + ["--steps", str(K), "--out", str(tmp_path / "full")])
    assert r.returncode == 0, r.stderr[-3000:]
    r = mpirun(2, base + ["--steps", str(K // 2), "--out", str(tmp_path / "half")])
    assert r.returncode == 0, r.stderr[-3000:]
    ck = tmp_path / "half" / "checkpoint.pt"
    if which == "cold_half":  # what this case must exercise: a cache one rank had not built
        d = read(ck)
        assert "th.zeta_cache" not in d["arrays"] and "th.zeta_ok" in d["arrays"], sorted(d["arrays"])
    full = read_snapshot(sorted((tmp_path / "full").glob("snap_*.h5"))[-1])
    r3 = mpirun(2 if which == "cold_half" else 3, base + ["--restart", str(ck), "--steps", str(K // 2), "--out",
                                                          str(tmp_path / "r3")])
    assert r3.returncode == 0, r3.stderr[-3000:]
    r1 = subprocess.run([sys.executable] + base + ["--restart", str(ck), "--steps", str(K // 2), "--out",
                                                   str(tmp_path / "r1")], cwd=ROOT, env=ENV, capture_output=True,
                        text=True, timeout=600)
    assert r1.returncode == 0, r1.stderr[-3000:]
    for d in ("r3", "r1"):
        s = read_snapshot(sorted((tmp_path / d).glob("snap_*.h5"))[-1])
        assert s["step"] == full["step"] == K
        assert np.array_equal(s["id"], full["id"])
        for k in ("position", "velocity", "density", "temperature"):
            assert rel(s[k], full[k]) < 1e-10, (d, k)


def test_a_one_process_checkpoint_restarts_on_two_ranks(tmp_path):
    """A run started in one process continues on 2 ranks from its checkpoint (the deposition
    scene: fed wire, active set, melt) and reaches the state of the uninterrupted
    one-process run."""
    case, ov, _ = DEPOSITION
    K = 100
    sets = [a for o in ov for a in ("--set", o)]
    base = [sys.executable, "-m", "torchsph", str(case), "--quiet"] + sets
    for d, steps in (("full", K), ("half", K // 2)):
        r = subprocess.run(base + ["--steps", str(steps), "--out", str(tmp_path / d)], cwd=ROOT, env=ENV,
                           capture_output=True, text=True, timeout=600)
        assert r.returncode == 0, r.stderr[-3000:]
    r2 = mpirun(2, base[1:] + ["--restart", str(tmp_path / "half" / "checkpoint.pt"), "--steps", str(K // 2),
                               "--out", str(tmp_path / "r2")])
    assert r2.returncode == 0, r2.stderr[-3000:]
    full = read_snapshot(sorted((tmp_path / "full").glob("snap_*.h5"))[-1])
    s = read_snapshot(sorted((tmp_path / "r2").glob("snap_*.h5"))[-1])
    assert s["step"] == full["step"] == K
    assert np.array_equal(s["id"], full["id"])
    for k in ("position", "velocity", "density", "temperature"):
        assert rel(s[k], full[k]) < 1e-10, k


def test_a_branch_on_two_ranks_equals_the_branch_in_one_process(tmp_path):
    """``--branch`` (a checkpoint's state with other physics: the beams at 300 W, no
    Marangoni force) from a one-process checkpoint of the deposition scene, on 2 ranks and in
    one process: the same state after 50 steps, and the same changes recorded."""
    case, ov, _ = DEPOSITION
    sets = [a for o in ov for a in ("--set", o)]
    base = [sys.executable, "-m", "torchsph", str(case), "--quiet"] + sets
    r = subprocess.run(base + ["--steps", "50", "--out", str(tmp_path / "a")], cwd=ROOT, env=ENV,
                       capture_output=True, text=True, timeout=600)
    assert r.returncode == 0, r.stderr[-3000:]
    what = ["--branch", str(tmp_path / "a" / "checkpoint.pt"), "--steps", "50", "--set", "scene.source_power_W=300.0",
            "--set", "surface.marangoni=false"]
    r1 = subprocess.run(base + what + ["--out", str(tmp_path / "one")], cwd=ROOT, env=ENV, capture_output=True,
                        text=True, timeout=600)
    assert r1.returncode == 0, r1.stderr[-3000:]
    r2 = mpirun(2, base[1:] + what + ["--out", str(tmp_path / "two")])
    assert r2.returncode == 0, r2.stderr[-3000:]
    one = read_snapshot(sorted((tmp_path / "one").glob("snap_*.h5"))[-1])
    two = read_snapshot(sorted((tmp_path / "two").glob("snap_*.h5"))[-1])
    assert one["step"] == two["step"] == 100 and np.array_equal(one["id"], two["id"])
    for k in ("position", "velocity", "density", "temperature"):
        assert rel(two[k], one[k]) < 1e-10, k
    b1, b2 = (json.loads((tmp_path / d / "summary.json").read_text())["branch"] for d in ("one", "two"))
    assert b1 == b2 and "surface.marangoni = True in the checkpoint, False now" in b1["changes"]
    assert "scene.source_power_W = 350.0 in the checkpoint, 300.0 now" in b1["changes"]


def test_an_exception_on_one_rank_ends_the_run(tmp_path):
    case, ov, _ = FLUID
    sets = [a for o in ov for a in ("--set", o)]
    t0 = time.time()
    r = mpirun(2, ["-m", "torchsph", str(case), "--quiet", "--steps", "200", "--out", str(tmp_path)] + sets,
               env={**ENV, "TORCHSPH_TEST_RAISE_RANK": "1"}, timeout=120)
    assert r.returncode != 0
    assert time.time() - t0 < 30
    assert "rank 1/2" in r.stderr and "test failure injected on rank 1" in r.stderr


def test_particles_leaving_the_scene_go_on_every_rank(tmp_path):
    """Drops flung out of the deposition scene (tests/escape_driver.py) are removed on 2 and 3
    ranks as in one process: owned rows and ghost copies go together, the send / receive
    lists follow, the state gathered by id equals the single-process one to 1e-10, and the
    escaped mass and the energy balance agree."""
    from escape_driver import run

    case, ov = DEPOSITION[0], DEPOSITION[1]
    sim = run(case, 100, 150, ov)
    s = sim.state
    o = s.id.argsort()
    assert sim.escape.n == 6
    for n in (2, 3):
        out = tmp_path / f"e{n}.npz"
        r = mpirun(n, [str(ROOT / "tests" / "escape_driver.py"), str(case), "100", "150", str(out)] + ov)
        assert r.returncode == 0, r.stderr[-3000:]
        g = np.load(out)
        assert np.array_equal(g["state_id"], s.id[o].numpy())
        assert g["escaped"][0] == 6 and g["escaped"][1] == pytest.approx(sim.escape.kg, rel=1e-12)
        assert float(g["residual"]) < 1e-12
        for k in ("x", "v", "T"):
            ref = getattr(s, k)[o].numpy()
            assert rel(g[f"state_{k}"], ref) < 1e-10, (n, k, rel(g[f"state_{k}"], ref))


def test_the_slab_bound_of_a_uniform_bar():
    """scripts/tools/slab_bound.py: on a uniform bar of length L the best cut is the middle,
    each rank computing L/2 + halo, so 2 ranks gain at most L / (L/2 + halo); idle particles
    (weight 0) change nothing."""
    sys.path.insert(0, str(ROOT / "scripts" / "tools"))
    from slab_bound import best_cut

    x = np.linspace(0.0, 10.0, 10001)
    w = np.ones_like(x)
    for halo in (0.5, 2.0):
        b, c, lo, hi = best_cut(x, w, halo, cuts=2001)
        assert c == pytest.approx(5.0, abs=5e-3) and b == pytest.approx(10.0 / (5.0 + halo), rel=1e-3)
    idle = np.concatenate([x, np.linspace(-30.0, 0.0, 5000)])
    b2, *_ = best_cut(idle, np.concatenate([w, np.zeros(5000)]), 2.0, cuts=2001)
    assert b2 == pytest.approx(10.0 / 7.0, rel=1e-3)
