"""The conduction sum as a cached sparse operator (torchsph/physics/heat_operator.py) against the
plain Cleary-Monaghan pair sum over the neighbour table (thermal.conduction_pairs), at the
same state: on a random cloud, through melting and refreezing between neighbour builds, and
through a deposition run with melt, feed and partial rebuilds."""
import pytest
import torch
from conftest import CASES
from test_deposition import small
from test_thermal import cloud_conduction

from torchsph.core.neighbors import NeighbourTable, build_table
from torchsph.core.state import Phase
from torchsph.io.config import load_case
from torchsph.physics.fluid import embed
from torchsph.physics.heat_operator import material_factor
from torchsph.physics.thermal import conduction_pairs
from torchsph.run.build import make_simulation
from torchsph.step.loop import run_steps


def pair_sum(th, state, T):
    """The plain pair sum over the table on ``rows`` (R,)."""
    return conduction_pairs(state.x, th.wall_temperature(state, T), th.k, state.m, state.rho, th.zeta_cache, th.rows,
                            th.table.gather(th.rows, within=True)[0], th.kernel, th.h, th.domain)


def checking(sim):
    """Wrap the thermal model's heat rate: every evaluation is compared with the pair sum.
    Returns the record {worst: max relative difference, evals, static_share (min), builds,
    carried: builds that carried entries from the last, refrozen: evaluations with a particle
    solid again but not yet steady}. A build's values are also compared, bit for bit, with
    the values made afresh (a build that carries the unchanged entries must equal it)."""
    th = sim.thermal
    rec = {"worst": 0.0, "evals": 0, "static_share": 1.0, "builds": 0, "refrozen": 0, "carried": 0}
    orig, orig_prepare = th.heat_rate_rows, th.prepare

    def prepare(state):  # where the operator's values are made (once per selection)
        op = th.op
        built, carry = op.built, op.built_from is not None
        orig_prepare(state)
        if not built:
            i, j = op.g_i, op.g_j
            fresh = material_factor(th.k[i], th.k[j], th.zeta_cache[i], th.zeta_cache[j]) * op.g_f
            fresh = torch.where(op.steady[i] & op.steady[j], fresh, torch.zeros_like(fresh))
            assert torch.equal(op.g, fresh)
            rec["builds"] += 1
            rec["carried"] += carry

    def checked(state, T):
        op = th.op
        q = orig(state, T)
        ref = pair_sum(th, state, T)
        if ref.numel():
            rec["worst"] = max(rec["worst"], float((q - ref).abs().max() / ref.abs().max()))
        rec["evals"] += 1
        rec["static_share"] = min(rec["static_share"], op.n_static / max(op.pairs, 1))
        rec["refrozen"] += bool(((state.phase == Phase.SOLID) & ~th.steady).any())
        return q

    th.heat_rate_rows, th.prepare = checked, prepare
    return rec


def hot_spot_block():
    """(cfg, sim): a moving steel block with a hot spot that melts, then refreezes."""
    _, cfg = load_case(CASES / "beam_plate", [
        "scene.size_m=[3e-3, 3e-3, 1e-3]", "thermal.phase_change=true", "fluid.c0_m_s=2.0",
        "fluid.viscosity_Pa_s=0.005", "scene.velocity_m_s=[0.015, 0.0, 0.0]", "run.t_end_s=0.02"])
    cfg.pop("beam")
    _, sim = make_simulation(cfg)
    s = sim.state
    hot = (s.x[:, 2] > -0.4e-3) & (s.x[:, 0].abs() < 0.3e-3) & (s.x[:, 1].abs() < 0.3e-3)
    s.T = torch.where(hot, torch.full_like(s.T, 2500.0), s.T)
    return cfg, sim


def test_operator_equals_the_pair_sum_on_a_cloud():
    """Random cloud, per-particle conductivity, one rigid body: every pair in the matrix."""
    st, c = cloud_conduction()
    c.zeta_cache = c.zeta(st)
    q = c.heat_rate(st, st.T)
    ref = embed(c.rows, pair_sum(c, st, st.T), st.n)
    assert float((q - ref).abs().max() / ref.abs().max()) < 1e-13
    assert c.op.n_dynamic == 0 and c.op.n_static > 0


def test_operator_through_melting_and_refreezing():
    """A hot spot on a moving block melts and refreezes: particles that froze since the last
    neighbour build are not at the build's distances (they flowed), so their pairs stay
    evaluated every step until the next build. Equal to the pair sum at every step."""
    cfg, sim = hot_spot_block()
    rec = checking(sim)
    for _ in range(400):
        run_steps(sim, steps=1)
        if sim.n_fluid == 0:
            break
    assert sim.n_fluid == 0 and rec["refrozen"] > 0, rec
    assert rec["worst"] < 1e-12, rec


def test_operator_through_a_deposition_run():
    """Melt, two moving bodies (wire and substrate), fed layers, partial neighbour rebuilds
    with the active set, phase changes: equal to the pair sum at every step; the matrix holds
    most pairs (what makes it cheap) and is built once per selection, not per step."""
    cfg = small("scene.source_power_W=150.0", "scene.wire_feed_m_s=0.3", "scene.wire_gap_m=1.0e-3",
                "numerics.conduction_window=0.0")  # (every pair every step: compared with the pair sum)
    _, sim = make_simulation(cfg)
    rec = checking(sim)
    run_steps(sim, steps=250)
    s = sim.state
    assert int((s.phase == Phase.FLUID).sum()) > 0 and sim.feeder.n_fed >= 1 and sim.nl.n_partial > 0
    assert rec["worst"] < 1e-12, rec
    assert rec["static_share"] > 0.8, rec
    assert rec["builds"] < 0.5 * rec["evals"], rec
    assert rec["carried"] > 0, rec  # (and each equal to the build made afresh)


def restarts_bit_for_bit(sim, cfg, tmp_path, K: int = 30):
    """A checkpoint of ``sim`` now, then K steps of it and K of a restart from the checkpoint: equal bit for bit."""
    from torchsph.io import checkpoint as ckpt
    from torchsph.run.build import resume

    path = tmp_path / "checkpoint.pt"
    ckpt.save(sim, path, ckpt.config_hash(cfg))
    run_steps(sim, steps=K)
    _, other = make_simulation(cfg)
    resume(other, path, cfg)
    run_steps(other, steps=K)
    for name in ("x", "v", "rho", "T", "phase", "body"):
        assert torch.equal(getattr(sim.state, name), getattr(other.state, name)), name


def test_restart_between_a_freeze_and_the_next_build_is_bit_for_bit(tmp_path):
    """A checkpoint written while a refrozen particle is solid but not yet steady (it froze
    since the last neighbour build, away from the build's positions): the restart rebuilds the
    operator from the checkpoint (the build's positions and which particles are steady), so
    K more steps equal the uninterrupted run's bit for bit."""

    cfg, sim = hot_spot_block()
    for _ in range(400):
        run_steps(sim, steps=1)
        st = sim.state
        if bool(((st.phase == Phase.SOLID) & ~sim.thermal.steady).any()) and sim.n_fluid > 0:
            break
    else:
        raise AssertionError("no particle froze between neighbour builds")
    restarts_bit_for_bit(sim, cfg, tmp_path)


def test_a_checkpoint_without_the_operators_arrays_gets_the_matrix_back_at_the_next_build(tmp_path):
    """A checkpoint of a version that did not carry which particles are steady (nor the
    matrix's positions): the restore guesses them (the solid that has not moved since the
    last build: none on a moving substrate), and the next neighbour build makes the matrix
    anew, which then holds most pairs again (before the fix it stayed empty while the
    conducting rows stayed the same: every pair evaluated every step, 9x slower)."""
    from torchsph.io import checkpoint as ckpt
    from torchsph.run.build import resume

    cfg = small("scene.source_power_W=150.0", "scene.wire_feed_m_s=0.3", "scene.wire_gap_m=1.0e-3",
                "numerics.conduction_window=0.0")  # (every pair every step: compared with the pair sum)
    _, sim = make_simulation(cfg)
    run_steps(sim, steps=60)
    d = ckpt.snapshot(sim)
    for k in ("steady", "x_op"):
        del d["arrays"][f"th.{k}"]
    d["config_hash"] = ckpt.config_hash(cfg)
    path = tmp_path / "old.pt"
    ckpt.write(d, path)
    _, other = make_simulation(cfg)
    resume(other, path, cfg)
    b = other.nl.n_builds
    while other.nl.n_builds == b:
        run_steps(other, steps=1)
    run_steps(other, steps=1)
    op = other.thermal.op
    assert op.n_static > 0.8 * op.pairs, (op.n_static, op.pairs)


def test_a_selection_reads_only_work_particles_with_a_table_row():
    """A decomposed run's work set holds outer ghosts that have no table row (the table is
    built for the particles whose neighbours that rank can know). A selection, as after a
    phase change between rebuilds, must not read their rows: on the full scene at 3 ms on 2
    ranks it stopped with an IndexError (fixed in dc52253). Here one halo particle's row is
    taken out of the table (beam_plate: 135 halo particles): the selection runs, and the
    conduction rate is the one of the whole table (a halo particle is a source only)."""
    _, cfg = load_case(CASES / "beam_plate")
    _, sim = make_simulation(cfg)
    run_steps(sim, steps=20)
    st, th, table = sim.state, sim.thermal, sim.nl.table
    act, work = sim.active_set.active, sim.active_set.work
    halo = torch.nonzero(work & ~act & (st.phase == Phase.SOLID) & table.has_row()).squeeze(1)
    assert halo.numel() > 0
    drop = halo[:1]
    keep = table.rows[table.rows != drop]
    slot = table.slot.index_select(0, keep)
    part = NeighbourTable(keep, table.nb.index_select(0, slot), table.mask.index_select(0, slot), table.n)
    assert not bool(part.has_row()[drop]) and bool(work[drop])
    q_whole = th.heat_rate(st, st.T)
    th.select_pairs(st, part, active=act, work=work, x_ref=sim.nl.x_ref, new_table=True)
    q_part = th.heat_rate(st, st.T)
    assert torch.allclose(q_part, q_whole, rtol=1e-12, atol=1e-12 * float(q_whole.abs().max()))


def test_an_operator_that_follows_a_new_row_set_is_the_one_made_afresh():
    """The active set moves between builds: the operator carries the rows that stay, makes the
    new rows' entries and drops the left rows' (``follow``). It must be the operator made
    afresh for the new rows, bit for bit (a restart makes it afresh), with some particles no
    longer steady (melted) and two bodies."""
    from torchsph.physics.heat_operator import ConductionOperator
    st, c = cloud_conduction(n=600, seed=3)
    n = st.n
    g = torch.Generator().manual_seed(5)
    body = (st.x[:, 0] > 0.8e-3).long()  # two bodies: no rigid pairs across x = 0.8 mm
    steady = torch.rand(n, generator=g, dtype=torch.float64) > 0.1
    nb, mask = build_table(st.x, 2 * c.h, c.domain)
    rows_a = torch.nonzero(st.x[:, 0] < 0.6e-3).squeeze(1)
    rows_b = torch.nonzero((st.x[:, 0] > 0.3e-3) & (st.x[:, 0] < 0.9e-3)).squeeze(1)
    args = (c.kernel, c.h, c.domain)
    a = ConductionOperator(rows_a, nb[rows_a], mask[rows_a], st.x, steady, body, *args)
    steady_b = steady & (torch.rand(n, generator=g, dtype=torch.float64) > 0.05)  # some melted since
    followed = a.follow(rows_b, lambda at: (nb[rows_b][at], mask[rows_b][at]), st.x, steady_b, body)
    afresh = ConductionOperator(rows_b, nb[rows_b], mask[rows_b], st.x, steady_b, body, *args)
    for name in ("g_row", "g_i", "g_j", "g_f", "crow", "row_of"):
        assert torch.equal(getattr(followed, name), getattr(afresh, name)), name
    assert followed.main_body == afresh.main_body and followed.n_static == afresh.n_static > 0
    # the carried rows were not made again: the new rows alone hold fewer entries
    new_rows = int((a.row_of[rows_b] < 0).sum())
    assert 0 < new_rows < rows_b.numel()


def test_rigid_marks_from_the_few_rows_equal_every_rows_own():
    """The rigid marks (solid, not next to melt, all neighbours firm and of its body) read
    from the rows outside the largest body and its non-firm rows (the table is symmetric),
    or from the non-firm rows and those whose row may hold a partner of another body (after
    a partial rebuild: ``cross_rows``), equal the marks read from every working row, through
    a deposition run with melt, a fed wire and partial rebuilds, at every selection."""
    from torchsph.physics.conduction_select import rigid_marks, rigid_marks_direct
    from torchsph.step.bookkeeping import cross_rows
    cfg = small("scene.source_power_W=150.0", "scene.wire_feed_m_s=0.3", "scene.wire_gap_m=1.0e-3",
                "numerics.conduction_window=0.0")  # (every pair every step: compared with the pair sum)
    _, sim = make_simulation(cfg)
    seen = {"checks": 0, "fluid": 0, "cross": 0}
    orig = sim.select_pairs

    def checked(new_table=False):
        orig(new_table)
        s, table = sim.state, sim.nl.table
        work = sim.active_set.work
        fast = rigid_marks(s, table, work)
        assert torch.equal(fast, rigid_marks_direct(s, table, work))
        cross = cross_rows(sim)
        if cross is not None:
            assert torch.equal(rigid_marks(s, table, work, cross), fast)
            seen["cross"] += 1
        seen["checks"] += 1
        seen["fluid"] += int((s.phase == Phase.FLUID).sum()) > 0 and bool((~fast & (s.phase == Phase.SOLID)).any())

    sim.select_pairs = checked
    run_steps(sim, steps=250)
    assert seen["checks"] > 5 and seen["fluid"] > 0 and seen["cross"] > 2, seen


def test_an_operator_made_in_blocks_of_rows_is_the_one_made_whole(monkeypatch):
    """The rigid entries are made in blocks of rows (a whole build of the full scene once every
    particle works peaked at ~20 GB): the same entries, values and order as in one go, bit
    for bit, for a build and for a follow, with blocks that cut the rows unevenly."""
    from torchsph.physics import heat_operator
    from torchsph.physics.heat_operator import ConductionOperator
    st, c = cloud_conduction(n=600, seed=4)
    n = st.n
    g = torch.Generator().manual_seed(6)
    body = (st.x[:, 0] > 0.8e-3).long()
    steady = torch.rand(n, generator=g, dtype=torch.float64) > 0.1
    nb, mask = build_table(st.x, 2 * c.h, c.domain)
    rows_a = torch.nonzero(st.x[:, 0] < 0.6e-3).squeeze(1)
    rows_b = torch.nonzero(st.x[:, 0] > 0.3e-3).squeeze(1)
    args = (c.kernel, c.h, c.domain)

    def make():
        a = ConductionOperator(rows_a, nb[rows_a], mask[rows_a], st.x, steady, body, *args)
        return a, a.follow(rows_b, lambda at: (nb[rows_b][at], mask[rows_b][at]), st.x, steady, body)

    whole = make()
    monkeypatch.setattr(heat_operator, "ENTRY_BLOCK", 7 * nb.shape[1] + 3)  # 7 rows a block
    calls, block = [], heat_operator.rigid_block
    monkeypatch.setattr(heat_operator, "rigid_block", lambda *a: calls.append(a[0].numel()) or block(*a))
    blocks = make()
    assert rows_a.numel() > 50 and whole[0].n_static > 1000
    assert len(calls) > rows_a.numel() // 7 and max(calls) == 7  # made block by block
    for w, b in zip(whole, blocks):
        for name in ("g_row", "g_j", "g_f", "crow", "cols"):
            assert torch.equal(getattr(w, name), getattr(b, name)), name


def windowed(*extra):
    """The small deposition scene with the conduction window (numerics.conduction_window)."""
    return small("scene.source_power_W=150.0", "scene.wire_feed_m_s=0.3", "scene.wire_gap_m=1.0e-3",
                 "numerics.conduction_window=0.25", *extra)


def test_a_split_operator_whose_window_closes_at_every_step_is_the_pair_sum(monkeypatch):
    """The split (fast rows every step, slow rows' mutual pairs once per window) through melt,
    feed and partial rebuilds, with the window closed at every step (factor 1): the fast rows'
    product, the boundary pairs and the slow pairs less the boundary are the whole pair sum to
    round-off, at every step, while slow rows exist; splits kept through a selection (no new
    fast row) with the new values among them."""
    from torchsph.physics.heat_operator import SlowSplit

    made, revalued = [0], [0]
    init, revalue = SlowSplit.__init__, SlowSplit.revalue

    def counted_init(self, *a):
        made[0] += 1
        init(self, *a)

    def counted_revalue(self, op):
        revalued[0] += 1
        revalue(self, op)
    monkeypatch.setattr(SlowSplit, "__init__", counted_init)
    monkeypatch.setattr(SlowSplit, "revalue", counted_revalue)
    _, sim = make_simulation(windowed())
    th = sim.thermal
    rec = checking(sim)
    inner = th.heat_rate_rows
    one = torch.ones((), dtype=torch.float64)
    slow = []

    def every_step(state, T):
        th.slow_now = one
        q = inner(state, T)
        slow.append(int((~th.op.split.fast).sum()))
        return q
    th.heat_rate_rows = every_step
    run_steps(sim, steps=250)
    assert int((sim.state.phase == Phase.FLUID).sum()) > 0 and sim.feeder.n_fed >= 1 and sim.nl.n_partial > 0
    assert rec["worst"] < 1e-12, rec
    assert max(slow) > 0 and int(th.op.split.fast.sum()) > 0, slow
    assert revalued[0] > made[0] > 0, (made, revalued)  # (a new split takes its values by revalue too)


def test_a_window_waits_and_conserves_energy_and_a_restart_inside_it_is_bit_for_bit(tmp_path):
    """With the window on, the slow pairs are summed on few steps (the window spans several
    acoustic steps), the energy balance closes to round-off, and a checkpoint written while a
    window is open restarts bit for bit (the window's start is carried)."""

    cfg = windowed()
    _, sim = make_simulation(cfg)
    run_steps(sim, steps=150)  # (until the melt's acoustic step holds dt: before, the heating limit did)
    assert sim.n_fluid > 0
    closed = []
    import torchsph.step.simulation as simulation
    orig = simulation.slow_factor

    def counted(th, t, dt, limits):
        f = orig(th, t, dt, limits)
        closed.append(f is not None)
        return f
    simulation.slow_factor = counted
    try:
        run_steps(sim, steps=100)
    finally:
        simulation.slow_factor = orig
    assert 0 < sum(closed) < len(closed) / 8, closed
    assert sim.energy_balance()["residual_rel"] < 1e-12
    while sim.thermal.slow_mark == sim.t:  # inside a window
        run_steps(sim, steps=1)
    restarts_bit_for_bit(sim, cfg, tmp_path)


@pytest.mark.parametrize("share", [0, None], ids=["always_by_rows", "by_rows_where_fewer"])
def test_the_changed_entries_found_from_the_rows_are_those_of_the_whole_pass(share, monkeypatch):
    """A build after the first finds the entries with a changed particle from the changed
    particles' rows and their partners' (a binary search in each partner's row), not by a pass
    over every entry: the same entries, for none, a few and many changed particles, and a
    changed particle that is a column without a row (the whole pass). Once with the rows' search
    taken however many rows changed, once with the whole pass where they hold a large share."""
    import torchsph.physics.heat_operator as H
    from torchsph.physics.heat_operator import changed_entries

    if share is not None:
        monkeypatch.setattr(H, "WHOLE_PASS_SHARE", share)

    _, sim = make_simulation(small("scene.source_power_W=150.0", "numerics.conduction_window=0.0"))
    run_steps(sim, steps=20)
    op = sim.thermal.op
    n = sim.state.n
    gen = torch.Generator().manual_seed(3)
    rowless = torch.nonzero(op.row_of.index_select(0, op.cols) < 0).squeeze(1)
    masks = [torch.zeros(n, dtype=torch.bool)] + [torch.rand(n, generator=gen) < f for f in (0.001, 0.05, 0.5)]
    if rowless.numel():  # (cold solid read but not integrated, at the active set's edge)
        masks.append(torch.zeros(n, dtype=torch.bool).index_fill_(0, op.cols[rowless[:1]], True))
    walls = torch.nonzero(op.row_of < 0).squeeze(1)  # particles that are no row (walls, cold solid)
    masks.append(torch.zeros(n, dtype=torch.bool).index_fill_(0, walls[:5], True) | masks[2])
    assert op.n_static > 1000
    for ch in masks:
        whole = torch.nonzero(ch.index_select(0, op.g_i) | ch.index_select(0, op.g_j)).squeeze(1)
        assert torch.equal(changed_entries(op, ch), whole)


def test_frozen_rows_are_none_a_beam_or_a_loss_can_reach():
    """Between windows only rows no heat reaches wait: a beam plate with surface losses and a
    fixed step (windows of ~20 steps) freezes interior rows, never a surface row or one a beam
    can reach, and books its energy to round-off; a beam that may reach any row (a moving one:
    no candidate rows) freezes none."""
    from torchsph.physics.conduction_window import integrated_rows
    from torchsph.physics.losses import surface_rows
    _, cfg = load_case(CASES / "beam_plate", ["run.t_end_s=0.02", "numerics.conduction_window=0.25",
                                              "numerics.dt_s=2e-6", "thermal.emissivity=0.4"])
    _, sim = make_simulation(cfg)
    run_steps(sim, steps=200)
    th = sim.thermal
    assert th.losses.active and th.int_rows is not None and 0 < th.int_rows.numel() < th.rows.numel()
    integrated = torch.zeros(sim.state.n, dtype=torch.bool).index_fill_(0, th.int_rows, True)
    _, srows, _ = surface_rows(th, sim.state)
    assert bool(integrated[srows].all())
    for b in th.beam_rows:
        assert bool(integrated[th.rows[b]].all())
    assert sim.energy_balance()["residual_rel"] < 1e-12
    th.beam_rows = [None]
    integrated_rows(th)
    assert th.int_rows is None
