"""The resolution study's convergence verdict on values with a known order and limit."""
import importlib.util
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]


def study():
    spec = importlib.util.spec_from_file_location("resolution_study", ROOT / "scripts" / "resolution_study.py")
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


def test_spacing_for_a_ten_percent_difference_follows_the_observed_order():
    """width = 2 + 5 h^2 (mm) at h = 0.4, 0.35, 0.3 mm: Richardson finds p = 2 and 2 mm, the
    two finest differ by 5 (0.35^2 - 0.3^2) / (2 + 5 0.3^2) = 6.6 %, and two rungs 0.35/0.3
    apart differ by less than 10 % below h = sqrt(0.2 / (5 ((7/6)^2 - 1))) = 0.333 mm."""
    mod = study()
    rows = [{"dx_mm": h, "width_mm": 2.0 + 5.0 * h * h} for h in (0.4, 0.35, 0.3)]
    ext = {"width_mm": mod.richardson([r["dx_mm"] for r in rows], [r["width_mm"] for r in rows])}
    assert ext["width_mm"]["p"] == pytest.approx(2.0, rel=1e-6) and ext["width_mm"]["f0"] == pytest.approx(2.0)
    text = mod.convergence(rows, ext, ["width_mm"])
    row = next(line for line in text.splitlines() if line.startswith("| width_mm"))
    _, diff, need, _ = (c.strip() for c in row.split("|")[1:])
    assert diff == f"{5 * (0.35**2 - 0.3**2) / (2 + 5 * 0.09):+.1%}" == "+6.6%"
    assert float(need) == pytest.approx((0.2 / (5 * ((0.35 / 0.3) ** 2 - 1))) ** 0.5, rel=1e-3)


def test_a_ramp_of_settled_bins_is_not_called_a_steady_bead():
    """The 0.2 mm rung of perpendicular_350W: nine bins, each changed < 5 % over 50 ms, held
    0.02 .. 4.71 mm2 along x (the melt held on the wire, dropped in turns). Their mean, 1.94 mm2,
    is not a bead's cross-section, and the row says so; bins within +-10 % of 2.26 mm2 are a
    steady bead (spread (max - min) / mean = 20 %)."""
    mod = study()
    ramp = [0.02, 0.71, 0.87, 1.20, 1.83, 2.46, 3.62, 4.71, 2.07]
    assert mod.spread(ramp) == pytest.approx((4.71 - 0.02) / (sum(ramp) / 9))
    note = mod.unsteady({"dx_mm": 0.2, "bins_mm2": ramp, "bins_spread": mod.spread(ramp)})
    assert note is not None and "Not a steady bead at dx = 0.2 mm" in note and "0.02, 0.71" in note
    even = [2.26 * (1 + 0.1 * k / 4) for k in range(-4, 5)]
    assert mod.spread(even) == pytest.approx(0.2, rel=1e-9)
    assert mod.unsteady({"dx_mm": 0.3, "bins_mm2": even, "bins_spread": mod.spread(even)}) is None
    assert mod.unsteady({"dx_mm": 0.25}) is None  # a row recorded before the column existed
