"""A simulation from a validated case: the scene, the physics it names (nothing else is built),
the decomposition's cut; a checkpoint put back into it; what it evaluates and skips."""
from __future__ import annotations

import math
from pathlib import Path

import torch

from torchsph.core.kernels import make_kernel
from torchsph.core.memory import keep_freed_blocks
from torchsph.core.schema import params
from torchsph.io.config import FLUID, NUMERICS, SURFACE, THERMAL
from torchsph.physics.beam import Beam
from torchsph.physics.enthalpy import ThermalParams
from torchsph.physics.fluid import FluidParams, WeaklyCompressibleFluid
from torchsph.physics.free_surface import ColourGradient
from torchsph.physics.losses import SurfaceLosses
from torchsph.physics.surface import SurfaceForces, SurfaceParams
from torchsph.physics.terms import TermContext
from torchsph.physics.terms import available as available_terms
from torchsph.physics.thermal import Conduction
from torchsph.scenes.builders import SCENES, Scene, build_scene, case_beams
from torchsph.step.active import ActiveSet
from torchsph.step.simulation import Simulation

DTYPES = {"float64": torch.float64, "float32": torch.float32}


def make_simulation(cfg: dict, dtype=None, device=None, compile=None,
                    scene: Scene | None = None, comm=None) -> tuple[Scene, Simulation]:
    """Scene and solver for a validated configuration (see :func:`config.load_case`); a
    study may pass the ``scene`` already built (and adjusted). ``comm``: a domain
    decomposition (``parallel.slab.SlabComm``); the scene is then built whole on every
    process and cut to this process's slab and halo."""
    keep_freed_blocks()
    run, fl = cfg["run"], cfg["fluid"]
    # (a run's config.json from before a numerics key was added: that key at its default)
    nm = {**{k: key.default for k, key in NUMERICS.items()}, **cfg["numerics"]}
    dtype = DTYPES[run["dtype"]] if dtype is None else dtype
    device = run["device"] if device is None else device
    if scene is None:
        scene = build_scene(cfg, dtype=dtype, device=device)
    dim = cfg["scene"]["dim"]
    h = nm["h_over_dx"] * scene.dx
    if comm is not None:
        from dataclasses import fields as dc_fields

        from torchsph.core.state import ParticleState
        whole = {f"state.{f.name}": getattr(scene.state, f.name) for f in dc_fields(scene.state)}
        local = comm.distribute(whole, first=True, domain=scene.domain)
        scene.state = ParticleState(**{k[6:]: v.to(scene.state.device) for k, v in local.items()})
    kernel = make_kernel(nm["kernel"], dim)
    compile = nm["compile"] if compile is None else compile
    fluid = thermal = None
    phase_change = "thermal" in cfg and cfg["thermal"]["phase_change"]
    if SCENES[cfg["scene"]["type"]].has_fluid or phase_change:
        prm = params(FluidParams, fl, FLUID, density_diffusion=nm["density_diffusion"], shifting=nm["shifting"])
        fluid = WeaklyCompressibleFluid(prm, kernel, h, scene.domain, compile=compile)
    # the free-surface stage: one colour gradient per step for the surface forces and losses
    colour = ColourGradient(kernel, h, scene.domain, cfg["surface"]["threshold"] if "surface" in cfg else 0.05,
                            compile=compile)
    if "thermal" in cfg:
        th = cfg["thermal"]
        tp = params(ThermalParams, th, THERMAL)
        k = torch.full((scene.state.n,), tp.conductivity, dtype=scene.state.dtype,
                       device=scene.state.device)
        beams = [Beam(b["power_W"], b["efficiency"], b["radius_m"], tuple(b["direction"]),
                      tuple(b["aim_m"]), tuple(b["velocity_m_s"])) for b in case_beams(cfg)]
        losses = params(SurfaceLosses, th, THERMAL)
        thermal = Conduction(tp, kernel, h, scene.domain, k, compile=compile, beams=beams, dx=scene.dx,
                             losses=losses, h_over_dx=nm["h_over_dx"], colour=colour)
        thermal.window = nm["conduction_window"]
        below = nm["conduction_window_below_K"]
        if below is None and tp.latent_heat > 0:
            below = losses.ambient + 0.5 * (tp.solidus - losses.ambient)
        thermal.slow_below = math.inf if below is None else below
    surface = None
    if "surface" in cfg and fluid is not None:
        sp = params(SurfaceParams, cfg["surface"], SURFACE)
        surface = SurfaceForces(sp, kernel, h, scene.domain, nm["h_over_dx"],
                                vapour_pressure=losses.vapour_pressure if thermal is not None else None,
                                compile=compile, colour=colour)
    # nothing moves in a scene without fluid (rigid solids at rest): no Verlet skin needed
    skin = nm["skin_over_dx"] * scene.dx if fluid is not None else 0.0
    active = None
    if nm["skip_cold_solid"] and thermal is not None:
        support = kernel.radius(h)
        active = ActiveSet(nm["active_tolerance_K"], cfg["thermal"]["ambient_K"], support, support + skin)
    ctx = TermContext(dx=scene.dx, h=h, kernel=kernel, domain=scene.domain, dim=dim, dtype=scene.state.dtype,
                      device=scene.state.device)
    terms = [term.from_case(cfg, ctx) for sec, term in available_terms().items() if sec in cfg]
    sim = Simulation(scene.state, fluid, scene.domain, skin=skin,
                     cfl=nm["cfl"], dt_fixed=nm["dt_s"], allow_unstable_dt=nm["allow_unstable_dt"],
                     max_compression=nm["max_compression"], dx=scene.dx,
                     damping_time=nm["damping_time_s"], thermal=thermal,
                     phase_change=(cfg["thermal"]["solidus_K"], cfg["thermal"]["liquidus_K"],
                                   cfg["thermal"]["mushy_drag_1_s"]) if phase_change else None,
                     surface=surface, active=active, feeder=scene.info.get("feeder"), escape=scene.info.get("escape"),
                     comm=comm, partial_rebuild=nm.get("partial_rebuild", True), terms=terms)
    if comm is not None:
        comm.check(sim)
    return scene, sim


def resume(sim: Simulation, path, cfg: dict, recorded: dict | None = None, branch: bool = False) -> dict:
    """Put a checkpoint into ``sim`` (state, clock, neighbour list, caches) and into the
    scene's wire feeder and escape box; returns the checkpoint's extras. ``branch``: the
    case's physics may differ from the checkpoint's (:func:`torchsph.io.checkpoint.check_case`)."""
    from torchsph.io import checkpoint as ckpt

    extra = ckpt.restore(sim, ckpt.load(path), cfg, str(path), recorded, branch)
    if sim.feeder is not None and "feeder" in extra:
        sim.feeder.load_state_dict(extra["feeder"])
    if sim.escape is not None and "escape" in extra:
        sim.escape.load_state_dict(extra["escape"])
    return extra


def simulation_from_run(checkpoint: Path, numerics: dict | None = None, compile=None):
    """(cfg, sim): the simulation a run's checkpoint holds, built from the run's
    ``config.json`` beside it; ``numerics``: step-control keys to change (e.g.
    ``{"partial_rebuild": False}``)."""
    import json

    checkpoint = Path(checkpoint)
    cfg = json.loads((checkpoint.parent / "config.json").read_text())
    cfg.pop("case", None)
    cfg["numerics"].update(numerics or {})
    _, sim = make_simulation(cfg, compile=compile)
    resume(sim, checkpoint, cfg)
    return cfg, sim


def physics_plan(sim: Simulation) -> dict:
    """What the scene evaluates, and what it skips (terms it does not declare cost nothing)."""
    plan = {"momentum": sim.fluid_model is not None, "conduction": sim.thermal is not None}
    if sim.fluid_model is not None:
        prm = sim.fluid_model.prm
        plan.update({"viscosity": prm.eta > 0, "gravity": any(prm.gravity),
                     "density_diffusion": prm.density_diffusion > 0, "shifting": prm.shifting > 0})
    if sim.thermal is not None:
        L = sim.thermal.losses
        plan.update({"beams": len(sim.thermal.beams), "radiation": L.emissivity > 0,
                     "convection": L.convection > 0, "evaporation": L.evaporation,
                     "phase_change": sim.phase_change is not None})
    sf = sim.surface_model
    plan.update({"surface_tension": sf is not None and sf.prm.tension > 0,
                 "marangoni": sf is not None and sf.marangoni_on,
                 "recoil": sf is not None and sf.prm.recoil,
                 "active_set": (f"on (tolerance {sim.active_set.tol:g} K)" if sim.active_set is not None
                                else "off")})
    plan.update({term.section: term.plan() for term in sim.terms})
    return plan
