"""The step between neighbour rebuilds compiles whole: ``torch.compile(fullgraph=True)``
traces each of its two halves (:mod:`torchsph.step`: everything between the step's two host
reads) on a small deposition scene with melt, beams, surface losses, surface forces, phase
change and a fed wire; the compiled steps reproduce the eager steps, and once warm they are
not traced again, across neighbour rebuilds (neither dt nor the pair counts specialise them).
A graph break anywhere in a half fails the test (that is what fullgraph=True means)."""
import pytest
import torch

from torchsph import step
from torchsph.runner import make_simulation, run_steps

from test_deposition import small

dynamo = pytest.importorskip("torch._dynamo")


@pytest.fixture
def compiled_halves(monkeypatch):
    dynamo.reset()
    halves = {name: torch.compile(getattr(step, name), fullgraph=True, backend="aot_eager")
              for name in ("first_half", "close_momentum", "close_energy")}

    def use():
        for name, f in halves.items():
            monkeypatch.setattr(step, name, f)
    return use


@pytest.mark.parametrize("window", [0.0, 0.25])  # (with the conduction window: its two graphs)
def test_the_step_between_rebuilds_compiles_with_fullgraph(compiled_halves, window):
    from torch._dynamo.utils import counters
    cfg = small("scene.source_power_W=300.0", "scene.wire_feed_m_s=0.3", "scene.wire_gap_m=3.0e-3",
                f"numerics.conduction_window={window}")
    _, eager = make_simulation(cfg)
    _, traced = make_simulation(cfg)
    run_steps(eager, steps=60)
    run_steps(traced, steps=60)
    assert int((traced.state.phase == 0).sum()) > 0  # melt flows: every term of the step is traced
    assert traced.thermal.op.n_static > 0  # conduction's matrix, traced as its entries' sum
    assert (traced.thermal.op.split is not None) == (window > 0)
    compiled_halves()
    graphs, builds, closed = [], [], []
    for _ in range(60):
        run_steps(traced, steps=1)
        run_steps(eager, steps=1)
        graphs.append(counters["stats"]["unique_graphs"])
        builds.append(traced.nl.n_builds)
        closed.append(traced.thermal.slow_mark == traced.t)  # a window closed: its variant of close_energy
    assert graphs[0] >= 3  # the three parts were traced, as whole graphs (else fullgraph raised)
    # warm after a few steps (and, with a window, after the first that closed): no trace per
    # step, none at a later rebuild
    warm = 15 if window == 0 else max(15, closed.index(True) + 1)
    assert warm < 50 and graphs[-1] == graphs[warm] and builds[-1] > builds[warm], (graphs, builds, closed)
    for k in ("x", "v", "rho", "T", "T_peak"):
        a, b = getattr(eager.state, k), getattr(traced.state, k)
        assert torch.allclose(a, b, rtol=1e-12, atol=1e-12 * float(a.abs().max())), k
    assert traced.energy_balance()["residual_rel"] < 1e-12
