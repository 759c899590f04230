"""The step's stages for the composable terms (torchsph/step/stages.py): a term that makes a
per-particle field ([temperature_gradient]: grad_T), another that reads it on its neighbours
([anisotropic_conduction]), the order between them, and the refusal of a read nothing writes."""
import math
import os
import shutil
import subprocess
import sys
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest
import torch

from conftest import CASES
from torchsph.core.analytic import conduction_1d_exact
from torchsph.core.schema import CaseError
from torchsph.core.state import Phase
from torchsph.io.config import load_case
from torchsph.physics.terms import TERMS, Term, register
from torchsph.run.build import make_simulation
from torchsph.step import stages
from torchsph.step.loop import run_steps

ROOT = Path(__file__).resolve().parents[1]
MPIEXEC = shutil.which("mpiexec", path=str(Path(sys.executable).parent)) or shutil.which("mpiexec")
BAR = CASES / "anisotropic_conduction_1d"


def block():
    """The preheated block without its source: a free 4 x 4 x 3 mm steel block, every particle
    in the work (the temperatures are set by hand after set-up)."""
    _, cfg = load_case(CASES / "preheated_block", ["numerics.skip_cold_solid=false"])
    cfg.pop("heating")
    return cfg


def test_the_gradient_of_a_linear_field_is_exact():
    """grad_T of T = T0 + G . x on a 3-D block, faces, edges and corners included: G to 1e-10
    (the renormalisation makes a linear field's gradient exact wherever L is invertible)."""
    cfg = block()
    cfg["temperature_gradient"] = {}
    _, sim = make_simulation(cfg)
    G = torch.tensor([2.0e5, -1.0e5, 5.0e4], dtype=torch.float64)
    sim.state.T = 300.0 + sim.state.x @ G
    stages.evaluate_fields(sim)
    g = sim.fields["grad_T"]
    assert g.shape == sim.state.x.shape
    assert float((g - G).abs().max()) < 1e-10 * float(G.abs().max())


def test_the_anisotropic_flux_neither_makes_nor_loses_heat():
    """A Gaussian temperature in a free block (no walls): each pair's contributions cancel, so
    the term's powers sum to zero to 1e-12 of their magnitude; and on a linear field they vanish."""
    cfg = block()
    cfg["temperature_gradient"] = {}
    cfg["anisotropic_conduction"] = {"extra_conductivity_W_mK": [10.0, 20.0, 40.0]}
    _, sim = make_simulation(cfg)
    x = sim.state.x
    sim.state.T = 300.0 + 1500.0 * torch.exp(-((x - torch.tensor([3e-4, 0.0, -1e-3], dtype=x.dtype)) ** 2).sum(1) / 1e-6)
    stages.evaluate_fields(sim)
    term = next(t for t in sim.terms if t.section == "anisotropic_conduction")
    P = term.heat(sim, 0.0, sim.thermal.rows)
    assert float(P.abs().sum()) > 0
    assert abs(float(P.sum())) < 1e-12 * float(P.abs().sum())


def bar_error(nx):
    _, cfg = load_case(BAR, [f"scene.nx={nx}"])
    scene, sim = make_simulation(cfg)
    run_steps(sim, t_end=cfg["run"]["t_end_s"])
    s, i = sim.state, scene.info
    m = s.phase == Phase.SOLID
    th = cfg["thermal"]
    alpha_x = (th["conductivity_W_mK"] + cfg["anisotropic_conduction"]["extra_conductivity_W_mK"][0]) / (
        cfg["fluid"]["rho0_kg_m3"] * th["specific_heat_J_kgK"])
    Te = conduction_1d_exact(s.x[m, 0], sim.t, alpha_x, i["T_face"], i["T0"])
    return float(torch.sqrt(((s.T[m] - Te) ** 2).mean()) / (i["T_face"] - i["T0"])), sim


def test_the_bar_with_extra_conduction_along_it_follows_erfc():
    """cases/anisotropic_conduction_1d: k = 42 plus 42 along x from the two stages, against the
    erfc of alpha_x = 84 / (rho c_p): L2 error < 0.5 % of the face's rise at nx = 100, converging
    at order >= 0.9 (the two-pass Laplacian beside the fixed-temperature wall is first order;
    measured 0.90 %, 0.40 %, 0.20 % at nx = 25, 50, 100), and the energy balance closed."""
    (e50, _), (e100, sim) = bar_error(50), bar_error(100)
    assert e100 < 0.005, e100
    assert math.log(e50 / e100) / math.log(2.0) >= 0.9, (e50, e100)
    eb = sim.energy_balance()
    assert eb["residual_rel"] < 1e-12 and eb["anisotropic_conduction_J"] > 0


def test_a_read_that_nothing_writes_is_refused_in_one_line(monkeypatch):
    class Reader(Term):
        section = "reader"
        reads = ("x", "grad_T")
        writes = ("heat",)

        @classmethod
        def from_case(cls, cfg, ctx):
            return cls()

        def heat(self, sim, t, rows):
            return torch.zeros(rows.numel(), dtype=sim.state.dtype)

    monkeypatch.setitem(TERMS, "reader", Reader)
    _, cfg = load_case(CASES / "radiating_slab")
    cfg["reader"] = {}
    with pytest.raises(CaseError, match=r"^\[reader\] reads 'grad_T', which nothing in this case writes; "
                                        r"\[temperature_gradient\] writes it: name that section$"):
        make_simulation(cfg)
    cfg["temperature_gradient"] = {}
    _, sim = make_simulation(cfg)  # with its writer, accepted
    assert [t.section for t in sim.fields.order] == ["temperature_gradient"]


def test_fields_are_made_before_they_are_read_and_cycles_are_refused():
    def term(sec, reads, fields):
        return SimpleNamespace(section=sec, reads=reads, fields=fields)
    a, b, c = term("a", ("f_b",), ("f_a",)), term("b", ("T",), ("f_b",)), term("c", ("f_a", "f_b"), ())
    assert [t.section for t in stages.order_terms([c, a, b], set())] == ["b", "a"]
    with pytest.raises(CaseError, match="cycle"):
        stages.order_terms([term("a", ("f_b",), ("f_a",)), term("b", ("f_a",), ("f_b",))], set())
    with pytest.raises(CaseError, match="both write the field 'f_a'"):
        stages.order_terms([term("a", (), ("f_a",)), term("b", (), ("f_a",))], set())
    with pytest.raises(TypeError, match="writes rates"):
        register(type("Odd", (Term,), {"section": "odd", "writes": ("grad_X",)}))  # a field it does not declare


@pytest.mark.skipif(MPIEXEC is None, reason="no mpiexec (pip install mpich)")
def test_two_and_three_ranks_equal_one_process_with_the_two_stages(tmp_path):
    """The bar on 2 and 3 ranks (slabs along x: the gradient field read across the slab
    boundary) equals one process to 1e-10 after 150 steps."""
    _, cfg = load_case(BAR, ["scene.nx=50"])
    _, sim = make_simulation(cfg)
    run_steps(sim, steps=150)
    order = sim.state.id.argsort()
    ref = sim.state.T[order].numpy()
    env = {**os.environ, "PYTHONPATH": str(ROOT), "OMP_NUM_THREADS": "1"}
    for n in (2, 3):
        out = tmp_path / f"r{n}.npz"
        r = subprocess.run([MPIEXEC, "-n", str(n), sys.executable, "-m", "parallel.driver", str(BAR), "150", str(out),
                            "scene.nx=50"], cwd=ROOT, env=env, capture_output=True, text=True, timeout=600)
        assert r.returncode == 0, r.stderr[-3000:]
        g = np.load(out)
        assert np.array_equal(g["state_id"], sim.state.id[order].numpy())
        assert np.abs(g["state_T"] - ref).max() < 1e-10 * np.abs(ref).max(), n
