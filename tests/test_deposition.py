"""Deposition scene: the fed wire, the sources, the active set, restarts, case errors."""
import math
from pathlib import Path

import pytest
import torch
from escape_driver import fling

from torchsph.core.state import Phase
from torchsph.io import checkpoint as ckpt
from torchsph.io.config import CaseError, load_case
from torchsph.post.analysis import nominal_wire_fed_kg
from torchsph.run.build import make_simulation
from torchsph.scenes.builders import case_beams
from torchsph.scenes.deposition import WIRE, measure
from torchsph.step.loop import run_steps

ROOT = Path(__file__).resolve().parents[1]
CASE = ROOT / "cases" / "perpendicular_350W"

# a small, fast variant of the production case: every physics term of the scene is on
SMALL = ["scene.dx_m=2.5e-4", "scene.substrate_size_m=[3.0e-3, 3.0e-3, 1.0e-3]",
         "scene.wire_offset_m=1.5e-3", "scene.wire_length_m=1.0e-3", "scene.wire_gap_m=0.5e-3"]


def small(*extra):
    return load_case(CASE, SMALL + list(extra))[1]


def test_wire_feed_is_a_continuous_lattice_with_the_exact_mass_flux():
    """No sources: the rigid wire advances and new layers enter at its top. After 25 layers'
    worth of feed the wire's layers are dx apart with no gap or overlap, ids are unique and
    the fed mass is rho0 (pi d^2 / 4) V t to within one layer (the particles' masses carry
    the disc area exactly, not the lattice's)."""
    cfg = small("scene.source_layout=\"none\"", "scene.wire_feed_m_s=0.3", "scene.wire_gap_m=8.0e-3")
    scene, sim = make_simulation(cfg)
    sc = cfg["scene"]
    dx, V = sc["dx_m"], sc["wire_feed_m_s"]
    n0 = sim.state.n
    run_steps(sim, t_end=25 * dx / V + 1e-7)
    s = sim.state
    wire = s.body == WIRE
    z = torch.unique(torch.round(s.x[wire, 2] / (1e-3 * dx)))
    gaps = torch.diff(z) * 1e-3 * dx
    assert gaps.numel() >= 4 + 25 - 1
    assert float((gaps - dx).abs().max()) < 1e-6 * dx  # a continuous lattice
    assert s.id.unique().numel() == s.n
    per_layer = int(wire.sum()) // z.numel()
    assert s.n - n0 == 25 * per_layer
    info = measure(s, scene.info, sim.t, sc["substrate_velocity_m_s"][0], V, cfg["fluid"]["rho0_kg_m3"],
                   cfg["thermal"]["liquidus_K"], dx)
    layer_mass = cfg["fluid"]["rho0_kg_m3"] * math.pi * sc["wire_diameter_m"] ** 2 / 4 * dx
    assert abs(info["wire_inserted_kg"] - info["wire_fed_kg"]) <= layer_mass * (1 + 1e-9)
    assert abs(info["wire_inserted_kg"] / layer_mass - 25) < 1e-9


def test_deposit_counts_material_on_the_substrate_and_spatter_apart():
    """measure(): wire material that has left the wire counts in the deposit where it lies over
    the substrate, and as off_substrate_kg (not deposit) where it was flung beside it."""
    from torchsph.core.state import Phase

    cfg = small("scene.source_layout=\"none\"")
    scene, sim = make_simulation(cfg)
    s, dx = sim.state, cfg["scene"]["dx_m"]
    args = (0.015, 0.03, cfg["fluid"]["rho0_kg_m3"], 1753.15, dx)
    base = measure(s, scene.info, 0.0, *args)
    drop = torch.nonzero(s.body == WIRE).squeeze(1)[:5]
    s.phase[drop] = int(Phase.FLUID)
    s.body[drop] = 0
    m_drop = float(s.m[drop].sum())
    s.x[drop] = torch.tensor([-0.5e-3, 0.0, 0.2e-3], dtype=s.dtype)  # a drop on the bead
    on = measure(s, scene.info, 0.0, *args)
    assert on["deposit_kg"] - base["deposit_kg"] == pytest.approx(m_drop, rel=1e-9)
    assert on["off_substrate_kg"] == 0.0
    s.x[drop, 1] = 20e-3  # flung 20 mm aside
    off = measure(s, scene.info, 0.0, *args)
    assert off["deposit_kg"] == pytest.approx(base["deposit_kg"], abs=1e-12 * m_drop)
    assert off["off_substrate_kg"] == pytest.approx(m_drop, rel=1e-12)


def test_feed_can_start_late():
    """wire_feed_start_s: the wire rests until then (the sources preheat its tip), then moves
    at the feed speed; fed mass counts from the start."""
    cfg = small("scene.source_layout=\"none\"", "scene.wire_feed_m_s=0.3", "scene.wire_gap_m=8.0e-3",
                "scene.wire_feed_start_s=0.005")
    scene, sim = make_simulation(cfg)
    run_steps(sim, t_end=0.004)
    wire = sim.state.body == WIRE
    assert float(sim.state.x[wire, 2].min()) == pytest.approx(8.0e-3 + 1.25e-4, abs=1e-12)
    run_steps(sim, t_end=0.015)
    assert float(sim.state.x[wire.nonzero()[0], 2]) == pytest.approx(8.0e-3 + 1.25e-4 - 0.3 * 0.010, abs=0.3 * 1.6e-3)
    sc = cfg["scene"]
    info = measure(sim.state, scene.info, sim.t, 0.0, 0.3, cfg["fluid"]["rho0_kg_m3"], 1753.15, sc["dx_m"])
    # the fed length is the distance the wire moved (it starts with the first step after
    # wire_feed_start_s), so it matches the feed clock to within one step
    rhoA = cfg["fluid"]["rho0_kg_m3"] * math.pi * 1.2e-3**2 / 4
    moved = 8.0e-3 + 1.25e-4 - float(sim.state.x[wire.nonzero()[0], 2])
    assert info["wire_fed_kg"] == pytest.approx(rhoA * moved, rel=1e-9)
    assert info["wire_fed_kg"] == pytest.approx(rhoA * 0.3 * (sim.t - 0.005), abs=rhoA * 0.3 * 2 * sim.choose_dt()[0])
    # the studies' nominal feed (torchsph.post.analysis) is what a feed that never waits brings, late start included
    assert info["wire_fed_kg"] == pytest.approx(nominal_wire_fed_kg(cfg, sim.t), abs=rhoA * 0.3 * 2 * sim.choose_dt()[0])
    assert nominal_wire_fed_kg(cfg, 0.004) == 0.0


def test_unmelted_wire_reaching_the_substrate_stops_with_a_diagnosis():
    from torchsph.step.simulation import SimulationError

    cfg = small("scene.source_layout=\"none\"", "scene.wire_feed_m_s=0.3", "scene.wire_gap_m=0.5e-3",
                "scene.wire_stall=false")
    _, sim = make_simulation(cfg)
    with pytest.raises(SimulationError, match="solid wire reached into the substrate .* the sources do not melt"):
        run_steps(sim, t_end=0.01)
    assert sim.t < 0.5e-3 / 0.3  # stopped in the step that took it below the top


def test_with_wire_stall_the_feed_waits_on_solid_substrate_and_goes_on_once_the_tip_melts():
    """scene.wire_stall: unmelted wire that reaches solid substrate rests there (no stop, no
    overlap growing), the fed length stops at the distance the wire moved, the stalled time is
    counted; once the touching layer has melted the feed goes on at the feed speed."""
    from torchsph.core.state import Phase

    V, gap = 0.03, 0.1e-3  # V dt < dx / 4 (no sources: dt is the heating limit, ~1.5 ms)
    cfg = small("scene.source_layout=\"none\"", f"scene.wire_feed_m_s={V}", f"scene.wire_gap_m={gap}",
                "scene.wire_stall=true")
    scene, sim = make_simulation(cfg)
    feeder, dx = scene.info["feeder"], cfg["scene"]["dx_m"]
    run_steps(sim, t_end=0.02)  # 0.6 mm of feed on the clock: the wire met the substrate at ~5 ms
    s = sim.state
    wire = (s.body == WIRE) & (s.phase == Phase.SOLID)
    tip = float(s.x[wire, 2].min())
    assert feeder.stalled and feeder.n_stalls == 1
    # it rests on the top face: stopped in the step that took its centre below half a spacing up
    assert 0.5 * dx - 2 * V * sim.choose_dt()[0] < tip < 0.5 * dx
    assert feeder.fed == pytest.approx(gap + 0.5 * dx - tip, rel=1e-9)  # the distance it moved
    assert feeder.stall_s == pytest.approx(0.02 - feeder.fed / V, abs=2 * sim.choose_dt()[0])
    assert bool((s.v[wire, 2] == 0).all())
    info = measure(s, scene.info, sim.t, 0.015, V, cfg["fluid"]["rho0_kg_m3"], 1753.15, dx)
    assert info["wire_stalled_s"] == feeder.stall_s and info["wire_stalls"] == 1
    # the wait is booked to the rule that began it: unmelted wire on solid substrate
    assert info["wire_stalled_by"] == {"unmelted": {"s": feeder.stall_s, "waits": 1}, "squeezed": {"s": 0.0, "waits": 0}}
    assert info["wire_fed_kg"] == pytest.approx(cfg["fluid"]["rho0_kg_m3"] * scene.info["wire_area"] * feeder.fed)
    run_steps(sim, steps=20)
    assert float(s.x[(s.body == WIRE) & (s.phase == Phase.SOLID), 2].min()) == tip  # still resting
    # melt the bottom layer: the wire is no longer blocked and moves on (hot enough to stay
    # above the liquidus through the step's conduction into the cold wire: the step decides
    # melting on its end temperatures)
    bottom = wire & (s.x[:, 2] < tip + 0.5 * dx)
    s.T = torch.where(bottom, torch.full_like(s.T, 2500.0), s.T)
    s.T_peak = torch.maximum(s.T_peak, s.T)
    fed0 = feeder.fed
    run_steps(sim, steps=3)
    assert not feeder.stalled
    assert bool((s.phase[bottom] == Phase.FLUID).all())
    assert feeder.fed > fed0
    wire = (s.body == WIRE) & (s.phase == Phase.SOLID)
    assert bool((s.v[wire, 2] == -V).all())


def test_solid_wire_may_dip_into_the_melt_pool_but_not_into_solid_substrate():
    """The wire is fed into the pool: solid wire below the substrate's top is allowed where
    the substrate around it is melt, and also beside the rigid wall of that pool; it stops
    the run (with the diagnosis) as soon as rigid substrate is within one spacing below it."""
    from torchsph.core.state import Phase
    from torchsph.step.simulation import SimulationError

    cfg = small("scene.source_layout=\"none\"", "scene.wire_gap_m=0.0", "scene.wire_stall=false")
    scene, sim = make_simulation(cfg)
    s, dx = sim.state, cfg["scene"]["dx_m"]
    feeder = scene.info["feeder"]
    wire = s.body == WIRE
    s.x[wire, 2] -= 2.0 * dx  # the two bottom layers now lie below the top face
    assert int((wire & (s.x[:, 2] < -0.5 * dx)).sum()) > 0
    r = s.x[:, :2].norm(dim=1)
    pool = ~wire & (r < 1.0e-3) & (s.x[:, 2] > -0.75e-3)  # a melt pool around and below the tip
    s.phase = torch.where(pool, torch.full_like(s.phase, int(Phase.FLUID)), s.phase)
    feeder.check_contact(sim)  # in the melt: no stop
    assert not bool(feeder.touches_solid_substrate(s).any())
    side = ~wire & (r >= 1.0e-3) & (r < 1.0e-3 + dx) & (s.x[:, 2] > -0.75e-3)  # the pool's wall, beside
    rim = float(r[wire].max())
    s.x[side, :2] *= (rim + 0.75 * dx) / r[side].unsqueeze(1)  # now 3/4 of a spacing from the wire's rim
    assert float(torch.cdist(s.x[side], s.x[wire]).min()) < dx
    feeder.check_contact(sim)  # rigid solid beside the wire is not in its way
    floor = ~wire & (s.phase != int(Phase.FLUID))
    s.x[wire, 2] -= 1.2 * dx  # its bottom layer 0.8 spacing above the pool's solid floor: in its way
    assert float(torch.cdist(s.x[wire], s.x[floor]).min()) > 0.5 * dx  # not overlapping
    assert bool(feeder.touches_solid_substrate(s).any())
    s.x[wire, 2] -= 0.8 * dx  # now its bottom layer is on the pool's solid floor
    touch = feeder.touches_solid_substrate(s)
    assert bool(touch.any()) and float(s.x[touch, 2].max()) < -0.75e-3 + dx
    with pytest.raises(SimulationError, match="solid wire reached into the substrate"):
        feeder.check_contact(sim)


def test_refrozen_wire_material_welds_to_the_substrate_and_unmelted_wire_still_stops():
    """wire_contact = "weld": wire-body material that has melted before (peak temperature
    above the liquidus; here the outer ring of the bottom layer, marked so by hand) joins the
    substrate where it reaches into it and moves with it; its mass is counted once and the
    total mass is unchanged. The never-melted core behind it still stops the run."""
    from torchsph.scenes.deposition import SUBSTRATE
    from torchsph.step.simulation import SimulationError

    cfg = small("scene.source_layout=\"none\"", "scene.wire_feed_m_s=0.3", "scene.wire_gap_m=0.25e-3",
                "scene.substrate_velocity_m_s=[0.015, 0.0, 0.0]", "scene.wire_stall=false")
    scene, sim = make_simulation(cfg)
    s = sim.state
    wire = s.body == WIRE
    r = s.x[:, :2].norm(dim=1)
    T_L = cfg["thermal"]["liquidus_K"]
    zb = float(s.x[wire, 2].min())
    collar = wire & (r > 0.3e-3) & (s.x[:, 2] < zb + 1.25e-4)  # the bottom layer's outer ring
    s.T_peak = torch.where(collar, torch.full_like(s.T_peak, T_L + 100.0), s.T_peak)
    m0, n0, ids = float(s.m.sum()), s.n, s.id[collar].clone()
    assert ids.numel() >= 8
    with pytest.raises(SimulationError, match="solid wire reached into the substrate"):
        run_steps(sim, t_end=0.01)
    s = sim.state
    welded = torch.isin(s.id, ids)
    feeder = scene.info["feeder"]
    assert feeder.n_welded == int(welded.sum()) == ids.numel()
    assert feeder.welded_kg == pytest.approx(float(s.m[welded].sum()), rel=1e-12)
    assert bool((s.body[welded] == SUBSTRATE).all())
    assert torch.allclose(s.v[welded], torch.tensor([0.015, 0.0, 0.0], dtype=s.dtype))
    assert float(s.m[s.id < n0].sum()) == pytest.approx(m0, rel=1e-12)  # ids 0..n0-1 at the start
    assert s.id.unique().numel() == s.n
    assert float(s.x[welded, 2].max()) < 0.5 * 2.5e-4  # welded once they reached the substrate's top


def test_sources_are_aimed_at_the_tip_in_the_declared_layout():
    for layout, axis in (("along", 0), ("perpendicular", 1)):
        cfg = small(f"scene.source_layout=\"{layout}\"", "scene.source_azimuth_deg=30.0")
        beams = case_beams(cfg)
        assert len(beams) == 2 and "beam" not in cfg  # made by the scene, not written into the case
        for b in beams:
            e = b["direction"]
            assert abs(math.degrees(math.acos(-e[2])) - 30.0) < 1e-9  # tilt from the vertical
            assert abs(e[1 - axis]) < 1e-15 and abs(abs(e[axis]) - 0.5) < 1e-12
            assert b["aim_m"] == [0.0, 0.0, cfg["scene"]["source_aim_height_m"]]
        assert beams[0]["direction"][axis] == -beams[1]["direction"][axis]  # opposite sides


def _run_pair(cfg, steps):
    torch.manual_seed(0)
    _, a = make_simulation(cfg)
    run_steps(a, steps=steps)
    return a


def test_active_set_error_stays_below_its_tolerance():
    """A 300 W beam on a plate for 40 ms with and without the active set: temperatures
    differ by less than the tolerance (the bound of torchsph/step/active.py) while a fraction of
    the particles does the work."""
    base = ["run.t_end_s=0.04", "scene.size_m=[16.0e-3, 12.0e-3, 1.5e-3]", "scene.dx_m=2.5e-4"]
    _, cfg_full = load_case(ROOT / "cases" / "beam_plate", base + ["numerics.skip_cold_solid=false"])
    _, cfg_skip = load_case(ROOT / "cases" / "beam_plate", base + ["numerics.active_tolerance_K=0.5"])
    _, full = make_simulation(cfg_full)
    _, skip = make_simulation(cfg_skip)
    run_steps(full, t_end=0.04)
    run_steps(skip, t_end=0.04)
    assert full.step == skip.step
    frac = skip.plan.report()["conduction"]["particles"]
    assert frac < 0.7, frac
    err = float((full.state.T - skip.state.T).abs().max())
    assert err < 0.5, err
    assert float(full.state.T.max()) > 1000.0  # the beam did heat the plate
    # the heat the halo did not take up is measured, and small next to the absorbed energy
    e = skip.energy_balance()
    assert abs(e["conduction_J"]) < 1e-3 * e["beam_J"] and e["residual_rel"] < 1e-6


def test_deposition_restart_is_bit_for_bit(tmp_path):
    """K steps == K/2 + restart + K/2 in float64 on the deposition scene with sources,
    a wire fed fast enough that layers enter in both halves, the active set, and partial
    neighbour rebuilds in both halves."""
    cfg = small("scene.wire_feed_m_s=0.5", "scene.wire_gap_m=2.5e-3")
    K = 24
    ref = _run_pair(cfg, K)
    h = cfg["scene"]["dx_m"] / cfg["scene"]["wire_feed_m_s"]
    assert ref.t > 2 * h  # layers entered
    torch.manual_seed(0)
    _, a = make_simulation(cfg)
    run_steps(a, steps=K // 2)
    path = tmp_path / "c.pt"
    ckpt.save(a, path, ckpt.config_hash(cfg), {"feeder": a.feeder.state_dict()})
    _, b = make_simulation(cfg)
    extra = ckpt.restore(b, ckpt.load(path), cfg)
    b.feeder.load_state_dict(extra["feeder"])
    run_steps(b, steps=K - K // 2)
    assert b.state.n == ref.state.n > a.state.n - 1
    # partial neighbour rebuilds on both sides of the restart (the checkpoint holds the body set)
    assert 0 < a.nl.n_partial < b.nl.n_partial
    for f in ("x", "v", "rho", "T", "T_peak"):
        assert torch.equal(getattr(b.state, f), getattr(ref.state, f)), f
    assert torch.equal(b.state.phase, ref.state.phase) and torch.equal(b.state.id, ref.state.id)


@pytest.mark.parametrize("override, msg", [
    ("scene.substrate_velocity_m_s=[0.0, 0.01, 0.0]", "substrate_velocity_m_s"),
    ("scene.dx_m=1.0e-3", "dx_m = 0.001: must be <= wire_diameter_m / 2"),
    ("thermal.phase_change=false", "phase_change"),
    ("scene.source_layout=\"diagonal\"", "source_layout"),
    ("scene.source_azimuth_deg=95.0", "source_azimuth_deg = 95.0: must be a number >= 0 and < 90"),
])
def test_malformed_deposition_cases(override, msg):
    with pytest.raises(CaseError, match=msg.replace("[", r"\[").replace("(", r"\(")):
        load_case(CASE, [override])


def test_preview_needs_a_preview_table(tmp_path):
    case = tmp_path / "c"
    case.mkdir()
    (case / "case.toml").write_text((ROOT / "cases" / "beam_plate" / "case.toml").read_text())
    with pytest.raises(CaseError, match="no \\[preview\\] table"):
        load_case(case, preview=True)
    _, cfg = load_case(CASE, preview=True)
    assert cfg["scene"]["dx_m"] == 2.5e-4 and cfg["run"]["t_end_s"] == 0.06


def test_rigid_geometry_kept_across_rebuilds_equals_recomputing_it():
    """Zeta, the surface area and the normal are recomputed after a neighbour rebuild only
    where they can have changed (torchsph/physics/thermal.py, "Cached geometry"): with melt on the
    moving substrate and wire layers entering, at every rebuild of the run what is kept and
    recomputed equals computing every row afresh to round-off, while a good part of the rows
    is kept. (Before new layers invalidated it, a wire particle that had been on the top
    face kept zeta = 1 where 1.0006 was due; before melt walls were excluded, 5e-2 was off.)"""
    from torchsph.core.state import Phase

    cfg = small("scene.wire_gap_m=1.5e-3", "scene.wire_feed_m_s=0.1")
    _, sim = make_simulation(cfg)
    th = sim.thermal
    fns = {"zeta": th.zeta, "area": th.surface_area}
    worst, kept = {"zeta": 0.0, "area": 0.0, "normal": 0.0}, []

    def checked(name):
        def fn(state):
            partial = th.zeta_prev if name == "zeta" else th.area_prev
            v = fns[name](state)
            if partial is not None:
                ok, n = getattr(th, f"{name}_ok"), th.normal
                kept.append(int((ok & th.rigid).sum()) / th.rows.numel())
                setattr(th, f"{name}_prev", None)  # the same rows, computed afresh
                full = fns[name](state)
                scale = 1.0 if name == "zeta" else float(full.abs().max())
                worst[name] = max(worst[name], float((v - full).abs().max()) / scale)
                if name == "area":
                    worst["normal"] = max(worst["normal"], float((n - th.normal).abs().max()))
                    th.normal = n
                setattr(th, f"{name}_ok", ok)
            return v
        return fn

    th.zeta, th.surface_area = checked("zeta"), checked("area")
    run_steps(sim, steps=300)
    assert sim.feeder.n_fed >= 1 and int((sim.state.phase == Phase.FLUID).sum()) > 0
    assert len(kept) > 5 and max(kept) > 0.3, kept
    assert worst["zeta"] < 1e-12 and worst["area"] < 1e-12 and worst["normal"] < 1e-9, worst


def test_two_selections_before_an_evaluation_keep_the_cached_geometry():
    """A phase change selects the pairs again at a step's end; when the next step starts with a
    neighbour rebuild, its selection comes before any evaluation of zeta and the area. What the
    first selection kept still holds where it says so: zeta and the area are made for the rows
    that can have changed only (before, every row again: 0.6-2 s of the full scene's zeta),
    and they equal making every row afresh to round-off."""
    cfg = small("scene.wire_gap_m=1.5e-3", "scene.wire_feed_m_s=0.1")
    _, sim = make_simulation(cfg)
    run_steps(sim, steps=40)
    th = sim.thermal
    sim.select_pairs()  # as at a phase change
    sim.refresh_pairs(force=True)  # then a rebuild, before any evaluation
    assert th.zeta_prev is not None and th.area_prev is not None
    made = int((~th.zeta_ok.index_select(0, th.rows)).sum())  # the rows zeta is made for
    assert 0 < made < th.rows.numel(), (made, th.rows.numel())
    ok_z, ok_a, normal = th.zeta_ok, th.area_ok, th.normal
    z, area = th.zeta(sim.state), th.surface_area(sim.state)
    kept_normal = th.normal
    th.zeta_prev = th.area_prev = th.normal_prev = None  # the same rows, computed afresh
    th.zeta_ok, th.area_ok, th.normal = ok_z, ok_a, normal
    z_full, area_full = th.zeta(sim.state), th.surface_area(sim.state)
    assert float((z - z_full).abs().max()) < 1e-12
    assert float((area - area_full).abs().max()) < 1e-12 * float(area_full.abs().max())
    assert float((kept_normal - th.normal).abs().max()) < 1e-9


def test_a_rebuild_between_steps_evaluates_the_rates_on_the_new_pairs():
    """A tool that builds the neighbour table between steps (after a restart, a state set from
    outside) calls ``Simulation.rebuild``: the pairs, then the accelerations on them, so that
    the next step's continuity reads the new table's pair geometry. Its steps then equal those
    of a run that did not rebuild (the pairs in the support are the same; only their order and
    the skin's padding differ: round-off). A bare ``refresh_pairs`` leaves the last momentum
    evaluation's geometry, made on the old table, and the next step stops with a clear error
    instead of pairing one table's geometry with another's neighbours (before, it ran on: a
    wrong drho/dt where the shapes agreed, a shape error where they did not)."""
    cfg = small("scene.wire_gap_m=1.5e-3", "scene.wire_feed_m_s=0.1")
    sims = [make_simulation(cfg)[1] for _ in range(3)]
    for sim in sims:
        run_steps(sim, steps=30)
    kept, rebuilt, bare = sims
    assert int((kept.state.phase == Phase.FLUID).sum()) > 0  # melt: the continuity sum has rows
    builds = rebuilt.nl.n_builds
    rebuilt.rebuild()
    assert rebuilt.nl.n_builds == builds + 1
    run_steps(kept, steps=5)
    run_steps(rebuilt, steps=5)
    for k in ("x", "v", "rho", "T"):
        a, b = getattr(kept.state, k), getattr(rebuilt.state, k)
        assert torch.allclose(a, b, rtol=1e-9, atol=1e-9 * float(a.abs().max())), k
    bare.refresh_pairs(force=True)
    with pytest.raises(RuntimeError, match="rebuild"):
        run_steps(bare, steps=1)


@pytest.mark.parametrize("heated", [False, True], ids=["cold_solid_left_out", "every_particle_working"])
def test_the_rebuild_check_on_its_few_rows_sees_the_largest_displacement(heated):
    """The neighbour rebuild is decided on the fluid, the walls, the particles whose rigid body
    changed since the last build and one particle per rigid body, a cold one where it has one
    (torchsph.step.bookkeeping.moving_rows), not on every particle: at every step of a run with melt,
    freezing and a fed wire, every particle left out of them has moved since the last build as
    one of them has (to round-off: it moved with a body they represent), so the largest
    displacement is theirs, while they are far fewer. Once with a longer substrate and wire than
    the small scene's, so that cold solid is left out of the work; once with a tolerance that
    puts every particle in the work, so that no body has a cold particle (late in the full
    scene: the rows stand for a body at a working particle, chosen again at each phase change)."""
    over = ("numerics.active_tolerance_K=1e-9",) if heated else (
        "scene.substrate_size_m=[10.0e-3, 3.0e-3, 1.0e-3]", "scene.wire_length_m=3.0e-3")
    cfg = small("scene.wire_gap_m=1.5e-3", "scene.wire_feed_m_s=0.1", *over)
    _, sim = make_simulation(cfg)
    lonely = 0
    worst, fewer, phases, checked, changed = 0.0, 0, set(), 0, 0
    for _ in range(300):
        s, ref = sim.state, sim.nl.x_ref
        rows = sim.moving_rows()
        if rows is not None and ref.shape == s.x.shape:
            d = sim.domain.minimum_image(s.x - ref)
            out = torch.ones(s.n, dtype=torch.bool).index_fill_(0, rows, False)
            # each left-out particle's displacement against the nearest of the rows' (m)
            gap = torch.cdist(d[out], d.index_select(0, rows), compute_mode="donot_use_mm_for_euclid_dist").min(1).values  # (the matmul form cancels: 1e-12 m at 1e-4 m)
            worst = max(worst, float(gap.max()))
            fewer += rows.numel() < 0.5 * int(sim.active_set.work.sum())
            changed += rows.numel() > sim.moving_for[2].numel()  # rows that left their body since the build
            no_cold = sim.moving_for[5]  # the bodies without a cold particle
            lonely += no_cold is not None and bool(no_cold[int(torch.bincount(s.body).argmax())])  # the substrate
            checked += 1
        phases.add(id(s.phase))
        run_steps(sim, steps=1)
    assert int((sim.state.phase == Phase.FLUID).sum()) > 0 and sim.feeder.n_fed >= 1
    assert len(phases) > 3  # the phase array was replaced: melting or freezing between builds
    assert checked > 250 and fewer > 0.9 * checked and changed > 0, (checked, fewer, changed)
    assert (lonely > 0.9 * checked) if heated else lonely == 0, lonely
    assert worst < 1e-8 * sim.nl.skin, (worst, sim.nl.skin)


def test_reused_rate_arrays_give_the_same_run_as_fresh_ones():
    """dv/dt, drho/dt and dh/dt are written into arrays reused from step to step, zeroing only
    the rows written the step before (torchsph.physics.fluid.Embedded): a run with melt, surface
    forces, the contact term and a fed wire is the same bit for bit as one that makes every
    rate array afresh."""
    cfg = small("scene.wire_gap_m=1.5e-3", "scene.wire_feed_m_s=0.1")
    _, reused = make_simulation(cfg)
    _, fresh = make_simulation(cfg)
    fresh.outs.clear()  # (the fluid model reads the same dict)
    assert reused.outs and fresh.fluid_model.outs == {}
    run_steps(reused, steps=300)
    run_steps(fresh, steps=300)
    assert int((reused.state.phase == Phase.FLUID).sum()) > 0
    assert reused.dvdt is reused.outs["dvdt"].out  # the reused array was in use
    for k in ("x", "v", "rho", "T"):
        assert torch.equal(getattr(reused.state, k), getattr(fresh.state, k)), k
    for k in ("dvdt", "drhodt", "dTdt"):
        assert torch.equal(getattr(reused, k), getattr(fresh, k)), k


def test_rows_leaving_the_active_set_close_the_energy_balance():
    """A row the active set lets go of is no longer integrated: with warm rows of non-zero
    conduction rate taken out at a rebuild, the energy balance still closes to round-off
    (what they exchange with the rows still integrated is booked as conduction)."""
    cfg = small("scene.substrate_size_m=[12.0e-3, 3.0e-3, 1.0e-3]", "scene.wire_offset_m=6.0e-3",
                "scene.source_power_W=150.0", "scene.wire_feed_m_s=0.3", "scene.wire_gap_m=3.0e-3")
    _, sim = make_simulation(cfg)
    run_steps(sim, steps=300)
    a, th = sim.active_set, sim.thermal
    orig, dropped = a.refresh, []

    def refresh(state, lit):
        orig(state, lit)
        if dropped:
            return
        q = torch.where(a.active & (state.phase == Phase.SOLID) & ~th.lit, sim.dTdt.abs(), torch.zeros_like(sim.dTdt))
        take = torch.topk(q, 20).indices
        assert float(q[take].min()) > 0
        a.active = a.active.clone().index_fill_(0, take, False)
        dropped.append(take)

    a.refresh = refresh
    sim.stale = True  # a rebuild (and refresh) at the next step
    run_steps(sim, steps=100)
    assert dropped
    e = sim.energy_balance()
    assert e["residual_rel"] < 1e-12, e


def test_particles_leaving_the_scene_are_removed_and_booked():
    """Drops flung out of the scene (beyond escape_margin_m outside the substrate's swept box)
    are removed at the next neighbour rebuild, one that stays inside the margin is not; the
    mass and stored energy they take are booked, so particle mass + escaped mass and the
    energy balance (with the ``escaped`` loss) still close to round-off while the run goes on
    (its rows renumbered: a misaligned row would show in the balance)."""
    cfg = small("scene.source_power_W=150.0", "scene.wire_feed_m_s=0.3", "scene.wire_gap_m=1.0e-3")
    _, sim = make_simulation(cfg)
    run_steps(sim, steps=100)
    s = sim.state
    ids = s.id[s.body == WIRE][:6]
    stay = s.id[s.body == WIRE][6:7]
    fling(sim, ids)
    r = torch.nonzero(torch.isin(s.id, stay)).squeeze(1)
    s.x[r, 1] = sim.escape.hi[1] + 0.5 * cfg["scene"]["escape_margin_m"]  # outside the box, inside the margin
    gone = torch.isin(s.id, ids)
    m_gone = float(s.m[gone].sum())
    E_gone = float((s.m * sim.thermal.to_enthalpy(s.T))[gone].sum())
    m_all, id_max = float(s.m.sum()), int(s.id.max())
    run_steps(sim, steps=1)
    s = sim.state
    assert not bool(torch.isin(s.id, ids).any()) and bool(torch.isin(s.id, stay).any())
    assert sim.escape.n == 6 and sim.escape.kg == pytest.approx(m_gone, rel=1e-12)
    e = sim.energy_balance()
    assert e["escaped_J"] == pytest.approx(-E_gone, rel=1e-3)  # (booked at the half step)
    assert e["residual_rel"] < 1e-12, e
    run_steps(sim, steps=200)
    s = sim.state
    assert s.id.unique().numel() == s.n
    new = s.id > id_max  # layers fed since
    assert float(s.m[~new].sum()) + sim.escape.kg == pytest.approx(m_all, rel=1e-13)
    e = sim.energy_balance()
    assert e["residual_rel"] < 1e-12, e


def test_escape_margin_must_exceed_the_search_radius():
    with pytest.raises(CaseError, match=r"escape_margin_m = 0.0005: must exceed the search radius"):
        small("scene.escape_margin_m=0.5e-3")


def test_with_wire_stall_the_feed_also_waits_while_it_squeezes_melt():
    """Melt caught under the solid tip (1.25 spacings below it) and compressed by 20 % makes
    the feed wait (scene.wire_squeeze_limit = 0.15); compressed by 10 %, or compressed by
    20 % but 2 spacings or more from the wire, it does not. Without wire_stall nothing waits."""
    from torchsph.core.state import Phase

    dx = 2.5e-4
    for stall in (True, False):
        cfg = small("scene.source_layout=\"none\"", f"scene.wire_gap_m={0.25 * dx}", f"scene.wire_stall={str(stall).lower()}")
        scene, sim = make_simulation(cfg)
        s, feeder = sim.state, scene.info["feeder"]
        R = 0.5 * cfg["scene"]["wire_diameter_m"]
        r = s.x[:, :2].norm(dim=1)
        tip = float(s.x[s.body == WIRE, 2].min())
        assert tip == pytest.approx(0.75 * dx)
        top = (s.body != WIRE) & (s.x[:, 2] > -dx)
        under = top & (r < R - 0.5 * dx)  # 1.25 spacings below the tip's layer
        away = top & (r > R + 2.5 * dx)   # as deep, 2+ spacings aside
        assert int(under.sum()) > 0 and int(away.sum()) > 0
        assert not bool(feeder.touches_solid_substrate(s).any())  # no solid-on-solid contact
        rho0 = cfg["fluid"]["rho0_kg_m3"]
        for where, comp, waits in ((under, 0.20, stall), (under, 0.10, False), (away, 0.20, False)):
            s.phase = torch.where(where, torch.full_like(s.phase, int(Phase.FLUID)), torch.full_like(s.phase, int(Phase.SOLID)))
            s.rho = torch.where(where, torch.full_like(s.rho, (1.0 + comp) * rho0), torch.full_like(s.rho, rho0))
            assert feeder.check_contact(sim) is waits, (stall, comp)
            if waits:  # a wait would begin here, booked to the squeezed melt
                assert feeder.stall_why == "squeezed"


def test_zeta_made_with_the_colour_gradient_equals_zeta_made_alone(monkeypatch):
    """At a neighbour rebuild the rows whose zeta changes are those whose surface area the
    colour stage makes afresh: it makes zeta from the same pairs (one pass, not two). Those
    values equal zeta made alone (laplacian_norm on those rows) bit for bit, so a restart, which
    makes every row's zeta alone, continues the run exactly."""
    from torchsph.physics import thermal

    cfg = small("scene.source_power_W=300.0", "scene.wire_feed_m_s=0.3", "scene.wire_gap_m=3.0e-3")
    _, sim = make_simulation(cfg)
    th = sim.thermal
    fused = []
    original = thermal.zeta_of

    def checked(th_, state, rows):
        z = original(th_, state, rows)
        if th_.zeta_want is not None and th_.colour.norm(state, th_.zeta_want) is not None:
            alone = thermal.laplacian_norm(state.x, state.m, state.rho, rows, th_.table.gather(rows, within=True)[0],
                                           th_.kernel, th_.h, th_.domain)
            assert torch.equal(z, alone)
            fused.append(rows.numel())
        return z

    monkeypatch.setattr(thermal, "zeta_of", checked)
    run_steps(sim, steps=120)
    assert len(fused) >= 1 and 0 < min(fused) and max(fused) < th.rows.numel(), fused  # (a rebuild's rows, not all)


def test_the_deposition_scene_runs_in_float32_through_its_first_melt():
    """In float32 a denominator floored at 1e-300 is floored at 0 (1e-300 rounds to 0): the first
    melt particle in the contact band, with no surface beside it, divided by zero and the run
    stopped with an infinite surface tension at its 22nd step. The floor is now the dtype's
    (:func:`torchsph.physics.fluid.tiny`): the run passes its first melt with finite accelerations and
    closes its energy balance to float32's precision (measured 3.9e-6 of the flows)."""
    ov = ["scene.dx_m=3.0e-4", "scene.substrate_size_m=[4.0e-3, 4.0e-3, 1.5e-3]", "scene.wire_offset_m=2.0e-3",
          "scene.wire_length_m=1.5e-3", 'run.dtype="float32"']
    _, cfg = load_case(CASE, ov)
    _, sim = make_simulation(cfg)
    assert sim.state.dtype == torch.float32
    run_steps(sim, t_end=0.008)
    assert int((sim.state.phase == Phase.FLUID).sum()) >= 1  # it melted
    assert bool(torch.isfinite(sim.state.v).all()) and bool(torch.isfinite(sim.dvdt).all())
    assert abs(sim.energy_balance()["residual_rel"]) < 1e-4
