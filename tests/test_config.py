"""Malformed case files give one-line errors naming the key, the value and what is allowed."""
import subprocess
import sys

import pytest
from conftest import CASES, ROOT

from torchsph.io.config import CaseError, load_case, load_raw

GOOD = (CASES / "taylor_green_2d" / "case.toml").read_text()


def with_edit(text, old, new):
    assert old in text, old
    return text.replace(old, new, 1)


BAD = {
    "unknown_key": (with_edit(GOOD, "nx = 50", "nx = 50\nnxx = 3"), ["unknown key [scene] nxx", "allowed"]),
    "unknown_section": (GOOD + "\n[solver]\nx = 1\n", ["unknown section [solver]"]),
    "negative_density": (with_edit(GOOD, "rho0_kg_m3 = 1.0", "rho0_kg_m3 = -1.0"),
                         ["[fluid] rho0_kg_m3 = -1.0", "must be a number > 0"]),
    "zero_sound_speed": (with_edit(GOOD, "c0_m_s = 10.0", "c0_m_s = 0"), ["[fluid] c0_m_s = 0", "> 0"]),
    "string_for_int": (with_edit(GOOD, "nx = 50", 'nx = "fifty"'), ['[scene] nx = "fifty"', "an integer"]),
    "float_for_int": (with_edit(GOOD, "nx = 50", "nx = 50.5"), ["[scene] nx = 50.5", "an integer"]),
    "bad_kernel": (with_edit(GOOD, 'kernel = "wendland_c2"', 'kernel = "gaussian"'),
                   ['[numerics] kernel = "gaussian"', "one of"]),
    "bad_scene_type": (with_edit(GOOD, 'type = "taylor_green"', 'type = "dam_break"'),
                       ['[scene] type = "dam_break"', "one of"]),
    "wrong_vector_length": (with_edit(GOOD, "viscosity_Pa_s = 0.01", "viscosity_Pa_s = 0.01\ngravity_m_s2 = [0, 0, -9.81]"),
                            ["[fluid] gravity_m_s2 = [0, 0, -9.81]", "list of 2 numbers"]),
    "missing_required": (with_edit(GOOD, "nx = 50            # particles per side\n", ""),
                         ["missing required key [scene] nx"]),
    "bool_for_float": (with_edit(GOOD, "t_end_s = 1.0", "t_end_s = true"), ["[run] t_end_s = true", "a number"]),
    "negative_viscosity": (with_edit(GOOD, "viscosity_Pa_s = 0.01", "viscosity_Pa_s = -0.01"),
                           ["[fluid] viscosity_Pa_s = -0.01", ">= 0"]),
    "h_out_of_range": (with_edit(GOOD, "h_over_dx = 1.5", "h_over_dx = 4.0"), ["[numerics] h_over_dx = 4.0", "<= 2.5"]),
    "bad_dtype": (with_edit(GOOD, 'dtype = "float64"', 'dtype = "float16"'), ['[run] dtype = "float16"', "one of"]),
    "both_end_conditions": (with_edit(GOOD, "t_end_s = 1.0", "t_end_s = 1.0\nsteps = 10"),
                            ["give exactly one of t_end_s or steps"]),
    "box_too_small": (with_edit(GOOD, "nx = 50", "nx = 4"), ["[scene] nx gives 4 particles", "must be >="]),
    "not_toml": ("[scene\ntype = 1", ["not valid TOML"]),
    "wrong_dim": (with_edit(GOOD, "dim = 2", "dim = 3"), ["[scene] dim = 3", "taylor_green"]),
    "section_not_table": (with_edit(GOOD, "[run]\n", "run = 3\n[runx]\n"), ["run"]),
}


def test_good_cases_load():
    for case in sorted(p for p in CASES.iterdir() if (p / "case.toml").exists()):
        _, cfg = load_case(case)
        assert cfg["scene"]["type"] in {"taylor_green", "poiseuille", "hydrostatic_tank", "conduction_1d",
                                        "gaussian_bump", "block", "drop", "sessile_drop", "pendant_drop", "deposition"}
        if "preview" in load_raw(case)[1]:  # the preview variant is a valid case too
            load_case(case, preview=True)


def test_overrides_are_validated():
    _, cfg = load_case(CASES / "taylor_green_2d", ["scene.nx=64", "run.dtype=float32"])
    assert cfg["scene"]["nx"] == 64 and cfg["run"]["dtype"] == "float32"
    with pytest.raises(CaseError, match=r"\[scene\] nx = -3"):
        load_case(CASES / "taylor_green_2d", ["scene.nx=-3"])
    with pytest.raises(CaseError, match="expected section.key=value"):
        load_case(CASES / "taylor_green_2d", ["nx=3"])


def test_a_term_section_is_switched_off_by_enabled_false():
    """A term a case names (here [solid_contact] added by --set) is built unless ``enabled =
    false``; a non-boolean ``enabled`` is an error naming the section and the value."""
    case = CASES / "perpendicular_350W"
    _, on = load_case(case, ["solid_contact.stiffness=0.5"])
    assert on["solid_contact"]["stiffness"] == 0.5
    _, off = load_case(case, ["solid_contact.stiffness=0.5", "solid_contact.enabled=false"])
    assert "solid_contact" not in off
    _, still = load_case(case, ["solid_contact.enabled=true"])
    assert "solid_contact" in still and "enabled" not in still["solid_contact"]
    with pytest.raises(CaseError, match=r"\[solid_contact\] enabled = 3: expected true or false"):
        load_case(case, ["solid_contact.enabled=3"])


def test_cli_prints_one_line_and_exits_2(tmp_path):
    text, _ = BAD["negative_density"]
    (tmp_path / "case.toml").write_text(text)
    r = subprocess.run([sys.executable, "-m", "torchsph", str(tmp_path), "--quiet"], cwd=ROOT,
                       capture_output=True, text=True, timeout=120)
    assert r.returncode == 2
    lines = r.stderr.strip().splitlines()
    assert len(lines) == 1 and "Traceback" not in r.stderr
    assert lines[0].startswith("torchsph: error:") and "rho0_kg_m3 = -1.0" in lines[0]


THERMAL_GOOD = (CASES / "conduction_1d" / "case.toml").read_text()
BAD_THERMAL = {
    "negative_conductivity": (with_edit(THERMAL_GOOD, "conductivity_W_mK = 42.0", "conductivity_W_mK = -42.0"),
                              ["[thermal] conductivity_W_mK = -42.0", "> 0"]),
    "latent_without_solidus": (with_edit(THERMAL_GOOD, "specific_heat_J_kgK = 450.0",
                                         "specific_heat_J_kgK = 450.0\nlatent_heat_J_kg = 82000.0"),
                               ["missing required key [thermal] solidus_K"]),
    "liquidus_below_solidus": (with_edit(THERMAL_GOOD, "specific_heat_J_kgK = 450.0",
                                         "specific_heat_J_kgK = 450.0\nlatent_heat_J_kg = 1.0\n"
                                         "solidus_K = 1800.0\nliquidus_K = 1700.0"),
                               ["[thermal] liquidus_K = 1700.0", "must be > solidus_K"]),
    "missing_thermal": (THERMAL_GOOD.split("[thermal]")[0] + "[run]\nt_end_s = 0.1\n",
                        ["missing section [thermal]"]),
    "unknown_thermal_key": (with_edit(THERMAL_GOOD, "conductivity_W_mK = 42.0", "conductivity = 42.0"),
                            ["unknown key [thermal] conductivity", "allowed"]),
    "emissivity_above_one": (with_edit(THERMAL_GOOD, "specific_heat_J_kgK = 450.0",
                                       "specific_heat_J_kgK = 450.0\nemissivity = 1.5"),
                             ["[thermal] emissivity = 1.5", "<= 1"]),
    "negative_convection": (with_edit(THERMAL_GOOD, "specific_heat_J_kgK = 450.0",
                                      "specific_heat_J_kgK = 450.0\nconvection_W_m2K = -5.0"),
                            ["[thermal] convection_W_m2K = -5.0", ">= 0"]),
    "evaporation_not_bool": (with_edit(THERMAL_GOOD, "specific_heat_J_kgK = 450.0",
                                       "specific_heat_J_kgK = 450.0\nevaporation = 1"),
                             ["[thermal] evaporation = 1", "true or false"]),
    "phase_change_without_liquidus": (with_edit(THERMAL_GOOD, "specific_heat_J_kgK = 450.0",
                                                "specific_heat_J_kgK = 450.0\nphase_change = true\nsolidus_K = 1723.0"),
                                      ["missing required key [thermal] liquidus_K (phase_change = true)"]),
    "phase_change_without_fluid": (with_edit(THERMAL_GOOD, "specific_heat_J_kgK = 450.0",
                                             "specific_heat_J_kgK = 450.0\nphase_change = true\n"
                                             "solidus_K = 1723.0\nliquidus_K = 1753.0"),
                                   ["missing required key [fluid] c0_m_s (phase_change = true"]),
    "fluid_case_without_c0": (with_edit(GOOD, "c0_m_s = 10.0        # 10 U: Mach 0.1\n", ""),
                              ["missing required key [fluid] c0_m_s"]),
}


BEAM_GOOD = (CASES / "beam_plate" / "case.toml").read_text()
BAD_BEAM = {
    "negative_power": (with_edit(BEAM_GOOD, "power_W = 300.0", "power_W = -300.0"), ["[beam 0] power_W = -300.0", "> 0"]),
    "efficiency_above_one": (with_edit(BEAM_GOOD, "efficiency = 0.85", "efficiency = 1.2"),
                             ["[beam 0] efficiency = 1.2", "<= 1"]),
    "zero_direction": (with_edit(BEAM_GOOD, "direction = [0.7071067811865476, 0.0, -0.7071067811865476]",
                                 "direction = [0.0, 0.0, 0.0]"), ["[beam 0] direction", "non-zero"]),
    "aim_wrong_length": (with_edit(BEAM_GOOD, "aim_m = [0.0, 0.0, 0.0]", "aim_m = [0.0, 0.0]"),
                         ["[beam 0] aim_m = [0.0, 0.0]", "list of 3 numbers"]),
    "unknown_beam_key": (with_edit(BEAM_GOOD, "radius_m = 0.75e-3", "radius = 0.75e-3"), ["unknown key [beam 0] radius"]),
}


ALL_BAD = {**BAD, **BAD_THERMAL, **BAD_BEAM}


@pytest.mark.parametrize("name", sorted(ALL_BAD))
def test_malformed_case_one_line_error(name, tmp_path):
    text, parts = ALL_BAD[name]
    (tmp_path / "case.toml").write_text(text)
    with pytest.raises(CaseError) as e:
        load_case(tmp_path)
    msg = str(e.value)
    assert "\n" not in msg
    assert str(tmp_path / "case.toml") in msg
    for p in parts:
        assert p in msg, msg


def test_at_least_ten_distinct_malformed_cases():
    assert len(ALL_BAD) >= 10


def test_the_parameter_classes_are_filled_from_the_schema():
    """Each case key names the parameter it sets (Key.field); every field of the physics'
    parameter classes is set by one key (or by the named extras, or keeps a default that no
    case sets), and a case's values arrive unchanged."""
    from dataclasses import fields

    from torchsph.core.schema import params
    from torchsph.io.config import FLUID, SURFACE, THERMAL
    from torchsph.physics.enthalpy import ThermalParams
    from torchsph.physics.fluid import FluidParams
    from torchsph.physics.losses import SurfaceLosses
    from torchsph.physics.surface import SurfaceParams
    fixed = {FluidParams: {"density_diffusion", "shifting"}, SurfaceLosses: {"sticking"}}
    for cls, schema in ((FluidParams, FLUID), (ThermalParams, THERMAL), (SurfaceLosses, THERMAL),
                        (SurfaceParams, SURFACE)):
        named = {k.field for k in schema.values() if k.field}
        assert {f.name for f in fields(cls)} <= named | fixed.get(cls, set()), cls
    _, cfg = load_case(CASES / "thermocapillary_layer_2d")
    fp = params(FluidParams, cfg["fluid"], FLUID, density_diffusion=0.0, shifting=0.0)
    assert fp.rho0 == cfg["fluid"]["rho0_kg_m3"] and fp.eta == cfg["fluid"]["viscosity_Pa_s"]
    assert fp.gravity == tuple(cfg["fluid"]["gravity_m_s2"])
    sp = params(SurfaceParams, cfg["surface"], SURFACE)
    assert sp.dtension_dT == cfg["surface"]["dtension_dT_N_mK"] and sp.threshold == cfg["surface"]["threshold"]
