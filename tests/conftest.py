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


def assert_blow_up_diagnosed(case, overrides, limit, factor, max_steps, parts):
    """Step ``case`` at ``factor`` x its ``limit`` until it stops; the one-line diagnosis
    must contain every string in ``parts``."""
    from torchsph.config import load_case
    from torchsph.runner import make_simulation
    from torchsph.simulation import SimulationError

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
