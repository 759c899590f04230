"""The step between neighbour rebuilds compiles whole: ``torch.compile(fullgraph=True)``
traces each of its two halves (:mod:`torchsph.step.integrator`: everything between the step's two host
reads) on a small deposition scene with melt, beams, surface losses, surface forces, phase
change and a fed wire; the compiled steps reproduce the eager steps; a plain step is never
traced again (neither dt nor the pair counts specialise it), and once the first rebuild and
feed have made the sizes dynamic, a rebuild is not either.
A graph break anywhere in a half fails the test (that is what fullgraph=True means)."""
import pytest
import torch
from test_deposition import small

from torchsph.run.build import make_simulation
from torchsph.step import integrator as step
from torchsph.step.loop import run_steps

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
                f"numerics.conduction_window={window}", "numerics.skin_over_dx=0.2")  # (rebuilds every ~40 steps)
    _, eager = make_simulation(cfg)
    _, traced = make_simulation(cfg)
    run_steps(eager, steps=60)
    run_steps(traced, steps=60)
    assert int((traced.state.phase == 0).sum()) > 0  # melt flows: every term of the step is traced
    assert traced.thermal.op.n_static > 0  # conduction's matrix, traced as its entries' sum
    assert (traced.thermal.op.split is not None) == (window > 0)
    compiled_halves()
    graphs, builds, closed = [], [], []
    sizes, quiet = [], None
    for _ in range(240 if window == 0 else 60):
        run_steps(traced, steps=1)
        run_steps(eager, steps=1)
        graphs.append(counters["stats"]["unique_graphs"])
        builds.append(traced.nl.n_builds)
        sizes.append(traced.state.n)
        closed.append(traced.thermal.slow_mark == traced.t)  # a window closed: its variant of close_energy
        fed = [i for i in range(1, len(sizes)) if sizes[i] != sizes[i - 1]]
        # warm: a rebuild after the first feed that traced nothing (from the step before it to 3 after)
        quiet = next((r for r in range(1, len(builds) - 3) if fed and r > fed[0] + 3 and builds[r] > builds[r - 1]
                      and graphs[r + 3] == graphs[r - 1]), None)
        if quiet is not None and window == 0:
            break
    assert graphs[0] >= 3  # the three parts were traced, as whole graphs (else fullgraph raised)
    # The parts are traced again only at an event (a rebuild, a feed, a window's close), while
    # they first see new shapes (each size becomes dynamic at its first change) and the rates'
    # first re-selections: a plain step never traces. Once those have been seen, a rebuild
    # traces nothing (shown without the window; with it, the 60 steps hold too few events).
    events = [0] + [i for i in range(1, len(builds)) if builds[i] > builds[i - 1] or sizes[i] != sizes[i - 1] or closed[i]]
    traced_at = [i for i in range(1, len(graphs)) if graphs[i] > graphs[i - 1]]
    assert all(any(0 <= t - e <= 3 for e in events) for t in traced_at), (traced_at, events)
    if window == 0:
        assert quiet is not None, (str(graphs), str(builds), str(sizes))
    for k in ("x", "v", "rho", "T", "T_peak"):
        a, b = getattr(eager.state, k), getattr(traced.state, k)
        assert torch.allclose(a, b, rtol=1e-12, atol=1e-12 * float(a.abs().max())), k
    assert traced.energy_balance()["residual_rel"] < 1e-12
