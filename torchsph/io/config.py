"""Case files: ``cases/NAME/case.toml``, read with tomllib and validated against a schema.

Every error is a :class:`CaseError` whose message is one line naming the key, the value
and what is allowed. The CLI prints it without a traceback.
"""
from __future__ import annotations

import copy
import math
import tomllib
from pathlib import Path

from torchsph.core.schema import REQUIRED, CaseError, Key  # noqa: F401 (re-exported)
from torchsph.physics.terms import available as available_terms


def _fmt(v) -> str:
    if isinstance(v, str):
        return repr(v).replace("'", '"')
    if isinstance(v, bool):
        return "true" if v else "false"
    return repr(v)


def _check_value(where: str, key: Key, v, dim: int | None):
    bad = f"{where} = {_fmt(v)}: must be {key.allowed()}"
    if key.kind == "bool":
        if not isinstance(v, bool):
            raise CaseError(bad)
        return v
    if key.kind == "str":
        if not isinstance(v, str) or (key.choices is not None and v not in key.choices):
            raise CaseError(bad)
        return v
    if key.kind == "strs":
        if not isinstance(v, list) or not all(isinstance(c, str) for c in v):
            raise CaseError(bad)
        return list(v)
    if key.kind == "vec":
        if (not isinstance(v, list) or not all(isinstance(c, (int, float)) and not isinstance(c, bool)
                                               for c in v)
                or not all(math.isfinite(c) for c in v)):
            raise CaseError(bad)
        if dim is not None and len(v) != dim:
            raise CaseError(f"{where} = {_fmt(v)}: must be a list of {dim} numbers (scene.dim = {dim})")
        return [float(c) for c in v]
    if key.kind == "int":
        if not isinstance(v, int) or isinstance(v, bool):
            raise CaseError(bad)
    elif key.kind == "float":
        if not isinstance(v, (int, float)) or isinstance(v, bool) or not math.isfinite(v):
            raise CaseError(bad)
        v = float(v)
    if key.choices is not None and v not in key.choices:
        raise CaseError(bad)
    if ((key.gt is not None and not v > key.gt) or (key.ge is not None and not v >= key.ge)
            or (key.lt is not None and not v < key.lt) or (key.le is not None and not v <= key.le)):
        raise CaseError(bad)
    return v


# keys that older versions accepted, with why they went
REMOVED = {"numerics.conduction_reuse": "multi-rate conduction: conduction is now evaluated at every step, "
                                        "a sparse operator that costs less than holding rates did"}


def validate_section(name: str, raw: dict, schema: dict[str, Key], dim: int | None = None) -> dict:
    if not isinstance(raw, dict):
        raise CaseError(f"[{name}] must be a table, got {_fmt(raw)}")
    unknown = sorted(set(raw) - set(schema))
    for k in unknown:
        if f"{name}.{k}" in REMOVED:
            raise CaseError(f"[{name}] {k} = {_fmt(raw[k])}: this key was removed ({REMOVED[f'{name}.{k}']}); "
                            "delete it from the case")
    if unknown:
        raise CaseError(f"unknown key [{name}] {unknown[0]} = {_fmt(raw[unknown[0]])} "
                        f"(allowed: {', '.join(schema)})")
    out = {}
    for k, key in schema.items():
        where = f"[{name}] {k}"
        if k not in raw:
            if key.default is REQUIRED:
                raise CaseError(f"missing required key {where} ({key.allowed()}; {key.doc})")
            out[k] = copy.deepcopy(key.default)
            if key.kind == "vec" and out[k] is None and dim is not None:
                out[k] = [0.0] * dim
            continue
        out[k] = _check_value(where, key, raw[k], dim)
    return out


# --- the common sections ------------------------------------------------------
FLUID = {
    "rho0_kg_m3": Key("float", gt=0, doc="reference density", field="rho0"),
    "c0_m_s": Key("float", default=None, gt=0,
                  doc="artificial speed of sound (Mach <= 0.1 of the flow); needed with fluid", field="c0"),
    "viscosity_Pa_s": Key("float", default=None, ge=0, doc="dynamic viscosity; needed with fluid", field="eta"),
    "gravity_m_s2": Key("vec", default=None, doc="gravity vector", field="gravity"),
    "gravity_ramp_s": Key("float", default=0.0, ge=0,
                          doc="gravity grows linearly from zero to gravity_m_s2 over this time, then holds "
                              "(a quasi-static load, e.g. until a pendant drop detaches; 0 = full from the start)",
                          field="gravity_ramp"),
    "body_force_m_s2": Key("vec", default=None, doc="extra body acceleration, e.g. a channel drive", field="body_force"),
    "gamma": Key("float", default=7.0, gt=0, doc="Tait exponent", field="gamma"),
    "background_pressure_Pa": Key("float", default=0.0, ge=0, doc="added to the Tait pressure", field="background_pressure"),
    "temperature_K": Key("float", default=300.0, gt=0, doc="initial temperature"),
}

NUMERICS = {
    "kernel": Key("str", default="wendland_c2", choices=("wendland_c2", "cubic_spline"),
                  doc="smoothing kernel"),
    "h_over_dx": Key("float", default=1.5, ge=1.0, le=2.5, doc="smoothing length / spacing"),
    "cfl": Key("float", default=0.25, gt=0, le=0.5, doc="acoustic CFL number"),
    "skin_over_dx": Key("float", default=0.5, ge=0, le=2.0,
                        doc="Verlet-list skin (0 = rebuild pairs every step)"),
    "density_diffusion": Key("float", default=0.0, ge=0, le=1.0,
                             doc="delta-SPH density diffusion coefficient (0 = off)"),
    "shifting": Key("float", default=0.0, ge=0, le=1.0,
                    doc="particle-shifting coefficient C (dr = -C h^2 grad C_i; 0 = off)"),
    "compile": Key("bool", default=False,
                   doc="fuse the pair loops with torch.compile (faster; first steps compile)"),
    "damping_time_s": Key("float", default=0.0, ge=0,
                          doc="settling time: velocities are damped for t < this (0 = off)"),
    "dt_s": Key("float", default=None, gt=0, doc="fixed time step (omit for automatic)"),
    "allow_unstable_dt": Key("bool", default=False, doc="accept a fixed dt above a stability limit"),
    "max_compression": Key("float", default=0.3, gt=0, lt=1,
                           doc="|rho/rho0 - 1| above which the run stops as blown up"),
    "skip_cold_solid": Key("bool", default=True,
                           doc="leave solid within active_tolerance_K of ambient out of the work (--no-skip: false)"),
    "partial_rebuild": Key("bool", default=True,
                           doc="neighbour rebuilds keep the largest rigid body's mutual pairs and search "
                               "only the other rows (false: full rebuilds)"),
    "rebalance_every": Key("int", default=10, ge=0,
                           doc="MPI: move slab boundaries to equal measured cost every this many migrations (0 = never)"),
    "migration_slack_over_skin": Key("float", default=4.0, ge=0, le=20.0,
                                     doc="MPI: halo slack, in Verlet skins, for the motion between migrations; a "
                                         "rebuild migrates once a particle moved half of it (0 = every rebuild)"),
    "active_tolerance_K": Key("float", default=1.0, gt=0,
                              doc="|T - ambient| below which solid far from heat is left out"),
    "conduction_window": Key("float", default=0.0, ge=0, le=0.5,
                             doc="steady solid far from melt, beams and the hot zone sums its conduction pairs "
                                 "once per window of this share of the thermal limit (0 = every step; one process)"),
    "conduction_window_below_K": Key("float", default=None, gt=0,
                                     doc="only solid colder than this waits for the window (default: halfway "
                                         "from ambient to solidus)"),
}

RUN = {
    "t_end_s": Key("float", default=None, gt=0, doc="simulated end time"),
    "steps": Key("int", default=None, gt=0, doc="number of steps (instead of t_end_s)"),
    "output_interval_s": Key("float", default=None, gt=0,
                             doc="time between snapshots (default: t_end / 10)"),
    "dtype": Key("str", default="float64", choices=("float64", "float32"), doc="float precision"),
    "device": Key("str", default="cpu", choices=("cpu", "cuda"), doc="torch device"),
    "fields": Key("strs", default=[], doc="per-particle arrays of the physics added to every snapshot, by "
                                          "output name (e.g. \"curvature\", \"enthalpy_rate\", \"surface_area\") "
                                          "or registry name (e.g. \"sf.kappa\"); the run says which the case offers"),
}

THERMAL = {
    "conductivity_W_mK": Key("float", gt=0, doc="thermal conductivity", field="conductivity"),
    "specific_heat_J_kgK": Key("float", gt=0, doc="specific heat c_p", field="specific_heat"),
    "latent_heat_J_kg": Key("float", default=0.0, ge=0, doc="latent heat of melting h_f", field="latent_heat"),
    "solidus_K": Key("float", default=None, gt=0, doc="solidus T_S (with latent heat)", field="solidus"),
    "liquidus_K": Key("float", default=None, gt=0, doc="liquidus T_L (with latent heat)", field="liquidus"),
    "phase_change": Key("bool", default=False,
                        doc="solid particles melt into the fluid above T_L, melt solidifies below T_S"),
    "mushy_drag_1_s": Key("float", default=1.0e4, ge=0,
                          doc="Carman-Kozeny drag C (1 - phi)^2 / (phi^3 + 1e-3) in the mushy zone, 1/s"),
    "ambient_K": Key("float", default=300.0, gt=0, doc="ambient temperature T0 of the surface losses", field="ambient"),
    "emissivity": Key("float", default=0.0, ge=0, le=1, doc="radiation sigma eps (T^4 - T0^4); 0 = off", field="emissivity"),
    "convection_W_m2K": Key("float", default=0.0, ge=0, doc="convection q_h (T - T0); 0 = off (vacuum)", field="convection"),
    "evaporation": Key("bool", default=False, doc="evaporation loss m_v [h_v + h(T)] (2.10)", field="evaporation"),
    "boiling_point_K": Key("float", default=3090.0, gt=0, doc="T_v of the vapour pressure (2.6)", field="boiling_point"),
    "evaporation_heat_J_kg": Key("float", default=6.1e6, gt=0, doc="latent heat of evaporation h_v", field="evaporation_heat"),
    "molar_mass_kg_mol": Key("float", default=0.0558, gt=0, doc="molar mass M", field="molar_mass"),
    "ambient_pressure_Pa": Key("float", default=101325.0, gt=0, doc="p_a in C_p = 0.54 p_a", field="ambient_pressure"),
}

BEAM = {
    "power_W": Key("float", gt=0, doc="beam power Q0 (per beam)"),
    "efficiency": Key("float", default=0.85, gt=0, le=1, doc="absorbed fraction eta0"),
    "radius_m": Key("float", gt=0, doc="1/e^2 radius of the Gaussian spot"),
    "direction": Key("vec", doc="propagation direction e_src (normalised)"),
    "aim_m": Key("vec", doc="a point on the beam axis at t = 0"),
    "velocity_m_s": Key("vec", default=None, doc="velocity of the aim point"),
}

SURFACE = {
    "tension_N_m": Key("float", default=0.0, ge=0, doc="surface tension alpha0 at reference_temperature_K", field="tension"),
    "dtension_dT_N_mK": Key("float", default=0.0, doc="d alpha / dT (negative for steel)", field="dtension_dT"),
    "reference_temperature_K": Key("float", default=300.0, gt=0, doc="T0 of alpha(T) = alpha0 + alpha' (T - T0)", field="reference_temperature"),
    "marangoni": Key("bool", default=True, doc="the tangential (Marangoni) force (with dtension_dT_N_mK != 0)", field="marangoni"),
    "recoil": Key("bool", default=False, doc="recoil pressure p_v(T) (2.6); vapour law from [thermal]", field="recoil"),
    "threshold": Key("float", default=0.05, gt=0, lt=1,
                     doc="|grad c| h above which a particle is on the free surface", field="threshold"),
    "zero_net_force": Key("bool", default=False,
                          doc="remove the discrete surface forces' resultant (a free body of liquid "
                              "only, e.g. a drop: on a closed surface the continuum forces have none)", field="zero_net_force"),
    "contact_angle_deg": Key("float", default=None, gt=0, lt=180,
                             doc="equilibrium contact angle theta_eq between melt and solid or wall "
                                 "(Young's force at the contact line; omit: no wetting model, "
                                 "a melt/solid contact is not a surface)", field="contact_angle"),
    "band_curvature": Key("str", default="clear", choices=("beside", "clear"),
                          doc="the curvature the contact band's tension takes: 'clear' (the default), "
                              "the surface particles beside the band with no solid in their support, "
                              "'beside' where the solid turns (an edge); 'beside', all the surface "
                              "particles beside the band (before stop 51: a receding 3-D cap stops 6-13 "
                              "deg short, docs/VERIFICATION.md)",
                          field="band_curvature"),
    "wetting": Key("bool", default=True,
                   doc="false: contact_angle_deg is ignored (the thesis's model, c = 1 in melt and solid), "
                       "e.g. to compare with a version before the wetting model", field="wetting"),
}

CORE = ("scene", "fluid", "thermal", "beam", "surface", "numerics", "run", "preview")


def sections() -> tuple[str, ...]:
    """Every section a case may hold: the core ones and one per registered term."""
    return CORE + tuple(available_terms())


def _set_dotted(raw: dict, dotted: str, value_text: str):
    parts = dotted.strip().split(".")
    if len(parts) != 2 or not all(parts):
        raise CaseError(f"--set {dotted}: expected section.key=value, e.g. run.t_end_s=0.5")
    try:
        value = tomllib.loads(f"v = {value_text}")["v"]
    except tomllib.TOMLDecodeError:
        value = value_text
    raw.setdefault(parts[0], {})
    if isinstance(raw[parts[0]], list) and all(isinstance(t, dict) for t in raw[parts[0]]):
        for t in raw[parts[0]]:  # an array of tables ([[beam]]): the key is set in every one
            t[parts[1]] = value
        return
    if not isinstance(raw[parts[0]], dict):
        raise CaseError(f"--set {dotted}: [{parts[0]}] is not a table")
    raw[parts[0]][parts[1]] = value


def apply_overrides(raw: dict, overrides: list[str] | None) -> dict:
    raw = copy.deepcopy(raw)
    for item in overrides or []:
        if "=" not in item:
            raise CaseError(f"--set {item}: expected section.key=value")
        k, v = item.split("=", 1)
        _set_dotted(raw, k, v)
    return raw


def load_raw(case_dir: str | Path) -> tuple[Path, dict]:
    p = Path(case_dir)
    path = p / "case.toml" if p.is_dir() else p
    if not path.exists():
        raise CaseError(f"{path}: no such case file (a case is a folder with case.toml)")
    try:
        with open(path, "rb") as f:
            return path, tomllib.load(f)
    except tomllib.TOMLDecodeError as e:
        raise CaseError(f"{path}: not valid TOML: {e}") from None


def validate(raw: dict) -> dict:
    """Validate a raw case dict; returns the resolved configuration (defaults filled)."""
    from torchsph.scenes.builders import SCENES

    raw = {k: v for k, v in raw.items() if k != "preview"}  # applied by load_case(preview=True)
    top = sections()
    unknown = sorted(set(raw) - set(top))
    if unknown:
        raise CaseError(f"unknown section [{unknown[0]}] (allowed: {', '.join(top)})")
    for sec in ("scene", "fluid", "run"):
        if sec not in raw:
            raise CaseError(f"missing section [{sec}]")
    scene_raw = raw["scene"]
    if not isinstance(scene_raw, dict):
        raise CaseError(f"[scene] must be a table, got {_fmt(scene_raw)}")
    stype = scene_raw.get("type")
    if stype not in SCENES:
        raise CaseError(f"[scene] type = {_fmt(stype)}: must be one of "
                        + ", ".join(repr(s) for s in SCENES))
    spec = SCENES[stype]
    dim = scene_raw.get("dim", spec.dims[0])
    if dim not in spec.dims or isinstance(dim, bool):
        raise CaseError(f"[scene] dim = {_fmt(dim)}: must be one of {', '.join(map(str, spec.dims))} "
                        f"for scene type {stype!r}")
    schema = {"type": Key("str", choices=tuple(SCENES)), "dim": Key("int", default=spec.dims[0]),
              **spec.schema}
    cfg = {"scene": validate_section("scene", scene_raw, schema, dim),
           "fluid": validate_section("fluid", raw["fluid"], FLUID, dim),
           "numerics": validate_section("numerics", _with_defaults(raw.get("numerics", {}), spec.numerics),
                                        NUMERICS, dim),
           "run": validate_section("run", raw["run"], RUN, dim)}
    nm = cfg["numerics"]
    if nm["shifting"] > 0:  # above its stability limit the shift amplifies the lattice's shortest waves
        from torchsph.physics.fluid import shifting_limit
        lim = shifting_limit(nm["kernel"], dim, nm["h_over_dx"])
        if nm["shifting"] > lim:
            raise CaseError(f"[numerics] shifting = {_fmt(nm['shifting'])}: above the shift's stability limit "
                            f"{math.floor(lim * 100) / 100:g} for {nm['kernel']} at h_over_dx = {_fmt(nm['h_over_dx'])} "
                            f"in {dim}-D (there it amplifies the particles' displacements step by step): "
                            f"must be <= {math.floor(lim * 100) / 100:g}")
    if spec.has_fluid:
        for key in ("c0_m_s", "viscosity_Pa_s"):
            if cfg["fluid"][key] is None:
                raise CaseError(f"missing required key [fluid] {key} ({FLUID[key].allowed()}; "
                                f"{FLUID[key].doc}) for scene type {stype!r}")
    if spec.needs_thermal and "thermal" not in raw:
        raise CaseError(f"missing section [thermal] (scene type {stype!r} solves the energy equation)")
    if "beam" in raw:
        beams = raw["beam"]
        if not isinstance(beams, list) or not all(isinstance(b, dict) for b in beams):
            raise CaseError("beam must be an array of tables ([[beam]] ... )")
        if "thermal" not in raw:
            raise CaseError("[[beam]] needs a [thermal] section (beams heat through the energy equation)")
        if dim != 3:
            raise CaseError(f"[[beam]] needs a 3-D scene (scene.dim = {dim})")
        cfg["beam"] = []
        for k, b in enumerate(beams):
            bb = validate_section(f"beam {k}", b, BEAM, dim)
            if not any(bb["direction"]):
                raise CaseError(f"[beam {k}] direction = {bb['direction']}: must be a non-zero vector")
            cfg["beam"].append(bb)
    if "thermal" in raw:
        th = cfg["thermal"] = validate_section("thermal", raw["thermal"], THERMAL, dim)
        if th["latent_heat_J_kg"] > 0:
            for key in ("solidus_K", "liquidus_K"):
                if th[key] is None:
                    raise CaseError(f"missing required key [thermal] {key} (latent_heat_J_kg > 0)")
        if th["phase_change"]:
            for key in ("solidus_K", "liquidus_K"):
                if th[key] is None:
                    raise CaseError(f"missing required key [thermal] {key} (phase_change = true)")
            for key in ("c0_m_s", "viscosity_Pa_s"):
                if cfg["fluid"][key] is None:
                    raise CaseError(f"missing required key [fluid] {key} (phase_change = true: "
                                    "melted particles are fluid)")
        if th["solidus_K"] is not None and th["liquidus_K"] is not None:
            if not th["liquidus_K"] > th["solidus_K"]:
                raise CaseError(f"[thermal] liquidus_K = {th['liquidus_K']}: must be > solidus_K = "
                                f"{th['solidus_K']}")
    if "surface" in raw:
        su = cfg["surface"] = validate_section("surface", raw["surface"], SURFACE, dim)
        if not (spec.has_fluid or cfg.get("thermal", {}).get("phase_change")):
            raise CaseError(f"[surface] needs fluid particles (scene type {stype!r} has none; "
                            "set [thermal] phase_change = true to melt it)")
        for key in ("c0_m_s", "viscosity_Pa_s"):
            if cfg["fluid"][key] is None:
                raise CaseError(f"missing required key [fluid] {key} ({FLUID[key].allowed()}) "
                                "for [surface] forces")
        if su["recoil"] and "thermal" not in raw:
            raise CaseError("[surface] recoil = true needs a [thermal] section (the vapour "
                            "pressure p_v(T) uses boiling_point_K, evaporation_heat_J_kg, molar_mass_kg_mol)")
        if su["tension_N_m"] == 0 and su["dtension_dT_N_mK"] == 0 and not su["recoil"]:
            raise CaseError("[surface] declares no force: set tension_N_m > 0, dtension_dT_N_mK != 0 "
                            "or recoil = true (or remove the section)")
    for sec, term in available_terms().items():  # the composable terms a case names
        if sec not in raw:
            continue
        body = dict(raw[sec])
        on = body.pop("enabled", True)  # a case's term turned off without editing the file
        if not isinstance(on, bool):
            raise CaseError(f"[{sec}] enabled = {on!r}: expected true or false")
        if not on:
            continue
        cfg[sec] = validate_section(sec, body, term.schema, dim)
        for need in term.needs:
            if need not in raw:
                raise CaseError(f"[{sec}] needs a [{need}] section ({term.doc})")
        term.check(cfg)
    run = cfg["run"]
    if (run["t_end_s"] is None) == (run["steps"] is None):
        raise CaseError("[run]: give exactly one of t_end_s or steps "
                        f"(got t_end_s = {_fmt(run['t_end_s'])}, steps = {_fmt(run['steps'])})")
    if spec.check is not None:
        spec.check(cfg)
    return cfg


def _with_defaults(section, defaults: dict):
    """A case's table over a scene's own defaults (a malformed table is left to the validator)."""
    return {**defaults, **section} if isinstance(section, dict) else section


def preview_overrides(raw: dict) -> list[str]:
    """The case's ``[preview]`` table ("section.key" = value) as --set overrides."""
    pv = raw.get("preview")
    if pv is None:
        raise CaseError("--preview: the case has no [preview] table (\"section.key\" = value, e.g. "
                        "\"scene.dx_m\" = 2.5e-4)")
    if not isinstance(pv, dict):
        raise CaseError(f"[preview] must be a table, got {_fmt(pv)}")
    out = []
    for k, v in pv.items():
        if isinstance(v, dict):  # a dotted key parsed as a nested table: scene.dx_m = ...
            out += [f"{k}.{kk}={_toml(vv)}" for kk, vv in v.items()]
        else:
            out.append(f"{k}={_toml(v)}")
    return out


def _toml(v) -> str:
    if isinstance(v, bool):
        return "true" if v else "false"
    if isinstance(v, str):
        return '"' + v + '"'
    if isinstance(v, list):
        return "[" + ", ".join(_toml(c) for c in v) + "]"
    return repr(v)


def load_case(case_dir: str | Path, overrides: list[str] | None = None,
              preview: bool = False) -> tuple[Path, dict]:
    """Read, override and validate a case; errors name the file. ``preview`` applies the
    case's [preview] overrides first (the command line's come after them)."""
    path, raw = load_raw(case_dir)
    try:
        if preview:
            raw = apply_overrides(raw, preview_overrides(raw))
        if not overrides:
            return path, validate(raw)
        validate(raw)  # the file (with its [preview]) alone: its errors name the file
    except CaseError as e:
        raise CaseError(f"{path}: {e}") from None
    try:
        return path, validate(apply_overrides(raw, overrides))
    except CaseError as e:  # the file was valid: the command line's values are wrong
        msg = str(e)
        if msg.startswith("--set"):
            raise
        named = [o for o in overrides if "=" in o and _names_key(msg, o.split("=", 1)[0])]
        raise CaseError(f"--set {' '.join(named or overrides)}: {msg}") from None


def _names_key(msg: str, dotted: str) -> bool:
    """Whether an error message is about the override ``section.key``."""
    sec, _, key = dotted.strip().partition(".")
    return bool(key) and key in msg and sec in msg
