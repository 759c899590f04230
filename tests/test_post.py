"""Post-processing on synthetic particle sets with known answers (issue 7)."""
import math

import numpy as np
import pytest

from torchsph.post import analysis as post
from torchsph.post import pictures, solidification

DX = 1.0e-4
TL = 1753.15


def lattice(lo, hi, dx=DX):
    axes = [np.arange(a + 0.5 * dx, b, dx) for a, b in zip(lo, hi)]
    return np.stack(np.meshgrid(*axes, indexing="ij"), -1).reshape(-1, 3)


def snap_of(x, T=None, Tp=None, t=0.0, body=None, phase=None):
    n = x.shape[0]
    T = np.full(n, 300.0) if T is None else T
    return {"position": x, "temperature": T, "peak_temperature": T.copy() if Tp is None else Tp,
            "velocity": np.zeros_like(x), "density": np.full(n, 7890.0), "mass": np.full(n, 7890.0 * DX**3),
            "phase": np.full(n, 2) if phase is None else phase, "body": np.ones(n, int) if body is None else body,
            "id": np.arange(n), "time": t}


def cfg_of(size):
    return {"scene": {"type": "deposition", "dx_m": DX, "substrate_size_m": size,
                      "substrate_velocity_m_s": [0.0, 0.0, 0.0]}, "thermal": {"liquidus_K": TL}}


def test_half_cylinder_bead_on_a_block():
    """A block 4 x 3 x 1 mm (top z = 0) with a half-cylinder bead of radius 0.6 mm along x on
    top, and a fusion zone (peak T > T_L) of half-width 0.8 mm and depth 0.35 mm (half
    ellipse) under it: width, height and penetration within one particle spacing, the added
    cross-section within 5 % of pi R^2 / 2; a detached drop over the bead does not count."""
    R, P, Wf = 0.6e-3, 0.35e-3, 0.8e-3
    block = lattice((0, -1.5e-3, -1e-3), (4e-3, 1.5e-3, 0))
    cand = lattice((0, -R, 0), (4e-3, R, R))
    bead = cand[cand[:, 1] ** 2 + cand[:, 2] ** 2 < R * R]
    x = np.concatenate([block, bead])
    Tp = np.full(x.shape[0], 600.0)
    fz = (x[:, 1] / Wf) ** 2 + (x[:, 2] / P) ** 2 < 1.0
    Tp[fz] = 2000.0
    # spatter: a drop of 8 particles flung 20 mm aside and 5 mm up over the same columns is
    # not part of the bead (not attached to the substrate)
    drop = lattice((2e-3, 20e-3, 5e-3), (2.2e-3, 20.2e-3, 5.2e-3))
    x = np.concatenate([x, drop])
    Tp = np.concatenate([Tp, np.full(drop.shape[0], 2100.0)])
    s = snap_of(x, Tp=Tp)
    assert post.detached(s, DX).sum() == drop.shape[0] == 8
    prof = post.bead_profile(s, cfg_of([4e-3, 3e-3, 1e-3]))
    b = post.steady_average(prof, 0.5e-3, 3.5e-3)
    assert b["columns"] >= 29
    assert abs(b["width_m"] - 2 * R) <= DX
    assert abs(b["height_m"] - R) <= DX
    assert abs(b["penetration_m"] - P) <= DX
    assert abs(b["added_area_m2"] / (math.pi * R * R / 2) - 1) < 0.05
    assert abs(b["toe_angle_deg"] - 90.0) < 5.0  # a half cylinder meets the top at 90 deg


def test_toe_angle_of_a_circular_segment_bead():
    """A bead cut from a cylinder of radius 1.2 mm whose axis lies 0.6 mm below the top (a
    circular segment meeting the top at 60 deg): the toe angle within 4 deg."""
    Rc, zc = 1.2e-3, -0.6e-3
    block = lattice((0, -1.5e-3, -1e-3), (4e-3, 1.5e-3, 0))
    cand = lattice((0, -Rc, 0), (4e-3, Rc, Rc))
    bead = cand[cand[:, 1] ** 2 + (cand[:, 2] - zc) ** 2 < Rc * Rc]
    prof = post.bead_profile(snap_of(np.concatenate([block, bead])), cfg_of([4e-3, 3e-3, 1e-3]))
    b = post.steady_average(prof, 0.5e-3, 3.5e-3)
    assert abs(b["toe_angle_deg"] - 60.0) < 4.0, b


def test_bead_columns_stay_on_the_lattice_with_spatter_far_away():
    """A drop fallen far below and behind the substrate (off the lattice, as spatter that
    leaked through lies) neither moves the columns off the substrate's lattice nor adds to
    any column: the profile equals the one without it."""
    R = 0.6e-3
    block = lattice((0, -1.5e-3, -1e-3), (4e-3, 1.5e-3, 0))
    cand = lattice((0, -R, 0), (4e-3, R, R))
    x = np.concatenate([block, cand[cand[:, 1] ** 2 + cand[:, 2] ** 2 < R * R]])
    n = x.shape[0]
    phase = np.full(n, 2)
    cfg = cfg_of([4e-3, 3e-3, 1e-3])
    ref = post.bead_profile(snap_of(x, phase=phase), cfg)
    fallen = np.array([[-37.31e-3, 0.4e-3, -50.0e-3], [-37.2e-3, 0.5e-3, -50.1e-3]])
    s = snap_of(np.concatenate([x, fallen]), phase=np.concatenate([phase, [0, 0]]),
                body=np.concatenate([np.ones(n, int), [0, 0]]))
    prof = post.bead_profile(s, cfg)
    on = (prof["x0_m"] > 0) & (prof["x0_m"] < 4e-3)
    assert np.allclose(prof["x0_m"][on], ref["x0_m"], atol=1e-12)  # the lattice's column centres
    for k in ("width_m", "height_m", "penetration_m", "added_area_m2"):
        assert np.allclose(prof[k][on], ref[k], atol=1e-15), k


def test_ellipsoidal_melt_pool():
    """T > T_L inside the half ellipsoid (x/a)^2 + (y/b)^2 + (z/c)^2 < 1, z < 0, a = 1.5 mm,
    b = 0.7 mm, c = 0.4 mm: length 2a, width 2b, depth c within one spacing; volume within
    5 % of (2/3) pi a b c."""
    a, b, c = 1.5e-3, 0.7e-3, 0.4e-3
    x = lattice((-3e-3, -2e-3, -1.5e-3), (3e-3, 2e-3, 0))
    inside = (x[:, 0] / a) ** 2 + (x[:, 1] / b) ** 2 + (x[:, 2] / c) ** 2 < 1
    T = np.where(inside, 2200.0, 900.0)
    mp = post.melt_pool(snap_of(x, T=T), TL, DX, vol=np.full(x.shape[0], DX**3))
    assert abs(mp["length_m"] - 2 * a) <= DX
    assert abs(mp["width_m"] - 2 * b) <= DX
    assert abs(mp["depth_m"] - c) <= DX
    assert abs(mp["volume_m3"] / (2 / 3 * math.pi * a * b * c) - 1) < 0.05
    assert mp["peak_temperature_K"] == 2200.0


def test_solidification_data_and_exaca_csv(tmp_path):
    """T(x, t) = T0 + G x - c t on a lattice sampled every 1 ms: every particle crosses T_L
    while cooling at t = (T0 + G x - T_L) / c. The cooling rate is c, the gradient G, the
    solidification rate c / G, the crossing time exact (T is linear in t), and the CSV has
    ExaCA's header and one row per lattice cell."""
    G, c, T0 = 2.0e5, 1.0e4, 2100.0
    x = lattice((0, 0, 0), (1e-3, 0.4e-3, 0.4e-3))
    snaps = []
    for k in range(80):
        t = 1e-3 * k
        snaps.append(snap_of(x, T=T0 + G * x[:, 0] - c * t, t=t))
    sol = solidification.solidification(snaps, TL, DX)
    assert sol["id"].size == x.shape[0]
    order = np.argsort(sol["id"])
    exact_tl = (T0 + G * x[:, 0] - TL) / c
    assert np.allclose(sol["tl"][order], exact_tl, rtol=0, atol=1e-12)
    assert np.allclose(sol["cr"], c, rtol=1e-9)
    assert np.allclose(sol["G"], G, rtol=1e-6)
    assert np.allclose(sol["R"], c / G, rtol=1e-6)
    assert np.all(sol["tm"] == 0.0)  # liquid from the start: melting time = first snapshot
    n = solidification.write_exaca_csv(tmp_path / "e.csv", sol, DX)
    lines = (tmp_path / "e.csv").read_text().splitlines()
    assert lines[0] == "x,y,z,tm,tl,cr" and len(lines) == n + 1 == x.shape[0] + 1
    row = np.array(lines[1].split(","), float)
    assert np.allclose(row[:3] / DX, np.round(row[:3] / DX)) and row[5] == pytest.approx(c)


def test_render_png(tmp_path):
    """Off-screen render; skips only where PyVista is missing or VTK cannot open a context."""
    pv = pytest.importorskip("pyvista")
    x = lattice((0, 0, 0), (1e-3, 1e-3, 0.3e-3))
    s = snap_of(x, T=300 + 1e6 * x[:, 0], phase=np.where(x[:, 0] > 5e-4, 0, 2))
    s["velocity"][:, 1] = 0.1
    try:
        pictures.render(s, tmp_path / "t.png", what="temperature", window=(200, 150))
        pictures.render(s, tmp_path / "v.png", what="velocity", window=(200, 150))
    except Exception as e:  # noqa: BLE001 - VTK raises various errors without an OpenGL context
        pytest.skip(f"VTK could not render off-screen here: {e}")
    for f in ("t.png", "v.png"):
        img = pv.read(str(tmp_path / f))
        assert img.n_points == 200 * 150


def test_section_picture_and_numbers(tmp_path):
    """The transverse section of the synthetic bead: a PNG, and the numbers of that column
    (width 2R, penetration P within one spacing)."""
    pytest.importorskip("matplotlib")
    R, P = 0.5e-3, 0.3e-3
    block = lattice((0, -1.5e-3, -1e-3), (2e-3, 1.5e-3, 0))
    cand = lattice((0, -R, 0), (2e-3, R, R))
    x = np.concatenate([block, cand[cand[:, 1] ** 2 + cand[:, 2] ** 2 < R * R]])
    Tp = np.where(x[:, 1] ** 2 / R**2 + x[:, 2] ** 2 / P**2 < 1, 2000.0, 500.0)
    nums = post.section(snap_of(x, Tp=Tp), cfg_of([2e-3, 3e-3, 1e-3]), 1.0e-3, tmp_path / "s.png")
    assert (tmp_path / "s.png").stat().st_size > 5000
    assert abs(nums["width_m"] - 2 * R) <= DX and abs(nums["penetration_m"] - P) <= DX
    assert abs(nums["x0_m"] - 1.0e-3) <= DX / 2


def test_pyvista_sections_show_the_fusion_zone(tmp_path):
    """The PyVista picture of the section (Fig. 6.6), two panels: each panel returns the
    numbers of :func:`post.section` for that column, and the fusion zone (peak T above T_L)
    is drawn crimson: the panel with a fusion zone has crimson pixels, the one without has
    none. Skips only where PyVista is missing or VTK cannot open a context."""
    pv = pytest.importorskip("pyvista")
    R, P = 0.5e-3, 0.3e-3
    block = lattice((0, -1.5e-3, -1e-3), (2e-3, 1.5e-3, 0))
    cand = lattice((0, -R, 0), (2e-3, R, R))
    x = np.concatenate([block, cand[cand[:, 1] ** 2 + cand[:, 2] ** 2 < R * R]])
    Tp = np.where(x[:, 1] ** 2 / R**2 + x[:, 2] ** 2 / P**2 < 1, 2000.0, 500.0)
    cfg = cfg_of([2e-3, 3e-3, 1e-3])
    fused, cold = snap_of(x, Tp=Tp), snap_of(x, Tp=np.full(x.shape[0], 500.0))
    try:
        nums = pictures.render_sections([(fused, cfg, "fused"), (cold, cfg, "cold")], 1.0e-3, tmp_path / "s.png",
                                    panel=(240, 160))
    except Exception as e:  # noqa: BLE001 - VTK raises various errors without an OpenGL context
        pytest.skip(f"VTK could not render off-screen here: {e}")
    assert abs(nums[0]["width_m"] - 2 * R) <= DX and abs(nums[0]["penetration_m"] - P) <= DX
    assert abs(nums[1]["width_m"] - 2 * R) <= DX and nums[1]["penetration_m"] == 0.0  # nothing fused
    img = pv.read(str(tmp_path / "s.png"))
    rgb = np.asarray(img.point_data[img.point_data.keys()[0]])[:, :3].astype(int).reshape(160, 480, 3)
    r, g, b = rgb[..., 0], rgb[..., 1], rgb[..., 2]
    crimson = (r > 100) & (r > 2.5 * g) & (r > 2 * b)  # shaded crimson; cividis has no red
    assert crimson[:, :240].sum() > 500 and crimson[:, 240:].sum() == 0  # the colour bar's swatch is ~50


def test_melt_pool_is_the_largest_connected_liquid():
    """A drop of liquid 2 mm above the pool is not part of it (counted as detached)."""
    a, b, c = 1.0e-3, 0.6e-3, 0.3e-3
    x = lattice((-2e-3, -1.5e-3, -1e-3), (2e-3, 1.5e-3, 0))
    T = np.where((x[:, 0] / a) ** 2 + (x[:, 1] / b) ** 2 + (x[:, 2] / c) ** 2 < 1, 2200.0, 900.0)
    drop = lattice((1.5e-3, 0, 2e-3), (1.8e-3, 0.3e-3, 2.3e-3))
    x = np.concatenate([x, drop])
    T = np.concatenate([T, np.full(drop.shape[0], 2000.0)])
    mp = post.melt_pool(snap_of(x, T=T), TL, DX, vol=np.full(x.shape[0], DX**3))
    assert abs(mp["length_m"] - 2 * a) <= DX and mp["n_detached"] == drop.shape[0]
    # and spatter falling past the substrate, bigger than the pool, is not the pool
    fall = lattice((5e-3, 0, -0.3), (6.5e-3, 1.5e-3, -0.3 + 1.5e-3))
    x2 = np.concatenate([x, fall])
    T2 = np.concatenate([T, np.full(fall.shape[0], 2000.0)])
    mp = post.melt_pool(snap_of(x2, T=T2), TL, DX, vol=np.full(x2.shape[0], DX**3), bottom=-1.1e-3)
    assert abs(mp["length_m"] - 2 * a) <= DX and abs(mp["depth_m"] - c) <= DX
    assert mp["n_detached"] == drop.shape[0] + fall.shape[0]


def test_fed_cross_section_is_the_nominal_less_the_stall():
    """A wire (1.2 mm, 30 mm/s) over a substrate at 15 mm/s, its feed waiting from 0.10 to
    0.12 s: the columns that passed under it in 0.05-0.09 s got the nominal 2.26 mm^2, those
    of 0.08-0.16 s (a quarter of it stalled) 3/4 of it; spans outside the history are NaN."""
    rho0, V, Vw, d = 7890.0, 0.015, 0.03, 1.2e-3
    mdot = rho0 * math.pi * d**2 / 4 * Vw
    ts = np.linspace(0.0, 0.2, 41)
    fed = mdot * (np.minimum(ts, 0.10) + np.clip(ts - 0.12, 0.0, None))
    hist = [{"t_s": float(t), "wire_fed_kg": float(f)} for t, f in zip(ts, fed)]
    nominal = math.pi * d**2 / 4 * Vw / V
    assert post.fed_cross_section(hist, -0.09 * V, -0.05 * V, V, rho0) == pytest.approx(nominal, rel=1e-12)
    assert post.fed_cross_section(hist, -0.16 * V, -0.08 * V, V, rho0) == pytest.approx(0.75 * nominal, rel=1e-12)
    assert math.isnan(post.fed_cross_section(hist, -0.25 * V, -0.15 * V, V, rho0))


def test_bead_settling_tells_filled_bins_from_growing_ones():
    """Three bins: one full for 0.1 s, one still filling (+20 % in the last 0.05 s), one
    empty (under the wire). Only the full one is settled, and the settled mean is its area;
    a lag longer than the history is an error, as are bins that moved."""
    ts = [0.0, 0.05, 0.10, 0.15]
    hist = [{"t_s": t, "bin_centres_m": [-3e-3, -2e-3, -1e-3],
             "added_area_m2": [2.2e-6 if t >= 0.05 else 1.0e-6, 1.5e-6 + 4e-6 * (t - 0.10) if t >= 0.10 else 0.0, 0.0]}
            for t in ts]
    s = post.bead_settling(hist, -3.5e-3, -0.5e-3, lag_s=0.05, tolerance=0.05)
    assert s["t_before_s"] == 0.10
    assert [r["settled"] for r in s["bins"]] == [True, False, False]
    assert s["bins"][1]["change"] == pytest.approx(0.2e-6 / 1.7e-6, rel=1e-12)
    assert s["settled_bins"] == 1 and s["settled_m2"] == pytest.approx(2.2e-6, rel=1e-12)
    assert post.bead_settling(hist, -3.5e-3, -2.5e-3, lag_s=0.05)["bins"][0]["x0_m"] == -3e-3
    with pytest.raises(ValueError, match="no entry"):
        post.bead_settling(hist, -3.5e-3, -0.5e-3, lag_s=0.2)
    moved = hist[:-1] + [dict(hist[-1], bin_centres_m=[-2.5e-3, -1.5e-3, -0.5e-3])]
    with pytest.raises(ValueError, match="bins differ"):
        post.bead_settling(moved, -3.5e-3, -0.5e-3, lag_s=0.05)


def test_settling_report_reads_the_runs_deposit_history(tmp_path):
    """post.summarize's bead_settling entry: from RUN/deposit.json; a missing file or a
    history shorter than the lag is reported, not raised."""
    import json
    assert post.settling_report(tmp_path, -3e-3, -1e-3) == {"error": "no deposit.json"}
    hist = [{"t_s": t, "bin_centres_m": [-2e-3, -1e-3], "added_area_m2": [2.0e-6, 1.0e-6 + 1e-5 * t]}
            for t in (0.0, 0.05, 0.10)]
    (tmp_path / "deposit.json").write_text(json.dumps(hist))
    rep = post.settling_report(tmp_path, -2.5e-3, -0.5e-3)
    assert [b["settled"] for b in rep["bins"]] == [True, False]  # +0.5e-6 of 2e-6 in 0.05 s
    assert rep["settled_m2"] == pytest.approx(2.0e-6, rel=1e-12)
    assert "no entry" in post.settling_report(tmp_path, -2.5e-3, -0.5e-3, lag_s=0.2)["error"]


def test_pictures_frame_the_melt_and_say_when_there_is_none(tmp_path):
    """The render is framed on what has melted (a long cold wire is left out) and a velocity
    picture without melt is not drawn (render returns False, no file)."""
    x = lattice((0, 0, 0), (1e-3, 1e-3, 0.3e-3))
    s = snap_of(x, T=np.full(len(x), 300.0), phase=np.full(len(x), 2))
    s["peak_temperature"] = np.where(x[:, 0] < 3e-4, 2000.0, 300.0)
    cfg = {"thermal": {"liquidus_K": 1753.0}}
    lo, hi = pictures.focus_box(s, cfg, pad_m=1e-4)
    assert hi[0] == pytest.approx(x[x[:, 0] < 3e-4, 0].max() + 1e-4) and lo[0] == pytest.approx(x[:, 0].min() - 1e-4)
    assert pictures.focus_box(s, {"thermal": {"liquidus_K": 3000.0}}) is None  # nothing melted: frame everything
    pytest.importorskip("pyvista")
    try:
        drawn = pictures.render(s, tmp_path / "v.png", cfg, what="velocity", window=(200, 150))
    except Exception as e:  # noqa: BLE001 - VTK raises various errors without an OpenGL context
        pytest.skip(f"VTK could not render off-screen here: {e}")
    assert drawn is False and not (tmp_path / "v.png").exists()


def test_richardson_recovers_the_limit_and_the_order():
    """f(h) = 2.26 + 0.8 h^1.7 at an uneven ladder: the limit and the order come back to
    round-off; an oscillating sequence and two values are refused with a reason."""
    h = [0.4, 0.3, 0.25, 0.2]
    f = [2.26 + 0.8 * x**1.7 for x in h]
    r = post.richardson(h, f)
    assert abs(r["p"] - 1.7) < 1e-9 and abs(r["f0"] - 2.26) < 1e-12, r
    r = post.richardson([0.4, 0.3, 0.2], [2.0, 2.3, 2.1])
    assert math.isnan(r["f0"]) and "monotone" in r["why"]
    assert math.isnan(post.richardson([0.3, 0.2], [2.0, 2.1])["f0"])
