"""Scene builders: a case's ``[scene]`` table turned into particles and a domain.

Each scene declares its keys (validated in :mod:`torchsph.io.config`), the dimensions it
supports, a cross-key check, and a builder. No code per case: cases are TOML only.
"""
from __future__ import annotations

import math

import numpy as np
import torch

from torchsph.core.analytic import gaussian_bump_exact, taylor_green_exact
from torchsph.core.lattice import Scene, SceneSpec, lattice, solid_block, tait_density  # noqa: F401 (re-exported)
from torchsph.core.neighbors import Domain
from torchsph.core.schema import CaseError, Key
from torchsph.core.state import ParticleState, Phase
from torchsph.scenes import deposition


def _support_cells(cfg) -> float:
    """Search radius (kernel support + skin) in units of dx."""
    nm = cfg["numerics"]
    return 2.0 * nm["h_over_dx"] + nm["skin_over_dx"]


def _need_periodic_span(cfg, n_cells: int, key: str):
    need = 2.0 * _support_cells(cfg)
    if n_cells < need:
        raise CaseError(f"[scene] {key} gives {n_cells} particles along a periodic axis: must be "
                        f">= {math.ceil(need)} (two kernel supports plus skin at h_over_dx = "
                        f"{cfg['numerics']['h_over_dx']:g})")


def _need_wall_layers(cfg):
    need = math.ceil(2.0 * cfg["numerics"]["h_over_dx"])
    if cfg["scene"]["wall_layers"] < need:
        raise CaseError(f"[scene] wall_layers = {cfg['scene']['wall_layers']}: must be >= {need} "
                        f"(walls must fill the kernel support of 2 h = "
                        f"{2 * cfg['numerics']['h_over_dx']:g} dx)")


# --- Taylor-Green vortex -------------------------------------------------------
def build_taylor_green(cfg, dtype, device) -> Scene:
    sc, fl = cfg["scene"], cfg["fluid"]
    L, nx, U = sc["length_m"], sc["nx"], sc["U_m_s"]
    dx = L / nx
    x = lattice((nx, nx), dx, dtype=dtype, device=device)
    v = taylor_green_exact(x, 0.0, L, U, 0.0)
    k = 2.0 * math.pi / L
    rho0 = fl["rho0_kg_m3"]
    p = -0.25 * rho0 * U * U * (torch.cos(2 * k * x[:, 0]) + torch.cos(2 * k * x[:, 1]))
    p = p + fl["background_pressure_Pa"]
    rho = tait_density(p, fl)
    m = rho0 * dx * dx
    st = ParticleState.create(x, v, rho, m, Phase.FLUID, T=fl["temperature_K"], p=p,
                              dtype=dtype, device=device)
    nu = fl["viscosity_Pa_s"] / rho0
    return Scene(st, Domain([0.0, 0.0], [L, L], [True, True]), dx,
                 {"L": L, "U": U, "nu": nu, "Re": U * L / nu if nu > 0 else float("inf")})


def check_taylor_green(cfg):
    _need_periodic_span(cfg, cfg["scene"]["nx"], "nx")


# --- Poiseuille channel ----------------------------------------------------------
def wall_slabs(nx_len, layers, dx, H, dtype, device):
    below = lattice((nx_len, layers), dx, origin=(0.0, -layers * dx), dtype=dtype, device=device)
    above = lattice((nx_len, layers), dx, origin=(0.0, H), dtype=dtype, device=device)
    return torch.cat([below, above])


def build_poiseuille(cfg, dtype, device) -> Scene:
    sc, fl = cfg["scene"], cfg["fluid"]
    H, ny, layers = sc["height_m"], sc["n_height"], sc["wall_layers"]
    dx = H / ny
    nxl = round(sc["length_m"] / dx)
    Lx = nxl * dx
    xf = lattice((nxl, ny), dx, dtype=dtype, device=device)
    xw = wall_slabs(nxl, layers, dx, H, dtype, device)
    rho0 = fl["rho0_kg_m3"]
    fluid = ParticleState.create(xf, torch.zeros_like(xf), rho0, rho0 * dx * dx, Phase.FLUID,
                                 T=fl["temperature_K"], dtype=dtype, device=device)
    wall = ParticleState.create(xw, torch.zeros_like(xw), rho0, rho0 * dx * dx, Phase.WALL,
                                T=fl["temperature_K"], id=torch.arange(xw.shape[0]) + xf.shape[0],
                                dtype=dtype, device=device)
    st = ParticleState.cat([fluid, wall])
    lo_y, hi_y = -layers * dx, H + layers * dx
    nu = fl["viscosity_Pa_s"] / rho0
    F = fl["body_force_m_s2"][0]
    return Scene(st, Domain([0.0, lo_y], [Lx, hi_y], [True, False]), dx,
                 {"H": H, "F": F, "nu": nu, "u_max": F * H * H / (8 * nu) if nu > 0 else math.inf})


def check_poiseuille(cfg):
    sc = cfg["scene"]
    ny = sc["n_height"]
    nxl = round(sc["length_m"] / (sc["height_m"] / ny))
    _need_periodic_span(cfg, nxl, "length_m")
    _need_wall_layers(cfg)
    if cfg["fluid"]["viscosity_Pa_s"] <= 0:
        raise CaseError("[fluid] viscosity_Pa_s = 0.0: must be > 0 for a Poiseuille channel")


# --- hydrostatic tank -----------------------------------------------------------
def build_hydrostatic_tank(cfg, dtype, device) -> Scene:
    sc, fl = cfg["scene"], cfg["fluid"]
    d = sc["dim"]
    D, nd, layers = sc["fluid_depth_m"], sc["n_depth"], sc["wall_layers"]
    dx = D / nd
    nw = round(sc["fluid_width_m"] / dx)
    nl = round(sc["fluid_length_m"] / dx) if sc["fluid_length_m"] is not None else nw
    nt = round(sc["tank_height_m"] / dx)
    horiz = [nl] + [nw] * (d - 2)  # x (length), then y (width) in 3-D
    counts = horiz + [nd]
    xf = lattice(counts, dx, dtype=dtype, device=device)
    # walls: a box of particles (n + 2 layers) per horizontal axis x (nt + layers), minus the interior
    box = lattice([n + 2 * layers for n in horiz] + [nt + layers], dx,
                  origin=[-layers * dx] * d, dtype=dtype, device=device)
    inside = torch.ones(box.shape[0], dtype=torch.bool, device=device)
    for a in range(d - 1):
        inside &= (box[:, a] > 0) & (box[:, a] < horiz[a] * dx)
    inside &= box[:, d - 1] > 0
    xw = box[~inside]
    g = fl["gravity_m_s2"]
    gz = -g[d - 1]
    rho0 = fl["rho0_kg_m3"]
    # hydrostatic equilibrium from the start: a particle whose lattice height is z0 carries
    # the weight of the fluid above it, p = rho0 g (D - z0), so rho = rho_Tait(p); its
    # height is compressed to match, z(z0) = int_0^z0 rho0 / rho(s) ds.
    z0 = xf[:, d - 1].clone()
    p = rho0 * gz * (D - z0) + fl["background_pressure_Pa"]
    rho = tait_density(p, fl)
    s = torch.linspace(0.0, D, 4001, dtype=torch.float64)
    inv = rho0 / tait_density(rho0 * gz * (D - s) + fl["background_pressure_Pa"], fl)
    zs = torch.cat([torch.zeros(1, dtype=torch.float64),
                    torch.cumsum(0.5 * (inv[1:] + inv[:-1]) * (s[1:] - s[:-1]), 0)])
    xf[:, d - 1] = torch.as_tensor(np.interp(z0.cpu().numpy(), s.numpy(), zs.numpy()),
                                   dtype=dtype, device=device)
    fluid = ParticleState.create(xf, torch.zeros_like(xf), rho, rho0 * dx**d, Phase.FLUID,
                                 T=fl["temperature_K"], p=p, dtype=dtype, device=device)
    wall = ParticleState.create(xw, torch.zeros_like(xw), rho0, rho0 * dx**d, Phase.WALL,
                                T=fl["temperature_K"], id=torch.arange(xw.shape[0]) + xf.shape[0],
                                dtype=dtype, device=device)
    lo = [-layers * dx] * d
    hi = [(n + layers) * dx for n in horiz] + [nt * dx]
    return Scene(ParticleState.cat([fluid, wall]), Domain(lo, hi, [False] * d), dx,
                 {"depth": D, "g": gz, "rho0": rho0, "z0": z0, "n_fluid": xf.shape[0]})


def check_hydrostatic_tank(cfg):
    sc, fl = cfg["scene"], cfg["fluid"]
    d = sc["dim"]
    g = fl["gravity_m_s2"]
    if not g[d - 1] < 0 or any(c != 0 for c in g[:d - 1]):
        raise CaseError(f"[fluid] gravity_m_s2 = {g}: a hydrostatic tank needs gravity along "
                        "-z only (last component < 0)")
    if sc["tank_height_m"] < sc["fluid_depth_m"]:
        raise CaseError(f"[scene] tank_height_m = {sc['tank_height_m']}: must be >= fluid_depth_m "
                        f"= {sc['fluid_depth_m']}")
    _need_wall_layers(cfg)


# --- thermal verification scenes --------------------------------------------------
def _cross_section(cfg) -> int:
    """Particles across a periodic cross-section: two search radii, rounded up."""
    return math.ceil(2.0 * _support_cells(cfg)) + 1


def build_conduction_1d(cfg, dtype, device) -> Scene:
    sc, fl = cfg["scene"], cfg["fluid"]
    d, L, nx, layers = sc["dim"], sc["length_m"], sc["nx"], sc["wall_layers"]
    dx = L / nx
    nc = _cross_section(cfg)
    xs = lattice([nx] + [nc] * (d - 1), dx, dtype=dtype, device=device)
    xw = lattice([layers] + [nc] * (d - 1), dx, origin=[-layers * dx] + [0.0] * (d - 1),
                 dtype=dtype, device=device)
    solid = solid_block(xs, fl, dx, d, sc["initial_temperature_K"], dtype, device)
    wall = solid_block(xw, fl, dx, d, sc["face_temperature_K"], dtype, device, id0=xs.shape[0],
                  phase=Phase.WALL)
    lo = [-layers * dx] + [0.0] * (d - 1)
    hi = [L] + [nc * dx] * (d - 1)
    th = cfg["thermal"]
    alpha = th["conductivity_W_mK"] / (fl["rho0_kg_m3"] * th["specific_heat_J_kgK"])
    return Scene(ParticleState.cat([solid, wall]), Domain(lo, hi, [False] + [True] * (d - 1)), dx,
                 {"alpha": alpha, "T_face": sc["face_temperature_K"], "T0": sc["initial_temperature_K"],
                  "L": L})


def build_gaussian_bump(cfg, dtype, device) -> Scene:
    sc, fl = cfg["scene"], cfg["fluid"]
    d, L, nx = sc["dim"], sc["length_m"], sc["nx"]
    dx = L / nx
    x = lattice([nx] * d, dx, dtype=dtype, device=device)
    dom = Domain([0.0] * d, [L] * d, [True] * d)
    th = cfg["thermal"]
    alpha = th["conductivity_W_mK"] / (fl["rho0_kg_m3"] * th["specific_heat_J_kgK"])
    center = [0.5 * L] * d
    T = gaussian_bump_exact(x, 0.0, alpha, center, sc["sigma_m"], sc["amplitude_K"],
                            sc["background_K"], dom)
    return Scene(solid_block(x, fl, dx, d, T, dtype, device), dom, dx,
                 {"alpha": alpha, "center": center, "sigma": sc["sigma_m"], "A": sc["amplitude_K"],
                  "Tb": sc["background_K"]})


def check_gaussian_bump(cfg):
    _need_periodic_span(cfg, cfg["scene"]["nx"], "nx")
    sc = cfg["scene"]
    if sc["sigma_m"] > sc["length_m"] / 8:
        raise CaseError(f"[scene] sigma_m = {sc['sigma_m']}: must be <= length_m / 8 = "
                        f"{sc['length_m'] / 8:g} so that periodic images stay negligible")


def build_block(cfg, dtype, device) -> Scene:
    """A rigid, heat-conducting block of lattice particles, its top face at z = 0 and
    centred on the origin in x and y."""
    sc, fl = cfg["scene"], cfg["fluid"]
    dx = sc["dx_m"]
    size = sc["size_m"]
    counts = [max(round(s / dx), 1) for s in size]
    origin = [-counts[0] * dx / 2, -counts[1] * dx / 2, -counts[2] * dx]
    x = lattice(counts, dx, origin=origin, dtype=dtype, device=device)
    if sc["shape"] == "sphere":  # the ball inscribed in the box
        c = torch.tensor([0.0, 0.0, -counts[2] * dx / 2], dtype=dtype, device=device)
        x = x[((x - c) ** 2).sum(-1) < (0.5 * min(counts) * dx) ** 2]
    st = solid_block(x, fl, dx, 3, sc["temperature_K"], dtype, device)
    st.v[:] = torch.as_tensor(sc["velocity_m_s"], dtype=dtype, device=device)  # rigid motion
    st.body[:] = 1  # the block is body 1
    lo = origin
    hi = [o + c * dx for o, c in zip(origin, counts)]
    per = [sc["periodic_xy"], sc["periodic_xy"], False]
    return Scene(st, Domain(lo, hi, per), dx, {"counts": counts})


def build_drop(cfg, dtype, device) -> Scene:
    """A free liquid drop centred on the origin: a disc/ball of diameter ``size_m`` or a
    square/cube of side ``size_m`` cut from the lattice, at rest or with the velocity of
    the mode-2 oscillation u = U0 (x, -y) / R (2-D) or U0 (x, y, -2 z) / R (3-D)."""
    sc, fl = cfg["scene"], cfg["fluid"]
    d, dx, L = sc["dim"], sc["dx_m"], sc["size_m"]
    n = max(round(L / dx), 1)
    x = lattice([n] * d, dx, origin=[-n * dx / 2] * d, dtype=dtype, device=device)
    if sc["shape"] == "ball":
        x = x[(x * x).sum(-1) < (n * dx / 2) ** 2]
    R = n * dx / 2
    v = torch.zeros_like(x)
    U0 = sc["mode2_velocity_m_s"]
    if U0:
        sgn = [1.0, -1.0] if d == 2 else [1.0, 1.0, -2.0]
        v = U0 / R * x * torch.tensor(sgn, dtype=dtype, device=device)
    rho0 = fl["rho0_kg_m3"]
    st = ParticleState.create(x, v, rho0, rho0 * dx**d, Phase.FLUID, T=fl["temperature_K"],
                              dtype=dtype, device=device)
    span = 2.0 * L
    return Scene(st, Domain([-span] * d, [span] * d, [False] * d), dx, {"R": R, "side": n * dx})


def build_sessile_drop(cfg, dtype, device) -> Scene:
    """A liquid cap on a flat plate: the plate's top face at the last axis = 0, centred on the
    origin; the cap is the part above the plate of a disc/ball of radius ``radius_m`` whose
    centre lies at -R cos(initial_angle) (90 deg: a half disc / hemisphere)."""
    sc, fl = cfg["scene"], cfg["fluid"]
    d, dx, R = sc["dim"], sc["dx_m"], sc["radius_m"]
    layers = sc["wall_layers"]
    width = sc["plate_width_m"] if sc["plate_width_m"] is not None else 7.0 * R
    nw = 2 * max(round(width / (2 * dx)), 1)  # even: the lattice is symmetric about 0
    zc = -R * math.cos(math.radians(sc["initial_angle_deg"]))
    top = R + zc
    nz = max(round(top / dx), 1)
    xf = lattice([nw] * (d - 1) + [nz], dx, origin=[-nw * dx / 2] * (d - 1) + [0.0], dtype=dtype, device=device)
    centre = torch.zeros(d, dtype=dtype, device=device)
    centre[-1] = zc
    xf = xf[((xf - centre) ** 2).sum(-1) < R * R]
    xw = lattice([nw] * (d - 1) + [layers], dx, origin=[-nw * dx / 2] * (d - 1) + [-layers * dx],
                 dtype=dtype, device=device)
    rho0 = fl["rho0_kg_m3"]
    drop = ParticleState.create(xf, torch.zeros_like(xf), rho0, rho0 * dx**d, Phase.FLUID,
                                T=fl["temperature_K"], dtype=dtype, device=device)
    phase = Phase.SOLID if sc["plate"] == "solid" else Phase.WALL
    plate = solid_block(xw, fl, dx, d, fl["temperature_K"], dtype, device, id0=xf.shape[0], phase=phase)
    if phase == Phase.SOLID:
        plate.body[:] = 1
    half = nw * dx / 2
    height = max(3.0 * R, 2.0 * top)
    # a plate narrower than 7 R (a pillar): room beside and below it for melt that runs over
    # its edges (the domain of the default plate is the plate's own)
    pillar = half < 3.5 * R - dx
    side = 3.5 * R if pillar else half
    lo = [-side] * (d - 1) + [-layers * dx - (2.0 * R if pillar else 0.0)]
    hi = [side] * (d - 1) + [height]
    volume = xf.shape[0] * dx**d
    return Scene(ParticleState.cat([drop, plate]), Domain(lo, hi, [False] * d), dx,
                 {"R": R, "volume": volume, "plate_top": 0.0})


def check_sessile_drop(cfg):
    _need_wall_layers(cfg)
    sc = cfg["scene"]
    if sc["radius_m"] < 4 * sc["dx_m"]:
        raise CaseError(f"[scene] radius_m = {sc['radius_m']:g}: must be >= 4 dx_m = {4 * sc['dx_m']:g} "
                        "(a cap needs a few particles across)")
    width = sc["plate_width_m"]
    if width is not None and width < 2 * sc["radius_m"]:
        raise CaseError(f"[scene] plate_width_m = {width:g}: must be >= the drop's diameter "
                        f"2 radius_m = {2 * sc['radius_m']:g}")


def build_pendant_drop(cfg, dtype, device) -> Scene:
    """A liquid drop hanging from the end face of a vertical wire (thesis §5.1, SPEC 3b): the
    wire, a cylinder of wall particles of diameter ``wire_diameter_m``, stands on the plane
    z = 0; the drop is the part below that plane of a ball of radius ``radius_m`` whose cut
    circle is the wire's end face (so the drop starts wetting the whole face). Gravity
    (``[fluid] gravity_m_s2``, with ``gravity_ramp_s`` to load it quasi-statically) pulls it
    off; the domain reaches 30 radii below the wire for the falling drop."""
    sc, fl = cfg["scene"], cfg["fluid"]
    dx, R, d_w = sc["dx_m"], sc["radius_m"], sc["wire_diameter_m"]
    r_w = d_w / 2
    nw = 2 * max(round(r_w / dx), 1)  # even: symmetric about the axis
    nz_w = max(round(sc["wire_length_m"] / dx), 1)
    xw = lattice([nw, nw, nz_w], dx, origin=[-nw * dx / 2, -nw * dx / 2, 0.0], dtype=dtype, device=device)
    xw = xw[(xw[:, :2] ** 2).sum(1) < r_w * r_w]
    zc = -math.sqrt(max(R * R - r_w * r_w, 0.0))
    nd = 2 * max(round(R / dx) + 1, 1)
    nz = max(round((R - zc) / dx), 1)
    xf = lattice([nd, nd, nz], dx, origin=[-nd * dx / 2, -nd * dx / 2, -nz * dx], dtype=dtype, device=device)
    centre = torch.tensor([0.0, 0.0, zc], dtype=dtype, device=device)
    xf = xf[((xf - centre) ** 2).sum(1) < R * R]
    rho0 = fl["rho0_kg_m3"]
    drop = ParticleState.create(xf, torch.zeros_like(xf), rho0, rho0 * dx**3, Phase.FLUID,
                                T=fl["temperature_K"], dtype=dtype, device=device)
    wire = solid_block(xw, fl, dx, 3, fl["temperature_K"], dtype, device, id0=xf.shape[0], phase=Phase.WALL)
    side = max(3.0 * R, 2.0 * r_w)
    lo, hi = [-side, -side, -30.0 * R], [side, side, nz_w * dx]
    return Scene(ParticleState.cat([drop, wire]), Domain(lo, hi, [False] * 3), dx,
                 {"R": R, "wire_radius": r_w, "mass": float(drop.m.sum()), "wire_end": 0.0})


def check_pendant_drop(cfg):
    sc = cfg["scene"]
    dx = sc["dx_m"]
    if sc["wire_diameter_m"] < 6 * dx * (1 - 1e-9):
        raise CaseError(f"[scene] wire_diameter_m = {sc['wire_diameter_m']:g}: must be >= 6 dx_m = {6 * dx:g} "
                        "(the contact line needs a few particles across the end face)")
    if sc["radius_m"] < sc["wire_diameter_m"] / 2:
        raise CaseError(f"[scene] radius_m = {sc['radius_m']:g}: must be >= the wire's radius "
                        f"{sc['wire_diameter_m'] / 2:g} (the drop's cut circle is the wire's end face)")
    need = 2.0 * cfg["numerics"]["h_over_dx"] * dx
    if sc["wire_length_m"] < need:
        raise CaseError(f"[scene] wire_length_m = {sc['wire_length_m']:g}: must be >= the kernel support "
                        f"2 h = {need:g} (the wire's end must be a full wall)")


SCENES: dict[str, SceneSpec] = {
    "taylor_green": SceneSpec(
        {"length_m": Key("float", default=1.0, gt=0, doc="side of the periodic box"),
         "nx": Key("int", gt=0, doc="particles per side"),
         "U_m_s": Key("float", default=1.0, gt=0, doc="velocity amplitude")},
        (2,), build_taylor_green, check_taylor_green, "2-D Taylor-Green vortex, periodic box",
        numerics={"density_diffusion": 0.1, "shifting": 0.4}),  # verified (docs/VERIFICATION.md, "The shift's stability limit"); below the limit for h_over_dx >= 1.31 in 2-D
    "poiseuille": SceneSpec(
        {"height_m": Key("float", gt=0, doc="channel height"),
         "length_m": Key("float", gt=0, doc="periodic channel length"),
         "n_height": Key("int", ge=4, doc="particles across the channel"),
         "wall_layers": Key("int", default=3, ge=1, doc="layers of wall particles")},
        (2,), build_poiseuille, check_poiseuille, "body-force-driven channel between two walls"),
    "hydrostatic_tank": SceneSpec(
        {"fluid_width_m": Key("float", gt=0, doc="width of the fluid block (y; and x unless fluid_length_m)"),
         "fluid_length_m": Key("float", default=None, gt=0, doc="length of the fluid block along x (default: the width)"),
         "fluid_depth_m": Key("float", gt=0, doc="depth of the fluid"),
         "tank_height_m": Key("float", gt=0, doc="height of the tank walls"),
         "n_depth": Key("int", ge=2, doc="particles across the depth"),
         "wall_layers": Key("int", default=3, ge=1, doc="layers of wall particles")},
        (3, 2), build_hydrostatic_tank, check_hydrostatic_tank, "fluid at rest in a walled box"),
    "conduction_1d": SceneSpec(
        {"length_m": Key("float", gt=0, doc="length of the bar along x"),
         "nx": Key("int", ge=4, doc="particles along x"),
         "face_temperature_K": Key("float", gt=0, doc="temperature held at x < 0"),
         "initial_temperature_K": Key("float", gt=0, doc="initial temperature of the bar"),
         "wall_layers": Key("int", default=3, ge=1, doc="layers of fixed-temperature particles")},
        (2, 3), build_conduction_1d, _need_wall_layers, "semi-infinite transient conduction",
        has_fluid=False, needs_thermal=True),
    "gaussian_bump": SceneSpec(
        {"length_m": Key("float", gt=0, doc="side of the periodic box"),
         "nx": Key("int", gt=0, doc="particles per side"),
         "sigma_m": Key("float", gt=0, doc="standard deviation of the bump"),
         "amplitude_K": Key("float", doc="peak excess temperature"),
         "background_K": Key("float", gt=0, doc="far-field temperature")},
        (3, 2), build_gaussian_bump, check_gaussian_bump, "diffusion of a Gaussian temperature bump",
        has_fluid=False, needs_thermal=True),
    "block": SceneSpec(
        {"size_m": Key("vec", doc="block size (x, y, z)"),
         "dx_m": Key("float", gt=0, doc="particle spacing"),
         "temperature_K": Key("float", gt=0, doc="initial temperature"),
         "shape": Key("str", default="box", choices=("box", "sphere"), doc="box, or the inscribed ball"),
         "periodic_xy": Key("bool", default=False, doc="periodic in x and y (an infinite slab)"),
         "velocity_m_s": Key("vec", default=None, doc="rigid velocity of the block (its body)")},
        (3,), build_block, None, "rigid heat-conducting block, top face at z = 0",
        has_fluid=False, needs_thermal=True),
    "drop": SceneSpec(
        {"size_m": Key("float", gt=0, doc="diameter (ball) or side (box)"),
         "dx_m": Key("float", gt=0, doc="particle spacing"),
         "shape": Key("str", default="ball", choices=("ball", "box"), doc="disc/ball or square/cube"),
         "mode2_velocity_m_s": Key("float", default=0.0, doc="initial mode-2 velocity amplitude U0")},
        (3, 2), build_drop, None, "free liquid drop (surface-tension studies)"),
    "sessile_drop": SceneSpec(
        {"radius_m": Key("float", gt=0, doc="radius of the initial cap's circle (sphere in 3-D)"),
         "dx_m": Key("float", gt=0, doc="particle spacing"),
         "initial_angle_deg": Key("float", default=90.0, gt=0, lt=180,
                                  doc="contact angle of the initial cap (90: a half disc / hemisphere)"),
         "plate_width_m": Key("float", default=None, gt=0, doc="side of the plate (default 7 radius_m)"),
         "plate": Key("str", default="wall", choices=("wall", "solid"),
                      doc="plate particles: rigid walls, or rigid solid (conducts heat with [thermal])"),
         "wall_layers": Key("int", default=3, ge=1, doc="layers of plate particles")},
        (2, 3), build_sessile_drop, check_sessile_drop, "liquid cap resting on a flat plate (wetting)"),
    "pendant_drop": SceneSpec(
        {"radius_m": Key("float", gt=0, doc="radius of the ball the drop is cut from"),
         "dx_m": Key("float", gt=0, doc="particle spacing"),
         "wire_diameter_m": Key("float", gt=0, doc="diameter d of the wire the drop hangs from"),
         "wire_length_m": Key("float", default=1.0e-3, gt=0, doc="length of wire modelled above its end face")},
        (3,), build_pendant_drop, check_pendant_drop, "drop hanging from a wire's end until it detaches (Tate's law)"),
    "deposition": SceneSpec(
        {"substrate_size_m": Key("vec", doc="substrate block (x travel, y width, z thickness)"),
         "dx_m": Key("float", gt=0, doc="particle spacing"),
         "temperature_K": Key("float", default=300.0, gt=0, doc="initial temperature of substrate and wire"),
         "substrate_velocity_m_s": Key("vec", doc="substrate velocity [V_sub, 0, 0]"),
         "wire_offset_m": Key("float", default=2.0e-3, ge=0,
                              doc="distance from the substrate's leading (+x) edge back to the wire at t = 0"),
         "wire_diameter_m": Key("float", gt=0, doc="wire diameter d"),
         "wire_length_m": Key("float", gt=0, doc="wire modelled above its tip (fed continuously)"),
         "wire_feed_m_s": Key("float", ge=0, doc="wire feed speed V_wire (along -z)"),
         "wire_gap_m": Key("float", ge=0, doc="height of the wire tip above the substrate at t = 0"),
         "wire_feed_start_s": Key("float", default=0.0, ge=0,
                                  doc="the feed starts at this time (the sources preheat the tip first)"),
         "wire_contact": Key("str", default="weld", choices=("stop", "weld"),
                             doc="wire material that melted and froze back onto the wire, reaching the "
                                 "substrate: stops the run, or joins the substrate"),
         "wire_stall": Key("bool", default=False,
                           doc="unmelted wire that reaches solid substrate waits there (the feed pauses) "
                               "until its tip melts; false: the run stops with a diagnosis"),
         "wire_squeeze_limit": Key("float", default=0.15, gt=0, lt=0.3,
                                   doc="with wire_stall: the feed also waits while melt within 1.5 spacings "
                                       "of the solid wire is compressed by more than this fraction (melt "
                                       "squeezed between the tip and solid substrate, with no way out)"),
         "escape_margin_m": Key("float", default=2.0e-3, gt=0,
                                doc="a particle this far outside the scene's box (the substrate swept by its "
                                    "travel, up to the wire's top) has left for good (spatter): it is removed, "
                                    "its mass and energy booked; must exceed the search radius"),
         "source_layout": Key("str", choices=("along", "perpendicular", "none"),
                              doc="sources in the plane of travel (ahead/behind) or across it"),
         "source_count": Key("int", default=2, ge=1, doc="number of sources, evenly spaced in azimuth"),
         "source_power_W": Key("float", default=0.0, ge=0, doc="power of each source Q0"),
         "source_efficiency": Key("float", default=0.85, gt=0, le=1, doc="absorbed fraction eta0"),
         "source_radius_m": Key("float", default=0.75e-3, gt=0, doc="1/e^2 spot radius r"),
         "source_azimuth_deg": Key("float", default=45.0, ge=0, lt=90, doc="tilt from the vertical"),
         "source_aim_height_m": Key("float", default=None,
                                    doc="height of the aim point on the wire axis (default: the tip, wire_gap_m)")},
        (3,), lambda cfg, dtype, device: deposition.build(cfg, dtype, device),
        lambda cfg: deposition.check(cfg),
        "substrate moving under a fed wire, sources aimed at the wire tip",
        has_fluid=False, needs_thermal=True,
        numerics={"density_diffusion": 0.1},  # as in the four thesis cases
        beams=lambda cfg: deposition.source_beams(cfg["scene"])),
}


def case_beams(cfg: dict) -> list[dict]:
    """Every beam of a case ([[beam]] tables): the case's own and those its scene derives
    from its keys (the deposition scene's sources). Validation leaves the case as written;
    the derived beams are made here. A configuration recorded by an older version carries
    the derived beams among its own: they are not added twice."""
    own = list(cfg.get("beam") or [])
    spec = SCENES.get(cfg.get("scene", {}).get("type"))
    if spec is None or spec.beams is None or "thermal" not in cfg:
        return own
    try:
        derived = spec.beams(cfg)
    except KeyError:  # a recorded configuration from before one of the scene's keys
        return own
    return own + [b for b in derived if b not in own]


def build_scene(cfg, dtype=torch.float64, device="cpu") -> Scene:
    return SCENES[cfg["scene"]["type"]].build(cfg, dtype, device)
