import sys
from pathlib import Path

import pytest
import torch

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
CASES = ROOT / "cases"


@pytest.fixture(autouse=True)
def _seed():
    torch.manual_seed(0)


@pytest.fixture(autouse=True)
def _threads():
    """A test that runs the command line sets torch's threads from the load (torchsph/run/threads.py):
    put them back, so that no later test runs on another count."""
    n = torch.get_num_threads()
    yield
    torch.set_num_threads(n)


def assert_blow_up_diagnosed(case, overrides, limit, factor, max_steps, parts):
    """Step ``case`` at ``factor`` x its ``limit`` until it stops; the one-line diagnosis
    must contain every string in ``parts``."""
    from torchsph.io.config import load_case
    from torchsph.run.build import make_simulation
    from torchsph.step.simulation import SimulationError

    _, cfg = load_case(CASES / case, overrides)
    _, sim = make_simulation(cfg)
    dt = factor * sim.limits()[limit]
    with pytest.raises(SimulationError) as err:
        for _ in range(max_steps):
            sim.advance(dt, "fixed")
    msg = str(err.value)
    print(msg)
    for part in parts:
        assert part in msg, (part, msg)
