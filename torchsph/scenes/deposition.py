"""The deposition scene (SPEC §1, §6): a substrate block moving along x under a vertical
wire fed along -z, heat sources aimed at the wire tip; the wire is fed continuously
(new layers of particles enter at its top as it advances) and measures of the deposit.

Frames: the wire axis is x = y = 0, the substrate's top face z = 0 at t = 0. The substrate
(body 1) moves with ``substrate_velocity_m_s`` (along +x), so the material point at x0
passes under the wire at t = -x0 / V and the bead is laid along x0 < 0. The wire (body 2)
moves down at the feed speed; its bottom starts ``wire_gap_m`` above the substrate.
"""
from __future__ import annotations

import math

import torch

from torchsph.core.kernels import make_kernel
from torchsph.core.lattice import Scene, lattice, solid_block
from torchsph.core.neighbors import Domain
from torchsph.core.schema import CaseError
from torchsph.core.state import ParticleState, Phase
from torchsph.physics.fluid import embed
from torchsph.step.limits import SimulationError

SUBSTRATE, WIRE = 1, 2


def disc_lattice(diameter: float, dx: float, dtype, device) -> torch.Tensor:
    """(n, 2) lattice points inside a disc centred on the origin: of the two lattice
    placements (a point on the axis, or the axis between four points) the one whose
    count times dx^2 is nearer the disc area."""
    best = None
    R = 0.5 * diameter
    k = int(math.ceil(R / dx)) + 1
    for shift in (0.0, 0.5):
        a = (torch.arange(-k, k + 1, dtype=dtype, device=device) + shift) * dx
        g = torch.stack(torch.meshgrid(a, a, indexing="ij"), -1).reshape(-1, 2)
        g = g[(g * g).sum(-1) < R * R]
        err = abs(g.shape[0] * dx * dx - math.pi * R * R)
        if best is None or err < best[0]:
            best = (err, g)
    return best[1]


class EscapeBox:
    """Where the scene ends: the box a particle that has left it for good (spatter flung off
    the bead, a drop fallen past the substrate) is removed from, ``margin`` outside the
    substrate's box swept by its travel up to time t and, up the z axis, outside the wire's
    top. With the margin above the search radius, a particle there is beyond the reach of
    everything in the scene; left in, it costs a neighbour rebuild every few steps as it
    falls. What leaves is booked (``n``, ``kg`` here; the energy balance's ``escaped``)."""

    def __init__(self, lo: list[float], hi: list[float], velocity: list[float], margin: float):
        self.lo, self.hi, self.velocity, self.margin = list(lo), list(hi), list(velocity), float(margin)
        self.n, self.kg = 0, 0.0

    def outside(self, x: torch.Tensor, t: float) -> torch.Tensor:
        out = torch.zeros(x.shape[0], dtype=torch.bool, device=x.device)
        for a in range(x.shape[1]):
            shift = self.velocity[a] * t
            lo = min(self.lo[a], self.lo[a] + shift) - self.margin
            hi = max(self.hi[a], self.hi[a] + shift) + self.margin
            out |= (x[:, a] < lo) | (x[:, a] > hi)
        return out

    def book(self, n: int, kg: float):
        self.n += int(n)
        self.kg += float(kg)

    def state_dict(self) -> dict:
        return {"n": self.n, "kg": self.kg}

    def load_state_dict(self, d: dict):
        self.n, self.kg = int(d.get("n", 0)), float(d.get("kg", 0.0))


class WireFeeder:
    """Feeds a vertical wire: layer j (counted from the bottom of the initial wire) is at
    z = z0 + (j + 1/2) dx - V t; layers K, K + 1, ... (K initial layers) are added as
    soon as they have come below the entry plane z0 + K dx, so the lattice continues
    without gap or overlap and the wire never runs out. Each particle's mass is
    rho0 (pi d^2 / 4) dx / n_layer: the fed mass flux is exactly rho0 (pi d^2 / 4) V."""

    def __init__(self, layer_xy: torch.Tensor, z0: float, n_layers: int, dx: float, speed: float,
                 mass: float, rho0: float, T0: float, next_id: int, start: float = 0.0,
                 contact: str = "stop", T_melt: float | None = None, stall: bool = False,
                 squeeze: float = 0.15):
        self.layer_xy = layer_xy
        self.z0, self.K, self.dx, self.speed = z0, n_layers, dx, speed
        self.start = start  # the feed starts at this time (the sources may preheat first)
        self.started = start <= 0.0
        self.mass, self.rho0, self.T0 = mass, rho0, T0
        self.next_id = next_id
        self.n_fed = 0  # layers added so far
        self.contact, self.T_melt = contact, T_melt  # see check_contact
        self.stall = stall  # unmelted wire on solid substrate waits instead of stopping the run
        self.squeeze = squeeze  # with stall: melt this compressed beside the solid wire also makes it wait
        self.welded_kg, self.n_welded = 0.0, 0  # refrozen wire material welded to the substrate
        self.fed = 0.0  # length of wire fed so far (the distance the solid wire has moved)
        self.stalled = False  # the wire rests on solid substrate; its feed waits
        self.stall_s, self.n_stalls = 0.0, 0  # time spent stalled, stalls begun
        # the same by the rule that began each wait: unmelted wire on solid substrate, or melt
        # squeezed between the solid tip and solid substrate (where both held, "unmelted")
        self.stall_by = {"unmelted": [0.0, 0], "squeezed": [0.0, 0]}
        self.stall_why = "unmelted"

    @property
    def area(self) -> float:
        """Cross-section the particles stand for, (layer mass) / (rho0 dx)."""
        return self.mass * self.layer_xy.shape[0] / (self.rho0 * self.dx)

    def layers(self, js: torch.Tensor, t: float) -> ParticleState:
        xy = self.layer_xy
        n = xy.shape[0]
        z = self.z0 + (js.to(xy.dtype) + 0.5) * self.dx - self.fed
        x = torch.cat([xy.repeat(js.numel(), 1), z.repeat_interleave(n).unsqueeze(1)], 1)
        v = torch.zeros_like(x)
        v[:, 2] = -self.speed if self.started and not self.stalled else 0.0
        ids = torch.arange(self.next_id, self.next_id + x.shape[0], device=x.device)
        self.next_id += x.shape[0]
        return ParticleState.create(x, v, self.rho0, self.mass, Phase.SOLID, T=self.T0, id=ids,
                                    body=WIRE, dtype=xy.dtype, device=xy.device)

    def _set_wire_velocity(self, sim, speed: float):
        vw = torch.zeros(sim.state.dim, dtype=sim.state.dtype, device=sim.state.device)
        vw[2] = -speed
        sim.set_body_velocity(WIRE, vw)

    def probe(self, sim) -> dict[str, torch.Tensor]:
        """The contact check's first questions (is solid wire at the substrate's top, is melt
        squeezed) as 0-d device tensors, which the step reads with its other decisions; the
        next :meth:`new_particles` (at the same positions) uses the answers. Only the wire's
        particles and the melt are read (not every particle)."""
        s = sim.state
        w = self.wire_rows(s)
        low = (s.phase.index_select(0, w) == Phase.SOLID) & (s.x.index_select(0, w)[:, 2] < 0.5 * self.dx)
        q = {"wire_low": low.any()}
        dense = None
        if self.stall:
            f = self.melt_rows(sim)
            dense = (f, s.rho.index_select(0, f) > (1.0 + self.squeeze) * self.rho0)
            q["melt_dense"] = dense[1].any()
        self.probed = (s.x, (w, low), dense)
        return q

    _wire = None  # (the body array, the wire's particles in it)

    def wire_rows(self, s) -> torch.Tensor:
        """The particles of the wire's body, found once per body array (the selection after a
        feed or a phase change makes it: :meth:`select`)."""
        if self._wire is None or self._wire[0] is not s.body:
            self._wire = (s.body, torch.nonzero(s.body == WIRE).squeeze(1))
        return self._wire[1]

    _melt = None  # (the phase array, the fluid particles in it)

    def melt_rows(self, sim) -> torch.Tensor:
        """The fluid particles, found once per phase array (the fluid model's, where it
        selected on this one)."""
        s, fm = sim.state, sim.fluid_model
        if fm is not None and getattr(fm, "fluid_rows_for", None) is s.phase:
            return fm.fluid_rows
        if self._melt is None or self._melt[0] is not s.phase:
            self._melt = (s.phase, torch.nonzero(s.phase == Phase.FLUID).squeeze(1))
        return self._melt[1]

    def select(self, sim):
        """At a pair selection (the particles, their phases or bodies may have changed)."""
        self.wire_rows(sim.state)
        self.melt_rows(sim)

    probed = None  # (positions, masks) of the last probe

    def new_particles(self, sim, t: float, answers: dict | None = None) -> ParticleState | None:
        """Called after the positions of the step from sim.t to t were updated: count the
        distance the wire moved in it, handle contact, add the layers now due. ``answers``:
        the read values of :meth:`probe` at these positions."""
        if self.started and not self.stalled:
            self.fed += self.speed * (t - sim.t)
        elif self.started:  # stalled (before the feed starts the wire waits anyway)
            self.stall_s += t - sim.t
            self.stall_by[self.stall_why][0] += t - sim.t
        blocked = self.check_contact(sim, answers)
        if self.stall and blocked != self.stalled:  # stall on contact, go on once it has melted
            self.stalled = blocked
            self.n_stalls += int(blocked)
            if blocked:
                self.stall_by[self.stall_why][1] += 1
            if self.started:
                self._set_wire_velocity(sim, 0.0 if blocked else self.speed)
        if not self.started and t >= self.start:  # the wire moves from the next step on
            self.started = True
            self._set_wire_velocity(sim, 0.0 if self.stalled else self.speed)
        due = int(math.floor(self.fed / self.dx + 1e-9)) - self.n_fed
        if due <= 0:
            return None
        js = torch.arange(self.K + self.n_fed, self.K + self.n_fed + due, device=self.layer_xy.device)
        self.n_fed += due
        return self.layers(js, t)

    def check_contact(self, sim, answers: dict | None = None) -> bool:
        """The wire is rigid until it melts. Solid wire may dip into the melt pool below the
        substrate's top face; where it runs into
        solid substrate (:meth:`touches_solid_substrate`) it is handled by ``contact`` and
        ``stall``:

        - wire that has never melted (peak temperature <= liquidus): with ``stall`` the feed
          waits (returns True: the wire rests on the substrate while the sources melt its tip,
          and goes on once the touching particles have melted: the feed is limited by the
          melting rate, and ``stall_s`` says for how long); without it the run stops with a
          diagnosis rather than let two rigid bodies overlap;
        - with ``contact = "weld"``, wire-body material that has melted and frozen back onto
          the wire (a collar of melt that ran up the wire's unlit side) joins the substrate
          where it touches it and moves with it from then on (its mass is counted in
          ``welded_kg``); with ``"stop"`` it stops the run like unmelted wire.

        - with ``stall``, the feed also waits while melt within 1.5 spacings of the solid wire
          is compressed by more than ``squeeze`` (a fraction of rho0): melt caught between the
          rigid tip and solid substrate, a layer or two of particles with no way out at this
          resolution, which the rigid feed would otherwise squeeze until the weakly
          compressible model breaks (it relaxes while the wire waits).

        Returns whether the feed waits (the same on every process). ``answers``: the read
        values of :meth:`probe` at these positions (else they are read here)."""
        s = sim.state
        if answers is not None and self.probed is not None and self.probed[0] is s.x:
            _, low, dense = self.probed  # read with the step's other decisions
            hit, some_dense = bool(answers["wire_low"]), bool(answers.get("melt_dense", False))
        else:
            q = self.probe(sim)
            vals = torch.stack(list(q.values())).tolist()  # one sync; the rest only on contact
            hit, some_dense = bool(vals[0]), len(vals) > 1 and bool(vals[1])
            _, low, dense = self.probed
        self.probed = None
        # (the probe's masks are of the wire's and the melt's particles; whole only when read)
        low = embed(*low, s.n) if hit else None
        dense = embed(*dense, s.n) if some_dense else None
        if hit:
            low = self.touches_solid_substrate(s, low)
            hit = bool(low.any())
        if hit and self.contact == "weld" and self.T_melt is not None:
            weld = low & (s.T_peak > self.T_melt)
            if bool(weld.any()):
                s.body = torch.where(weld, torch.full_like(s.body, SUBSTRATE), s.body)
                s.v = torch.where(weld.unsqueeze(-1), sim.body_velocity[SUBSTRATE], s.v)
                sim.new_body_velocity = True  # and keep it at the step's end
                own = sim.comm.owned(sim)
                mine = weld if own is None else weld & own
                self.welded_kg += float(s.m[mine].sum())
                self.n_welded += int(mine.sum())
                low = low & ~weld
                hit = bool(low.any())
        blocked = False
        if self.stall:  # every process takes part, touching or not
            unmelted = low & (s.T_peak <= (self.T_melt or math.inf)) if hit else None
            touch = hit and bool(unmelted.any())
            blocked = sim.comm.any(touch or (some_dense and self.squeezed(s, dense)))
            if blocked and not self.stalled:  # a wait begins: which rule (every process asks)
                self.stall_why = "unmelted" if sim.comm.any(touch) else "squeezed"
            if hit:
                low = low & ~unmelted
                hit = bool(low.any())
        if not hit:
            return blocked
        z = torch.where(low, s.x[:, 2], torch.full_like(s.x[:, 2], math.inf))
        k = int(torch.argmin(z))
        where = (f"step {sim.step}, t = {sim.t:.6g} s: {{}} (particle id {int(s.id[k])}, z = {float(z[k]):.4g} m, "
                 f"r = {float(s.x[k, :2].norm()):.4g} m from the wire axis, T = {float(s.T[k]):.1f} K, peak "
                 f"{float(s.T_peak[k]):.1f} K)")
        if float(s.T_peak[k]) <= (self.T_melt or math.inf):
            raise SimulationError(where.format("solid wire reached into the substrate") + (
                f": the sources do not melt the feed ({self.speed:g} m/s) before it arrives; raise the source "
                "power, aim the sources lower (source_aim_height_m), start the wire higher (wire_gap_m), "
                "feed slower, or let the feed wait for the tip to melt (scene.wire_stall = true)"))
        raise SimulationError(where.format("wire material that melted and froze back onto the wire reached "
                                           "into the substrate") + ": scene.wire_contact = \"weld\" lets it join "
                                           "the substrate")

    def squeezed(self, s, dense: torch.Tensor) -> bool:
        """Whether any of the ``dense`` melt (compressed by more than ``squeeze``; the caller
        tests that mask with the contact check, in one sync) lies within 1.5 spacings of the
        solid wire's tip layers."""
        wire = (s.body == WIRE) & (s.phase == Phase.SOLID)
        if not bool(wire.any()):
            return False
        xw = s.x[wire]
        xw = xw[xw[:, 2] < xw[:, 2].min() + 3.0 * self.dx]  # the tip's layers
        return bool((torch.cdist(s.x[dense], xw) < 1.5 * self.dx).any())

    def touches_solid_substrate(self, s, low: torch.Tensor | None = None) -> torch.Tensor:
        """Mask of the solid wire particles at the substrate's top or below (centre less than
        half a spacing above the original top face) that run into rigid (solid) substrate
        material in their way: less than 0.72 spacing aside, from the layer below them (up to
        1.25 spacings lower) up to their own height (an overlap). A wire resting on the top
        face is therefore blocked; rigid solid beside the wire (0.75 spacing or more aside),
        e.g. the wall of the pool it is fed into, does not count. Wire below the top but
        surrounded by melt is fed into the pool, as in the real process, and melts there.
        Only the few low particles are compared, against the substrate particles in their
        bounding box grown by 1.5 spacings. ``low``: the mask of solid wire at the top or
        below, if the caller has it."""
        if low is None:
            low = (s.body == WIRE) & (s.phase == Phase.SOLID) & (s.x[:, 2] < 0.5 * self.dx)
        idx = low.nonzero().squeeze(1)
        out = torch.zeros_like(low)
        if idx.numel() == 0:
            return out
        xl = s.x[idx]
        lo, hi = xl.min(0).values - 1.5 * self.dx, xl.max(0).values + 1.5 * self.dx
        sub = ((s.body == SUBSTRATE) & (s.phase != Phase.FLUID) & (s.x >= lo).all(1) & (s.x <= hi).all(1))
        xs = s.x[sub]
        if xs.shape[0]:
            dz = xl[:, 2:3] - xs[:, 2].unsqueeze(0)
            # in the wire's way: substrate in its column (less than 0.72 spacing aside: on a
            # lattice some column is always within dx / sqrt(2), so a wire resting on a moving
            # substrate stays blocked whatever the two lattices' alignment), from the layer
            # below (dz ~ dx) up to its own height (an overlap)
            way = (dz > -0.5 * self.dx) & (dz < 1.25 * self.dx) & (torch.cdist(xl[:, :2], xs[:, :2]) < 0.72 * self.dx)
            out[idx[way.any(1)]] = True
        return out

    def state_dict(self) -> dict:
        return {"n_fed": self.n_fed, "next_id": self.next_id, "started": self.started,
                "welded_kg": self.welded_kg, "n_welded": self.n_welded, "fed": self.fed,
                "stalled": self.stalled, "stall_s": self.stall_s, "n_stalls": self.n_stalls,
                "stall_by": {k: list(v) for k, v in self.stall_by.items()}, "stall_why": self.stall_why}

    def load_state_dict(self, d: dict):
        self.n_fed, self.next_id = d["n_fed"], d["next_id"]
        self.started = d.get("started", self.start <= 0.0)
        self.welded_kg, self.n_welded = d.get("welded_kg", 0.0), d.get("n_welded", 0)
        # older checkpoints: no stall, so the fed length followed the feed clock
        self.fed = d.get("fed", self.n_fed * self.dx)
        self.stalled, self.stall_s, self.n_stalls = d.get("stalled", False), d.get("stall_s", 0.0), d.get("n_stalls", 0)
        # older checkpoints: the waits not told apart (counted as unmelted from here on)
        self.stall_by = {k: list(v) for k, v in d.get("stall_by", {"unmelted": [0.0, 0], "squeezed": [0.0, 0]}).items()}
        self.stall_why = d.get("stall_why", "unmelted")


def source_beams(sc: dict) -> list[dict]:
    """[[beam]] tables for the scene's sources: ``source_count`` beams spaced evenly in
    azimuth around the vertical, the first in the plane of travel (``along``: one ahead,
    one behind for two) or across it (``perpendicular``: left and right), each tilted
    ``source_azimuth_deg`` from the vertical and aimed at the wire tip."""
    if sc["source_layout"] == "none":
        return []
    th = math.radians(sc["source_azimuth_deg"])
    phi0 = 0.0 if sc["source_layout"] == "along" else 0.5 * math.pi
    aim = [0.0, 0.0, sc["wire_gap_m"] if sc["source_aim_height_m"] is None else sc["source_aim_height_m"]]
    out = []
    for k in range(sc["source_count"]):
        phi = phi0 + 2.0 * math.pi * k / sc["source_count"]
        # the source sits at azimuth phi above the tip and shines towards it
        e = [-math.sin(th) * math.cos(phi), -math.sin(th) * math.sin(phi), -math.cos(th)]
        e = [0.0 if abs(c) < 1e-15 else c for c in e]
        out.append({"power_W": sc["source_power_W"], "efficiency": sc["source_efficiency"],
                    "radius_m": sc["source_radius_m"], "direction": e, "aim_m": aim,
                    "velocity_m_s": [0.0, 0.0, 0.0]})
    return out


def build(cfg, dtype, device):

    sc, fl = cfg["scene"], cfg["fluid"]
    dx = sc["dx_m"]
    Lx, Ly, Lz = sc["substrate_size_m"]
    counts = [max(round(Lx / dx), 1), max(round(Ly / dx), 1), max(round(Lz / dx), 1)]
    off = sc["wire_offset_m"]
    origin = [off - counts[0] * dx, -counts[1] * dx / 2, -counts[2] * dx]
    xs = lattice(counts, dx, origin=origin, dtype=dtype, device=device)
    T0 = sc["temperature_K"]
    sub = solid_block(xs, fl, dx, 3, T0, dtype, device)
    sub.v[:] = torch.as_tensor(sc["substrate_velocity_m_s"], dtype=dtype, device=device)
    sub.body[:] = SUBSTRATE
    rho0 = fl["rho0_kg_m3"]
    xy = disc_lattice(sc["wire_diameter_m"], dx, dtype, device)
    area = math.pi * sc["wire_diameter_m"] ** 2 / 4
    K = max(round(sc["wire_length_m"] / dx), 1)
    feeder = WireFeeder(xy, sc["wire_gap_m"], K, dx, sc["wire_feed_m_s"], rho0 * area * dx / xy.shape[0],
                        rho0, T0, next_id=xs.shape[0], start=sc["wire_feed_start_s"],
                        contact=sc["wire_contact"], T_melt=cfg["thermal"]["liquidus_K"] if "thermal" in cfg else None,
                        stall=sc["wire_stall"], squeeze=sc["wire_squeeze_limit"])
    wire = feeder.layers(torch.arange(K, device=device), 0.0)
    st = ParticleState.cat([sub, wire])
    hi_z = sc["wire_gap_m"] + K * dx
    dom = Domain([origin[0], origin[1], origin[2]], [off, -origin[1], hi_z], [False] * 3)
    # the box's top is the wire's top (fixed: the wire is fed through it), its x range moves
    # with the substrate
    escape = EscapeBox(dom.lo, dom.hi, [sc["substrate_velocity_m_s"][0], 0.0, 0.0], sc["escape_margin_m"])
    info = {"feeder": feeder, "escape": escape, "n_substrate": xs.shape[0], "wire_id0": xs.shape[0],
            "substrate_counts": counts, "substrate_origin": origin, "wire_area": area,
            "wire_area_lattice": xy.shape[0] * dx * dx, "wire_mass0": float(wire.m.sum())}
    return Scene(st, dom, dx, info)


def check(cfg):

    sc = cfg["scene"]
    v = sc["substrate_velocity_m_s"]
    if v[1] != 0 or v[2] != 0 or v[0] < 0:
        raise CaseError(f"[scene] substrate_velocity_m_s = {v}: must be [V, 0, 0] with V >= 0 "
                        "(travel along +x; the wire is at x = y = 0)")
    Lx, Ly, Lz = sc["substrate_size_m"]
    if sc["wire_diameter_m"] >= Ly:
        raise CaseError(f"[scene] wire_diameter_m = {sc['wire_diameter_m']}: must be < the substrate "
                        f"width substrate_size_m[1] = {Ly}")
    if not 0 <= sc["wire_offset_m"] <= Lx:
        raise CaseError(f"[scene] wire_offset_m = {sc['wire_offset_m']}: must lie in [0, substrate "
                        f"length {Lx}] (distance from the substrate's leading edge to the wire)")
    if sc["wire_diameter_m"] < 2 * sc["dx_m"]:
        raise CaseError(f"[scene] dx_m = {sc['dx_m']}: must be <= wire_diameter_m / 2 = "
                        f"{sc['wire_diameter_m'] / 2:g} (a wire needs particles across it)")
    if "thermal" not in cfg or not cfg["thermal"]["phase_change"]:
        raise CaseError("[thermal] phase_change = false: the deposition scene melts wire and substrate "
                        "(set phase_change = true)")
    nm = cfg.get("numerics", {})
    if "kernel" in nm:

        reach = (make_kernel(nm["kernel"], 3).radius(nm["h_over_dx"] * sc["dx_m"])
                 + nm["skin_over_dx"] * sc["dx_m"])
        if sc["escape_margin_m"] <= reach:
            raise CaseError(f"[scene] escape_margin_m = {sc['escape_margin_m']}: must exceed the search "
                            f"radius {reach:g} m (kernel support + Verlet skin at dx_m = {sc['dx_m']}), or a "
                            "particle removed there could still have had neighbours in the scene")


def measure(state: ParticleState, info: dict, t: float, V_sub: float, V_wire: float, rho0: float,
            T_liquidus: float, dx: float, bin_m: float | None = None, welded_kg: float | None = None,
            escaped_kg: float | None = None) -> dict:
    """Deposit and melt-pool measures at time t.

    - ``added_area_m2``: the bead's added cross-section per substrate-frame x bin, from mass:
      (mass now in the bin, the solid wire excluded, minus the substrate's own mass there)
      / (rho0 bin length); the steady value is (pi d^2 / 4) V_wire / V_sub by mass conservation;
    - ``wire_fed_kg`` = rho0 A (length fed: V_wire t less the time stalled) against ``wire_inserted_kg``, the mass of the layers
      the feeder added (equal to within one layer); ``wire_melted_kg``, the wire-origin mass
      no longer in the solid wire, against ``deposit_kg``, the mass over the substrate's
      own in all bins (the difference is material that left the substrate's x range, or
      ``off_substrate_kg``: flung more than a spacing beside the substrate, spatter);
      ``welded_kg``: refrozen wire material that joined the substrate by contact
      (:meth:`WireFeeder.check_contact`; ``welded_kg`` overrides the feeder's count);
      ``escaped_kg``: mass removed from the run as it left the scene (:class:`EscapeBox`;
      the argument overrides the box's count), part of what was fed or melted but no longer
      in any bin;
    - the melt pool: particles above the liquidus, their volume and extents (not counting
      spatter beside or below the substrate: ``n_liquid_away``), peak temperature.
    """
    x, m = state.x, state.m
    wire_origin = state.id >= info["wire_id0"]
    solid_wire = (state.body == WIRE) & (state.phase == Phase.SOLID)
    x0 = x[:, 0] - V_sub * t  # substrate-frame x
    origin, counts = info["substrate_origin"], info["substrate_counts"]
    bin_m = bin_m or 4 * dx
    nb = max(int(counts[0] * dx // bin_m), 1)
    lo = origin[0]
    k = torch.floor((x0 - lo) / bin_m).long()
    # material flung beside the substrate (spatter) is not on the bead: counted apart
    off = (~solid_wire) & (x[:, 1].abs() > 0.5 * counts[1] * dx + dx)
    keep = (~solid_wire) & ~off & (k >= 0) & (k < nb)
    mass_bin = torch.zeros(nb, dtype=m.dtype, device=m.device).index_add_(0, k[keep], m[keep])
    m_sub = float(m[0])  # substrate particles all have one mass
    sub_bin = m_sub * counts[1] * counts[2] * (bin_m / dx)
    added = (mass_bin - sub_bin) / (rho0 * bin_m)
    centres = lo + (torch.arange(nb, dtype=m.dtype) + 0.5) * bin_m
    hot = state.T > T_liquidus
    fused = state.T_peak > T_liquidus  # has been liquid: the fusion zone so far
    pool = {"fused_volume_m3": float((m[fused] / state.rho[fused]).sum())}
    away = hot & (off | (x[:, 2] < -(counts[2] + 1) * dx))  # spatter beside or below the substrate
    pool["n_liquid_away"] = int(away.sum())
    hot = hot & ~away
    if bool(hot.any()):
        xp = x[hot]
        ext = (xp.max(0).values - xp.min(0).values).tolist()
        pool |= {"length_m": ext[0], "width_m": ext[1], "depth_below_top_m": max(0.0, -float(xp[:, 2].min())),
                "volume_m3": float((m[hot] / state.rho[hot]).sum())}
    feeder = info["feeder"]
    fed = rho0 * feeder.area * feeder.fed
    inserted = float(m[wire_origin].sum()) - info["wire_mass0"]
    melted = float(m[wire_origin & ~solid_wire].sum())
    return {"t_s": t, "bin_centres_m": centres.tolist(), "added_area_m2": added.tolist(),
            "expected_area_m2": info["wire_area"] * V_wire / V_sub if V_sub > 0 else math.inf,
            "wire_fed_kg": fed, "wire_inserted_kg": inserted, "wire_melted_kg": melted,
            "deposit_kg": float((mass_bin - sub_bin).sum()),
            "off_substrate_kg": float(m[off].sum()),
            "welded_kg": feeder.welded_kg if welded_kg is None else welded_kg,
            "escaped_kg": (info["escape"].kg if "escape" in info else 0.0) if escaped_kg is None else escaped_kg,
            "wire_stalled_s": feeder.stall_s, "wire_stalls": feeder.n_stalls,
            "wire_stalled_by": {k: {"s": v[0], "waits": v[1]} for k, v in feeder.stall_by.items()},
            "peak_temperature_K": float(state.T.max()), "melt_pool": pool,
            "n_liquid": int(hot.sum()), "n_particles": state.n}
