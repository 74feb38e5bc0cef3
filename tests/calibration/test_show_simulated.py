"""Issue 4's Show, on simulated calibration stacks with known aberrations, tilt, defects and noise.

One simulated dataset (module fixture): 300 particles of 1 µm at the paper's signal level (5e5
photons), 3 % defective (dimers and particles of twice the diameter), on a substrate tilted by
2 mrad, imaged through ±3 µm in 121 planes (50 nm steps) at 16 stage positions covering the 2048²
field. The aberrations are the simulator's paper-like map without its random part, whose field
curvature is symmetric about the field centre: a random planar part of the field curvature would be
indistinguishable from substrate tilt, for this method and any other that levels by best focus.
"""

import warnings

import numpy as np
import pandas as pd
import pytest
from scipy.optimize import least_squares
from scipy.spatial import cKDTree

from latentz.calibration.tilt import TiltPlane
from latentz.calibration.traces import extract_traces, traces_table
from latentz.calibration.workflow import calibrate
from latentz.simulate.aberrations import AberrationMap
from latentz.simulate.datasets import calibration_dataset, render_spots

ROI = 21


def simulated_calibration():
    """The module's dataset and its calibration: (dataset, calibration, each calibration
    particle's simulated truth, distance to it in px)."""
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


@pytest.fixture(scope="module")
def sim():
    return simulated_calibration()


def _gaussian_amplitude(image: np.ndarray, start: np.ndarray, readnoise: float) -> np.ndarray:
    """Parameters (x, y, A, B, wx, wy, ρ) of eq. 1 fitted to a noise-free image (photoelectrons)
    by Poisson maximum likelihood with the read noise as in the calibration's fit
    (``d + s² ~ Poisson(μ + s²)``), with scipy: least squares on the deviance residuals."""
    rows, cols = np.indices(image.shape, dtype=float)
    data = image + readnoise**2

    def residuals(p):
        dx, dy = (cols - p[0]) / p[4], (rows - p[1]) / p[5]
        q = (dx**2 + dy**2 - 2 * p[6] * dx * dy) / (2 * (1 - p[6] ** 2))
        mu = p[2] * np.exp(-q) + p[3] + readnoise**2
        deviance = 2 * (data * np.log(data / mu) - (data - mu))
        return (np.sign(data - mu) * np.sqrt(np.maximum(deviance, 0.0))).ravel()

    bounds = ([0, 0, 0, 0, 0.3, 0.3, -0.95], [ROI, ROI, np.inf, np.inf, ROI, ROI, 0.95])
    return least_squares(residuals, start, bounds=bounds, x_scale="jac", xtol=1e-10).x


def _gaussian_focus_nm(ds, particle: pd.Series) -> float:
    """The paper's best focus from the optics, without latentz's fitter: the piezo z at which the
    amplitude A of eq. 1, fitted by scipy to the simulator's noise-free images of this particle
    (its field position, diameter and photons, on a ROI x ROI patch), peaks. A is sampled every
    40 nm from 300 nm below to 140 nm above the brightest-pixel focus, and its maximum refined
    by a parabola through the five samples around it."""
    coef = ds.aberrations.at(np.array([particle.field_x]), np.array([particle.field_y]))
    wave = np.tensordot(coef.reshape(1, -1), ds.optics.zernike_basis(ds.aberrations.modes), 1)
    defocus = particle.focus_defocus_nm + np.arange(-300.0, 141.0, 40.0)
    centre = np.tile([ROI // 2, ROI // 2], (defocus.size, 1)).astype(float)
    images = ds.optics.render_batch(wave, defocus, centre, (ROI, ROI), particle.diameter_nm)
    start = np.array([ROI // 2, ROI // 2, 1.0, ds.background, 3.0, 3.0, 0.0])
    amplitude = []
    for image in images * particle.photons + ds.background:
        start[2] = image.max() - ds.background
        start = _gaussian_amplitude(image, start, ds.camera.readnoise)
        amplitude.append(start[2])
    k = int(np.argmax(amplitude))
    assert 2 <= k <= defocus.size - 3, "the amplitude peak must lie inside the scanned range"
    c = np.polyfit(defocus[k - 2 : k + 3] - defocus[k], amplitude[k - 2 : k + 3], 2)
    return defocus[k] - c[1] / (2 * c[0]) - particle.z_nm  # defocus -> piezo z


@pytest.fixture(scope="module")
def focus_error(sim):
    """z_f minus the optics' best focus for 40 good particles drawn at random over the field.

    The truth is the paper's definition (the peak of the fitted amplitude A(z), Fig. 2d), from
    noise-free images and a fit that is not latentz's. It is not the simulator's ``z_focus_nm``
    (the peak of the brightest pixel), which lies about 60 nm above it for this aberration map:
    primary spherical aberration (Z11 = 12 nm RMS) makes the image asymmetric through focus, and
    the plane where the central pixel is brightest (the most intense core) is not the plane where
    the Gaussian that best fits the whole spot, halo included, is highest. Measured on noise-free
    images: 0 nm without Z11, -50 nm with Z11 = +12 nm at the field centre (1 µm particle; -80 nm
    for a point), +50 nm with Z11 = -12 nm; -50 to -65 nm over this field; the brightest pixel
    also moves with the particle's sub-pixel position (up to 43 nm), A's peak by < 0.5 nm."""
    ds, cal, truth, dist = sim
    good = np.flatnonzero(~truth["defective"].to_numpy() & (dist < 1.0) & ~cal.culled)
    chosen = np.random.default_rng(0).choice(good, 40, replace=False)
    optical = np.array([_gaussian_focus_nm(ds, truth.iloc[i]) for i in chosen])
    err = cal.particles["z_f"].to_numpy()[chosen] - optical
    brightest = truth["z_focus_nm"].to_numpy()[chosen] - optical
    print(
        f"z_f − best focus (fitted A): mean {err.mean():+.1f} nm, SD {err.std():.1f} nm; "
        f"brightest-pixel focus − fitted-A focus: mean {brightest.mean():+.1f} nm"
    )
    return err


@pytest.mark.slow
def test_focus_follows_the_optical_best_focus_across_the_field(focus_error):
    # the field dependence of best focus (which tilt and field curvature are made of): every
    # particle's z_f minus the optics' best focus has an SD within the paper's 10 nm
    assert np.std(focus_error) <= 10.0


@pytest.mark.slow
def test_focus_within_10_nm_of_the_optical_best_focus(focus_error):
    # a z_f 10 nm off, for all particles (a bias) or each its own way (scatter), gives an RMS of
    # at least 10 nm; the shot noise of 5e5-photon particles gives about 4 nm
    assert np.sqrt(np.mean(focus_error**2)) <= 10.0


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


def independent_emitters(ds, cal, *, diameter_nm, seed, photons=0.3 * 5e5, noise=True):
    """40 test emitters that are not calibration particles: random field positions 4-10 px from
    the nearest calibration particle, ``photons`` (default 0.3x the calibration particles'), the
    given diameter, centred at the height a calibration particle's centre would have there, at a
    random z within ±2 µm on the calibration's axis; with camera noise, or (``noise=False``) the
    expected image in ADU. Returns (spots, true z)."""
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
                "photons": [photons],
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
            noise=noise,
            seed=seed + i,
        )
        if not noise:
            image = ds.camera.to_adu(image)
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
        1000.0,  # its emitters (traces_table) carry the sandwich errors, as localize's spots do
    ],
    ids=["particles"],
)
def test_independent_emitters_are_localized_within_their_uncertainty(sim, diameter_nm):
    """Emitters independent of the calibration particles (other positions, 0.3x the
    brightness) localized with the intensity-independent ρ_w. Point emitters: the next test."""
    from latentz.calibration.workflow import calibrate_traces

    ds, cal, _, _ = sim
    rho_w = calibrate_traces(cal.traces, camera=cal.camera, shape="rho_w", field_model="nearest")
    spots, z_true = independent_emitters(ds, rho_w, diameter_nm=diameter_nm, seed=11)
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
    # the RMS of n normal errors lies within 3 standard errors, 3/√(2n), of its expectation
    # (34 % for these 40); the reported uncertainty must account for it, and not by more
    within = 1 + 3 / np.sqrt(2 * inside.sum())
    assert rmse <= within * reported
    assert reported <= within * rmse


@pytest.mark.slow
def test_point_emitters_are_flagged_against_a_particle_calibration(sim):
    """A calibration made with 1 µm particles does not localize point emitters (paper Supp.
    Fig. 9: a particle's image is the PSF blurred by the particle, so its shape changes with z
    unlike a point's; measured z RMSE ~190 nm against ~20 nm reported). latentz must say so:
    the point emitters' widths far below the calibration's, one warning naming emitters smaller
    than the calibration particles, nothing good; while emitters like
    the calibration particles (1 µm, at other places and brightness) stay consistent."""
    from latentz.calibration.workflow import calibrate_traces
    from latentz.localization.mismatch import calibration_mismatch, check_calibration_fits
    from latentz.localization.quality import CHI2_LIMIT, assess

    ds, cal, _, _ = sim
    rho_w = calibrate_traces(cal.traces, camera=cal.camera, shape="rho_w", field_model="nearest")

    def localized(diameter_nm):
        spots, z_true = independent_emitters(ds, rho_w, diameter_nm=diameter_nm, seed=11)
        spots = spots.drop(columns="z_nm").assign(frame=np.arange(len(spots)))
        return assess(rho_w.apply(spots), rho_w), z_true

    points, z_true = localized(0.0)
    err = points["z_nm"].to_numpy() - z_true
    rmse = np.sqrt(np.nanmean(err**2))
    reported = np.sqrt(np.nanmean(points["z_err_nm"].to_numpy() ** 2))
    chi2 = points["consistency_chi2"].to_numpy()
    print(
        f"point emitters: z RMSE {rmse:.0f} nm, reported {reported:.1f} nm; consistency χ² "
        f"{np.nanmin(chi2):.0f}–{np.nanmax(chi2):.0f}; {calibration_mismatch(points, rho_w)}"
    )
    # against truth: their errors are far outside the reported uncertainty (5x, while for 1 µm
    # emitters it holds within 1.25x: the test above), so none may be good
    assert rmse > 5 * reported
    located = np.isfinite(chi2)
    assert located.mean() >= 0.9
    with pytest.warns(UserWarning, match="emitters smaller than the calibration particles"):
        checked = check_calibration_fits(points, rho_w)
    assert not checked["good"].any()

    particles, _ = localized(1000.0)
    # emitters like the calibration particles: χ² beyond the per-spot limit is rare
    assert np.mean(particles["consistency_chi2"] <= CHI2_LIMIT) >= 0.95
    with warnings.catch_warnings():
        warnings.simplefilter("error", UserWarning)
        check_calibration_fits(particles, rho_w)


def test_auto_shapes_on_the_pi_over_4_microscope(sim):
    from latentz.calibration.workflow import calibrate_traces

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
