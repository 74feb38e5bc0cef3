"""Issue 4's Show, on simulated calibration stacks with known aberrations, tilt, defects and noise.

One simulated dataset (module fixture): 300 particles of 1 µm at the paper's signal level (5e5
photons), 3 % defective (dimers and particles of twice the diameter), on a substrate tilted by
2 mrad, imaged through ±3 µm in 121 planes (50 nm steps) at 16 stage positions covering the 2048²
field. The aberrations are the simulator's paper-like map without its random part, whose field
curvature is symmetric about the field centre: a random planar part of the field curvature would be
indistinguishable from substrate tilt, for this method and any other that levels by best focus.
"""

import numpy as np
import pandas as pd
import pytest
from scipy.spatial import cKDTree

from latentz.calibration.pipeline import calibrate
from latentz.calibration.tilt import TiltPlane
from latentz.calibration.traces import extract_traces, traces_table
from latentz.simulate.aberrations import AberrationMap
from latentz.simulate.datasets import calibration_dataset, render_spots

ROI = 21


@pytest.fixture(scope="module")
def sim():
    aberrations = AberrationMap.default(random_nm=0.0)
    ds = calibration_dataset(
        n_particles=300,
        n_stage_positions=16,
        frame_shape=(256, 256),
        z_nm=np.linspace(-3000.0, 3000.0, 121),
        defective_fraction=0.03,
        aberrations=aberrations,
        min_spacing_px=30.0,
        seed=2,
    )
    cal = calibrate(
        list(ds.stacks),
        ds.z_nm,
        camera=ds.camera,
        field_model="nearest",
        stage_offsets_px=ds.origins[:, ::-1],
        roi_size=ROI,
    )
    # each calibration particle's simulated truth (a dimer may be found as two particles)
    dist, idx = cKDTree(ds.truth[["field_x", "field_y"]].to_numpy()).query(cal.positions)
    return ds, cal, ds.truth.iloc[idx].reset_index(drop=True), dist


def _focus_error(sim):
    """z_f against the optics: the simulator's aberration map puts each particle's best focus
    (the peak of its noise-free image, from the pupil function) at the piezo position
    ``z_focus_nm``; the calibration finds z_f at the peak of the fitted amplitude A(z) of noisy
    images (the paper's definition)."""
    ds, cal, truth, dist = sim
    good = ~truth["defective"].to_numpy() & (dist < 1.0) & ~cal.culled
    err = cal.particles["z_f"].to_numpy()[good] - truth["z_focus_nm"].to_numpy()[good]
    print(f"z_f − optical best focus: mean {err.mean():.1f} nm, SD {err.std():.1f} nm")
    return err


def test_focus_follows_the_optical_best_focus_across_the_field(sim):
    # the field dependence of best focus (which tilt and field curvature are made of): every
    # particle's z_f minus the optics' best focus has an SD within the paper's 10 nm
    assert np.std(_focus_error(sim)) <= 10.0


@pytest.mark.xfail(
    strict=True,
    reason="known gap: the peak of the fitted Gaussian amplitude (the paper's z_f) lies about "
    "60 nm below the peak of the noise-free image's brightest pixel (the simulator's best "
    "focus) for this aberration map: measured -59.9 ± 8.4 nm over the good particles",
)
def test_focus_within_10_nm_of_the_optical_best_focus(sim):
    err = _focus_error(sim)
    assert np.mean(np.abs(err) <= 10.0) >= 0.95


def test_tilt_of_2_mrad_is_recovered_within_5_percent(sim):
    ds, cal, truth, _ = sim
    print(
        f"tilt {cal.tilt_mrad:.3f} mrad (truth {ds.tilt_mrad}), azimuth "
        f"{np.degrees(cal.plane.azimuth_rad):.1f}° (truth {np.degrees(ds.tilt_direction_rad):.1f}°)"
    )
    assert cal.tilt_mrad == pytest.approx(ds.tilt_mrad, rel=0.05)
    # the substrate rises along the tilt direction, so best focus (piezo) falls along it and the
    # normal of the z_f plane leans the same way; a 5 % error across the axis is 0.05 rad
    lean = np.angle(np.exp(1j * (cal.plane.azimuth_rad - ds.tilt_direction_rad)))
    assert abs(lean) < 0.1


def test_sigma_z_of_rho_a_over_6_um_is_reported(sim):
    _, cal, _, _ = sim
    kept = ~cal.culled
    values = {s: np.nanmean(cal.mean_sigma_z(s, 6000.0)[kept]) for s in ("rho", "rho_w", "rho_A")}
    print(
        "mean σ_z over 6 µm (nm):",
        {k: round(v, 1) for k, v in values.items()},
        "— paper, rho_A: 25–40 nm",
    )
    # rho_A must cover the 6 µm range for most particles, and beat rho_w there (paper Fig. 3d)
    assert np.mean(np.isfinite(cal.mean_sigma_z("rho_A", 6000.0)[kept])) >= 0.9
    assert values["rho_A"] < values["rho_w"]


def test_defective_particles_are_culled(sim):
    ds, cal, truth, dist = sim
    bad = ds.truth["defective"].to_numpy()
    # a defective particle counts as culled when every calibration particle on it is culled
    on = cKDTree(cal.positions).query_ball_point(ds.truth[["field_x", "field_y"]], r=6.0)
    found = np.array([len(i) > 0 for i in on])
    culled = np.array([len(i) > 0 and cal.culled[i].all() for i in on])
    assert found[bad].all()
    print(
        f"culled {culled[bad].mean():.0%} of {bad.sum()} defective, "
        f"{culled[~bad & found].mean():.1%} of {np.sum(~bad & found)} good"
    )
    assert culled[bad].mean() >= 0.9
    assert culled[~bad & found].mean() <= 0.02


def _independent_emitters(ds, cal, *, diameter_nm, seed):
    """40 test emitters that are not calibration particles: random field positions 4-10 px from
    the nearest calibration particle, 0.3x the calibration particles' photons, the given
    diameter, centred at the height a calibration particle's centre would have there, at a
    random z within ±2 µm on the calibration's axis. Returns (spots, true z)."""
    rng = np.random.default_rng(seed)
    kept = ~cal.culled
    tree = cKDTree(cal.positions[kept])
    field = np.asarray(cal.options["field_shape"], float)
    chosen = []
    while len(chosen) < 40:
        p = rng.uniform(40.0, field[::-1] - 40.0)
        if 4.0 <= tree.query(p)[0] <= 10.0:
            chosen.append(p)
    chosen = np.array(chosen)
    surface = TiltPlane.from_estimate(
        *ds.truth[["field_x", "field_y"]].to_numpy().T, ds.truth["z_surface_nm"].to_numpy()
    )
    height = surface(*chosen.T) + 500.0  # a calibration particle's centre (1 µm nominal)
    z_true = rng.uniform(-2000.0, 2000.0, len(chosen))
    piezo = z_true + cal.plane(*(chosen * 130.0).T)
    spots = []
    for i, p in enumerate(chosen):
        corner = np.rint(p).astype(int) - 16
        emitter = pd.DataFrame(
            {
                "x": [p[0] - corner[0]],
                "y": [p[1] - corner[1]],
                "z_nm": [height[i] + piezo[i]],
                "photons": [0.3 * 5e5],
                "diameter_nm": [diameter_nm],
            }
        )
        image, _ = render_spots(
            emitter,
            frame_shape=(33, 33),
            origin=(int(corner[1]), int(corner[0])),
            z_piezo_nm=0.0,
            camera=ds.camera,
            optics=ds.optics,
            aberrations=ds.aberrations,
            background=ds.background,
            seed=seed + i,
        )
        traces = extract_traces(
            [image],
            np.zeros(1),
            camera=ds.camera,
            roi_size=ROI,
            positions=[[p - corner]],
            stage_offsets_px=[corner],
        )
        spots.append(traces_table(traces))
    return pd.concat(spots, ignore_index=True), z_true


@pytest.mark.parametrize(
    "diameter_nm",
    [
        pytest.param(
            1000.0,
            marks=pytest.mark.xfail(
                strict=True,
                reason="known gap: for 1 µm emitters at 0.3x the calibration's brightness, 4-10 px "
                "from a calibration particle, the brightness correction (calibration.dimming) "
                "cut the z RMSE from 45.7 to 20.8 nm (bias +0.7 nm), but the reported z_err_nm "
                "(15.6 nm: sandwich fit, local and cross-validated field parts) is still 0.75x "
                "it, short of the 0.8x the test allows (docs/accuracy.md)",
            ),
        ),
        pytest.param(
            0.0,
            marks=pytest.mark.xfail(
                strict=True,
                reason="known gap: a point emitter's image changes with z unlike a 1 µm "
                "particle's (paper Supp. Fig. 9), so a particle calibration does not transfer: "
                "measured z RMSE 189 nm, bias +66 nm, against a reported 13.5 nm",
            ),
        ),
    ],
    ids=["particles", "point-emitters"],
)
def test_independent_emitters_are_localized_within_their_uncertainty(sim, diameter_nm):
    """Emitters independent of the calibration particles (other positions, 0.3x the
    brightness, and point emitters) localized with the intensity-independent ρ_w."""
    from latentz.calibration.pipeline import calibrate_traces

    ds, cal, _, _ = sim
    rho_w = calibrate_traces(cal.traces, camera=cal.camera, shape="rho_w", field_model="nearest")
    spots, z_true = _independent_emitters(ds, rho_w, diameter_nm=diameter_nm, seed=11)
    located = rho_w.apply(spots)
    inside = located["in_range"].to_numpy()
    err = located["z_nm"].to_numpy()[inside] - z_true[inside]
    sigma = located["z_err_nm"].to_numpy()[inside]
    rmse, reported = np.sqrt(np.mean(err**2)), np.sqrt(np.mean(sigma**2))
    print(
        f"{diameter_nm:.0f} nm emitters: {inside.mean():.0%} in range, z RMSE {rmse:.1f} nm, "
        f"bias {err.mean():+.1f} nm, reported σ_z {reported:.1f} nm"
    )
    assert inside.mean() >= 0.9
    # 36+ errors: their RMS is within ~25 % of its expectation (3 standard errors); the
    # reported uncertainty must account for it
    assert rmse <= 1.25 * reported


def test_auto_shapes_on_the_pi_over_4_microscope(sim):
    from latentz.calibration.pipeline import calibrate_traces

    _, cal, _, _ = sim
    kept = ~cal.culled
    for shape, paper in (("auto", "rho_w"), ("auto_A", "rho_A")):
        auto = calibrate_traces(cal.traces, camera=cal.camera, shape=shape, field_model="nearest")
        # oblique astigmatism dominates the simulated map: θ ≈ π/4 (vertical Z6 tilts it a bit)
        assert auto.local.theta == pytest.approx(np.pi / 4, abs=0.1)
        mine = np.nanmean(auto.mean_sigma_z(shape, 4000.0)[kept])
        theirs = np.nanmean(cal.mean_sigma_z(paper, 4000.0)[kept])
        print(
            f"θ = {auto.local.theta:.3f} rad; mean σ_z over 4 µm: {shape} {mine:.1f} nm, "
            f"{paper} {theirs:.1f} nm"
        )
        assert mine == pytest.approx(theirs, rel=0.15)
