"""calibrate / calibrate_traces / Calibration.apply: validation, culling reasons, range limits,
intensity normalisation, and the batch evaluation the widefield stage uses."""

import numpy as np
import pandas as pd
import pytest
from calib_synthetic import make_traces

from latentz.calibration.traces import traces_table
from latentz.calibration.workflow import calibrate, calibrate_traces
from latentz.camera import Camera

CAM = Camera(offset=0.0, gain=1.0, readnoise=0.0, pixel_size_nm=100.0)


@pytest.fixture(scope="module")
def calibrated():
    # 60 particles on a 500 px field; one of them is never in focus within ±3 µm
    z_f = np.random.default_rng(20).uniform(-150, 150, 60)
    z_f[5] = 3600.0
    traces, truth = make_traces(60, z_f=z_f, seed=20)
    return calibrate_traces(traces, camera=CAM, shape="rho_A", field_model="nearest"), traces, truth


def test_never_in_focus_is_culled_with_its_reason(calibrated):
    cal, _, _ = calibrated
    table = cal.particles
    assert table.loc[5, "culled"]
    assert "never_in_focus" in table.loc[5, "cull_reason"]
    assert not table.drop(index=5)["culled"].any()
    for column in (
        "x",
        "y",
        "z_f",
        "z_f_nm",
        "sigma_z_rho",
        "sigma_z_rho_w",
        "sigma_z_rho_A",
        "z_min_nm",
        "z_max_nm",
        "culled",
        "reason",
        "z_coef",
        "dx_coef",
        "dy_coef",
    ):
        assert column in table


def _independent_emitters(
    cal, n: int, *, seed: int, z_readout: str = "shape", **kwargs
) -> tuple[pd.DataFrame, np.ndarray]:
    """``n`` emitters at random places (not calibration particles), each in focus at piezo 0,
    through ±2 µm; their fitted spots localized by ``cal`` (with ``z_readout``), and their true
    z on the calibration's tilt-corrected axis (the piezo minus the plane at them)."""
    positions = np.random.default_rng(seed).uniform(0, 500, (n, 2))
    test, _ = make_traces(n, z_nm=np.arange(-2000.0, 2000.1, 100.0), z_f=np.zeros(n),
                          positions=positions, seed=seed, **kwargs)  # fmt: skip
    out = cal.apply(traces_table(test), z_readout=z_readout)
    true = np.repeat(positions * 100, test.z_nm.size, axis=0)  # nm, in focus at the piezo's 0
    out = out.assign(true_x_nm=true[:, 0], true_y_nm=true[:, 1])
    return out, np.tile(test.z_nm, n) - cal.plane(out["x"] * 100, out["y"] * 100)


def _normalised_rms(out: pd.DataFrame, z_true: np.ndarray) -> tuple[float, float]:
    """RMS of the z errors over their reported 1σ, and 3 of its standard errors: the errors
    are ruled by the nearest particles' own focus offsets, so they are as many independent
    values as the particles used (counted by their share of the spots)."""
    keep = out["in_range"].to_numpy()
    err = out["z_nm"].to_numpy()[keep] - z_true[keep]
    counts = np.bincount(out["cal_particle"].to_numpy()[keep])
    independent = counts.sum() ** 2 / np.sum(counts**2)
    return np.sqrt(np.mean((err / out["z_err_nm"].to_numpy()[keep]) ** 2)), 3 / np.sqrt(
        2 * independent
    )


@pytest.mark.parametrize("z_readout", ["shape", "joint"])
def test_independent_emitters_localize_with_nearest_models(z_readout):
    """Each particle focuses ±150 nm off its neighbours (white noise), so an emitter elsewhere
    errs by its nearest particle's offset, which the reported z error must hold, from the one
    shape value or from the joint readout."""
    traces, _ = make_traces(200, seed=30)
    cal = calibrate_traces(traces, camera=CAM, shape="rho_A", field_model="nearest")
    out, z_true = _independent_emitters(cal, 200, seed=31, z_readout=z_readout)
    assert out["in_range"].mean() > 0.5
    ratio, tol = _normalised_rms(out, z_true)
    assert ratio == pytest.approx(1.0, abs=tol)
    keep = out["in_range"]
    assert np.isfinite(out.loc[keep, ["x_nm", "y_nm", "x_err_nm", "y_err_nm"]]).all().all()


@pytest.mark.parametrize("z_readout", ["shape", "joint"])
def test_places_without_errors_are_the_places_with_them(calibrated, z_readout):
    """``errors=False`` leaves the error columns out and nothing else: independent emitters'
    places, in range or not (every fifth spot 3x wider than any calibrated image, one a failed
    fit), bit for bit those of the full ``apply``."""
    cal = calibrated[0]
    positions = np.random.default_rng(32).uniform(0, 500, (40, 2))
    test, _ = make_traces(40, z_nm=np.arange(-2000.0, 2000.1, 100.0), z_f=np.zeros(40),
                          positions=positions, seed=32)  # fmt: skip
    spots = traces_table(test)
    spots.loc[::5, ["wx", "wy"]] *= 3.0
    spots.loc[1, ["x", "y"]] = np.nan
    places = cal.apply(spots, z_readout=z_readout, errors=False)
    full = cal.apply(spots, z_readout=z_readout)
    new = ["x_nm", "y_nm", "z_nm", "in_range", "cal_particle"]
    assert list(places.columns) == [*spots.columns, *(c for c in new if c not in spots)]
    assert not places.loc[1, "in_range"] and 0.5 < places["in_range"].mean() < 0.9
    pd.testing.assert_frame_equal(places, full[places.columns], check_exact=True)
    with pytest.raises(ValueError, match="error_parts=True needs the errors"):
        cal.apply(spots, errors=False, error_parts=True)


def test_out_of_range_is_never_extrapolated(calibrated):
    cal, traces, _ = calibrated
    spots = traces_table(traces.subset([0]))
    spots["rho"] = 0.99  # with a faint image: beyond any calibrated ρ_A
    spots["amplitude"] *= 1e-3
    out = cal.apply(spots)
    assert not out["in_range"].any()
    assert out[["z_nm", "x_nm", "y_nm", "z_err_nm"]].isna().all().all()
    spots.loc[0, ["x", "y"]] = np.nan  # a failed fit
    assert not cal.apply(spots)["in_range"].any()


def test_track_normalisation_makes_rho_a_intensity_independent(calibrated):
    cal, _, truth = calibrated
    test, _ = make_traces(60, z_f=truth["z_f"], seed=20, noise_seed=22)
    spots = traces_table(test.subset([10]))
    spots["amplitude"] *= 2.0  # an emitter twice as bright as the calibration particle
    by_calibration = cal.apply(spots)
    by_track = cal.apply(spots, amplitude_reference="particle")
    z_true = np.asarray(test.z_nm) - cal.plane(*(cal.positions[10] * 100))
    near = np.abs(z_true) < 1500
    rms_track = np.sqrt(np.nanmean((by_track["z_nm"] - z_true)[near] ** 2))
    rms_cal = np.sqrt(np.nanmean((by_calibration["z_nm"] - z_true)[near] ** 2))
    assert rms_track < 3 * cal.particles["sigma_z"].iloc[10]
    assert rms_cal > 5 * rms_track


def test_batch_evaluation_over_particles(calibrated):
    cal, _, _ = calibrated
    z = cal.local_z(0.0)
    assert z.shape == (60,)
    assert np.isnan(cal.local_z(50.0)).all()
    dx, dy = cal.local_delta(np.zeros(60))
    # Δ(z_f) = 0 by definition (eqs. 2–3)
    dx_f, dy_f = cal.local_delta(cal.local.z_f)
    np.testing.assert_allclose(dx_f[cal.local.in_focus], 0.0, atol=1e-9)
    np.testing.assert_allclose(dy_f[cal.local.in_focus], 0.0, atol=1e-9)
    assert dx.shape == dy.shape == (60,)


def test_local_models_are_never_extrapolated_beyond_the_imaged_z_span(calibrated):
    from latentz.calibration.widefield import WidefieldModel

    cal, traces, _ = calibrated
    lo, hi = cal.z_span_nm.T
    # the tilt-corrected span is the piezo range shifted by the plane under each particle
    shift = cal.plane(*(cal.positions * 100).T)
    np.testing.assert_allclose(lo, traces.z_nm[0] - shift)
    np.testing.assert_allclose(hi, traces.z_nm[-1] - shift)
    for z, finite in ((hi + 100.0, False), (lo - 100.0, False), ((lo + hi) / 2, True)):
        dx, dy = cal.local_delta(z)
        assert np.isfinite(dx).tolist() == [finite] * 60
        assert np.isfinite(dy).tolist() == [finite] * 60
    # the widefield tables take a particle's values only inside its span, however far the z
    # grid reaches for the others (a 16th-order polynomial beyond its data is meaningless)
    model = WidefieldModel.from_calibration(cal, kind="nearest", field_shape=(520, 520))
    kept = cal.kept
    inside = (model.z_grid_nm >= lo[kept, None]) & (model.z_grid_nm <= hi[kept, None])
    assert (model.dx.valid == inside).all() and (model.dy.valid == inside).all()
    z_lo, z_hi = cal.z_span_nm[kept].T
    with np.errstate(invalid="ignore"):
        z_ok = (model.axial.values >= z_lo[:, None]) & (model.axial.values <= z_hi[:, None])
    assert (z_ok == model.axial.valid).all()


@pytest.mark.parametrize("field_model", ["nearest", "curves"])
def test_models_are_never_used_across_a_gap_of_failed_fits(field_model):
    """Eight particles whose fits failed on the planes from -950 to -750 nm: their local
    models stop at the gap, and no spot is corrected by a Δx' extrapolated across it (an
    order-16 polynomial there errs by pixels). Emitters 3 px from each of them, in focus at 0,
    through ±2 µm: every spot in range is put at its emitter's place (px · 100 nm) within
    30 nm (measured: 2 nm median, 26 nm at most; one Δx' extrapolated across the gap errs by
    166 nm)."""
    traces, _ = make_traces(40, seed=5)
    z = traces.z_nm
    gapped = np.arange(8)
    for name in ("x", "y", "wx", "wy", "rho", "amplitude"):
        traces.data[name][np.ix_(gapped, (z > -1000.0) & (z < -700.0))] = np.nan
    cal = calibrate_traces(traces, camera=CAM, shape="rho", field_model=field_model)
    shift = cal.plane(*(cal.positions[gapped] * 100).T)
    assert np.all(cal.z_span_nm[gapped, 0] >= -750.0 - shift - 1e-6)
    place = cal.positions[gapped] + [3.0, 0.0]
    test, _ = make_traces(gapped.size, z_nm=np.arange(-2000.0, 2000.1, 50.0),
                          z_f=np.zeros(gapped.size), positions=place, seed=7)  # fmt: skip
    out = cal.apply(traces_table(test))
    keep = out["in_range"].to_numpy()
    assert keep.mean() > 0.5
    true_x = np.repeat(place[:, 0], test.z_nm.size) * 100.0
    assert np.max(np.abs(out["x_nm"].to_numpy() - true_x)[keep]) < 30.0


def test_fits_failing_only_beyond_the_models_run_do_not_cull_a_particle():
    """Spots that outgrow the ROI fail to fit far from focus: here every plane beyond ±2 µm
    (a third of the ±3 µm stack) failed. The models use only the run about focus, so the
    particles are kept (before, every one was culled as ``fit_failed`` and calibrate raised)
    and independent emitters within ±1 µm are localized from them."""
    traces, _ = make_traces(40, seed=5)
    far = np.abs(traces.z_nm) > 2000.0
    for name in ("x", "y", "wx", "wy", "rho", "amplitude"):
        traces.data[name][:, far] = np.nan
    traces.data["converged"][:, far] = False
    cal = calibrate_traces(traces, camera=CAM, shape="rho", field_model="nearest")
    assert not cal.particles["cull_reason"].str.contains("fit_failed").any()
    assert cal.kept.size >= 38
    place = np.random.default_rng(8).uniform(0, 500, (20, 2))
    test, _ = make_traces(20, z_nm=np.arange(-1000.0, 1000.1, 50.0), z_f=np.zeros(20),
                          positions=place, seed=9)  # fmt: skip
    out = cal.apply(traces_table(test))
    assert out["in_range"].mean() >= 0.99


@pytest.mark.parametrize("cap_px", [None, 3.0])
def test_spots_far_beyond_the_monotonic_range_are_not_in_range(cap_px):
    """ρ is monotonic within about ±1.3 µm of focus here and returns towards 0 beyond, so a
    spot 2.5-3 µm from focus has the ρ of one inside the range. Its widths and ρ together match
    its particle's curves beyond the range. ``cap_px``: no fitted width above 3 px, in the
    particles' traces as in the spots, as a small ROI cuts defocused spots off, so that the
    widths alone no longer grow. Emitters at their own places through ±3 µm (truth: the piezo z
    less the plane): at most 5 % of those beyond 2.5 µm may be claimed in range (measured: 0 %
    and 0 %; with the shape value and widths alone 19 % and 100 %), and none within 1 µm of
    focus may be lost."""
    traces, _ = make_traces(40, seed=5)
    place = np.random.default_rng(8).uniform(0, 500, (30, 2))
    test, _ = make_traces(30, z_nm=np.arange(-3000.0, 3000.1, 50.0), z_f=np.zeros(30),
                          positions=place, seed=9)  # fmt: skip
    if cap_px is not None:
        for table in (traces, test):
            for name in ("wx", "wy"):
                table.data[name] = np.minimum(table.data[name], cap_px)
    cal = calibrate_traces(traces, camera=CAM, shape="rho", field_model="nearest")
    out = cal.apply(traces_table(test))
    z_true = np.tile(test.z_nm, 30) - cal.plane(out["x"] * 100, out["y"] * 100)
    keep = out["in_range"].to_numpy()
    assert keep[np.abs(z_true) > 2500].mean() <= 0.05
    assert keep[np.abs(z_true) < 1000].mean() >= 0.99


def test_the_shape_grid_spans_what_enough_particles_cover(calibrated):
    from latentz.calibration.widefield import WidefieldModel

    cal, _, _ = calibrated
    domain = cal.local.shapes[cal.shape].inverse.domain[cal.kept]
    model = WidefieldModel.from_calibration(
        cal, kind="nearest", field_shape=(520, 520), min_particles=10
    )
    count = np.sum((domain[:, :1] <= model.s_grid) & (model.s_grid <= domain[:, 1:]), axis=0)
    assert count[0] >= 10 and count[-1] >= 10
    # just beyond either end, fewer than 10 particles cover
    step = np.diff(model.s_grid[:2])[0] * 1e-3
    for s in (model.s_grid[0] - step, model.s_grid[-1] + step):
        assert np.sum((domain[:, 0] <= s) & (s <= domain[:, 1])) < 10
    # asking for more particles than were kept asks for all of them
    model = WidefieldModel.from_calibration(
        cal, kind="nearest", field_shape=(520, 520), min_particles=100
    )
    count = np.sum((domain[:, :1] <= model.s_grid) & (model.s_grid <= domain[:, 1:]), axis=0)
    assert (count == len(cal.kept)).all()


def test_bad_input(calibrated):
    cal, traces, _ = calibrated
    z = np.arange(30.0) * 100
    with pytest.raises(ValueError, match="at least 18 planes"):
        calibrate(np.zeros((10, 32, 32)), np.arange(10.0))
    with pytest.raises(ValueError, match="strictly monotonic"):
        calibrate(np.zeros((30, 32, 32)), np.r_[z[:10], z[11], z[10], z[12:]])
    flat = np.random.default_rng(1).poisson(100.0, (30, 40, 40)).astype(np.uint16)
    with pytest.raises(ValueError, match="No particles found"):
        calibrate(flat, z, camera=Camera(offset=0.0), field_model="nearest")
    with pytest.raises(ValueError, match="field_model"):
        calibrate_traces(traces, field_model="spline")
    with pytest.raises(TypeError, match="Unknown calibration option"):
        calibrate_traces(traces, field_model="nearest", colour="red")
    with pytest.raises(ValueError, match="shape"):
        calibrate_traces(traces, field_model="nearest", shape="sigma")
    with pytest.raises(ValueError, match="missing column"):
        cal.apply(pd.DataFrame({"x": [1.0], "y": [1.0]}))
    with pytest.raises(ValueError, match="particle"):
        cal.apply(
            traces_table(traces.subset([0])).drop(columns="particle"),
            amplitude_reference="particle",
        )
    with pytest.raises(ValueError, match="planes"):
        calibrate(np.zeros((30, 32, 32)), np.arange(31.0))


def test_a_calibration_that_keeps_no_particle_is_one_clear_error(calibrated):
    _, traces, _ = calibrated
    with pytest.raises(ValueError, match=r"Every one of the 1 calibration particles failed \("):
        calibrate_traces(traces.subset([5]), camera=CAM, field_model="nearest")


@pytest.mark.parametrize("shape", ["auto", "auto_A"])
def test_auto_shapes_work_with_a_cylindrical_lens(shape):
    # astigmatism along the camera axes: ρ ≡ 0 carries nothing, e_θ does
    traces, _ = make_traces(200, theta=0.0, seed=40)
    cal = calibrate_traces(traces, camera=CAM, shape=shape, field_model="nearest")
    assert abs(cal.local.theta) < 0.01
    out, z_true = _independent_emitters(cal, 200, seed=41, theta=0.0)
    assert out["in_range"].mean() > 0.4
    # errors consistent with the reported 1σ uncertainties
    ratio, tol = _normalised_rms(out, z_true)
    assert ratio == pytest.approx(1.0, abs=tol)


def test_errors_cover_with_weak_astigmatism():
    """Foci 100 nm apart (widths within 1 % of each other over ±400 nm): z is read through an
    inverse z(s) whose slope, an order-16 polynomial's, swings with noise and turns at the range
    ends, and a σ_z of hundreds of nm spans the bends of Δx'(z), Δy'(z) beyond the range. The
    particles all focus at 0 and sit on the field's one curve, so every error is the spots' and
    the local models' noise: 1σ covers 60-76 % of the errors (pooled over 2,000- and
    10,000-photon emitters) on each axis, against geometry (lateral: one offset removed)."""
    traces, _ = make_traces(20, z_nm=np.arange(-1500.0, 1500.1, 50.0), z_f=np.zeros(20), seed=3,
                            c_nm=np.full(20, 50.0))  # fmt: skip
    cal = calibrate_traces(traces, camera=CAM, shape="rho", field_model="nearest")
    errors, sigmas = {a: [] for a in "xyz"}, {a: [] for a in "xyz"}
    for photons, seed in ((2000.0, 4), (10000.0, 5)):
        out, z_true = _independent_emitters(cal, 100, seed=seed, photons=photons,
                                            c_nm=np.full(100, 50.0))  # fmt: skip
        keep = out["in_range"].to_numpy()
        assert keep.mean() > 0.2  # of spots through ±2 µm
        for a, true in (("x", out["true_x_nm"]), ("y", out["true_y_nm"]), ("z", z_true)):
            err = out[f"{a}_nm"].to_numpy()[keep] - np.asarray(true)[keep]
            errors[a].append(err - (np.mean(err) if a != "z" else 0.0))
            sigmas[a].append(out[f"{a}_err_nm"].to_numpy()[keep])
    for a in "xyz":
        cover = np.mean(np.abs(np.concatenate(errors[a])) <= np.concatenate(sigmas[a]))
        assert 0.60 <= cover <= 0.76, (a, cover)


def test_auto_reproduces_rho_w_and_rho_a_at_pi_over_4(calibrated):
    cal, traces, _ = calibrated
    auto = calibrate_traces(traces, camera=CAM, shape="auto", field_model="nearest")
    auto_a = calibrate_traces(traces, camera=CAM, shape="auto_A", field_model="nearest")
    # θ from the data is π/4 within its noise, so e_θ ≈ e2 = ρ (wx = wy on this microscope)
    assert auto.local.theta == pytest.approx(np.pi / 4, abs=0.01)
    for mine, paper in ((auto, "rho_w"), (auto_a, "rho_A")):
        ratio = mine.particles["sigma_z"] / cal.particles[f"sigma_z_{paper}"]
        assert np.nanmedian(ratio) == pytest.approx(1.0, abs=0.05)
        np.testing.assert_allclose(
            mine.particles["z_max_nm"], cal.particles[f"z_max_{paper}"], atol=100.0
        )


def test_images_with_decreasing_z_give_the_same_calibration():
    from latentz.fit import render_rois

    rng = np.random.default_rng(50)
    z = np.linspace(-2000.0, 2000.0, 41)
    traces, _ = make_traces(
        4, z_nm=z, noise=0.0, positions=[[20, 20], [60, 20], [20, 60], [60, 60]]
    )
    stack = np.full((z.size, 80, 80), 20.0)
    for p in range(4):
        params = np.stack(
            [
                traces["x"][p] - traces["x"][p].round() + 7,
                traces["y"][p] - traces["y"][p].round() + 7,
                traces["amplitude"][p] * 5,
                np.zeros(z.size),
                traces["wx"][p],
                traces["wy"][p],
                traces["rho"][p],
            ],
            axis=1,
        )
        r, c = int(traces["y"][p, 0].round()) - 7, int(traces["x"][p, 0].round()) - 7
        stack[:, r : r + 15, c : c + 15] += render_rois(params, shape=15)
    stack = rng.poisson(stack).astype(np.uint16)
    camera = Camera(offset=0.0, gain=1.0, readnoise=0.0, pixel_size_nm=100.0)
    up = calibrate(stack, z, camera=camera, field_model="nearest", roi_size=15)
    down = calibrate(stack[::-1], z[::-1], camera=camera, field_model="nearest", roi_size=15)
    assert len(up.particles) == 4
    np.testing.assert_allclose(up.particles["z_f"], down.particles["z_f"])


def test_hdf5_round_trip_is_exact(calibrated, tmp_path):
    from latentz.calibration.result import Calibration

    cal, traces, _ = calibrated
    path = tmp_path / "cal.h5"
    cal.save(path, provenance={"inputs": ["synthetic"]})
    back = Calibration.load(path)
    arrays, attrs = cal.as_arrays()
    arrays2, attrs2 = back.as_arrays()
    record = attrs2.pop("provenance")
    assert record["inputs"] == ["synthetic"] and record["latentz_version"] and record["created"]
    attrs.pop("provenance")
    assert attrs == attrs2
    assert arrays.keys() == arrays2.keys()
    for key, value in arrays.items():
        np.testing.assert_array_equal(value, arrays2[key], err_msg=key)
    spots = traces_table(traces.subset([1, 2]))
    pd.testing.assert_frame_equal(cal.apply(spots), back.apply(spots))
    with pytest.raises(ValueError, match="format"):
        from latentz.calibration.storage import from_arrays

        from_arrays(arrays, {**attrs, "format": "other"}, factory=type(cal))


@pytest.fixture(scope="module")
def zernike_file(calibrated, tmp_path_factory):
    cal, traces, _ = calibrated
    wide = calibrate_traces(traces, camera=CAM, field_model="zernike", n_terms=28)
    path = tmp_path_factory.mktemp("zernike") / "cal.h5"
    wide.save(path)
    return wide, traces, path


def test_widefield_models_are_stored_and_apply_bit_identically(zernike_file):
    import h5py

    from latentz.calibration.result import Calibration

    wide, traces, path = zernike_file
    with h5py.File(path, "r") as handle:
        for name in ("s_grid", "z_grid_nm", "axial/coefficients", "dx/values", "dy/valid"):
            assert f"widefield/{name}" in handle, name
    back = Calibration.load(path)
    assert "widefield" in back._cache  # read from the file, not re-tabulated
    arrays, options = wide.widefield.as_arrays()
    arrays2, options2 = back.widefield.as_arrays()
    assert options == options2 and arrays.keys() == arrays2.keys()
    for key, value in arrays.items():
        np.testing.assert_array_equal(value, arrays2[key], err_msg=key)
    spots = traces_table(traces.subset([3, 4, 5]))
    located = wide.apply(spots)
    assert located["in_range"].sum() > 30
    pd.testing.assert_frame_equal(located, back.apply(spots))


def test_a_format_1_file_rebuilds_its_widefield_models(zernike_file, tmp_path):
    import json
    import shutil

    import h5py

    from latentz.calibration.result import Calibration

    wide, traces, path = zernike_file
    old = tmp_path / "old.h5"
    shutil.copy(path, old)
    with h5py.File(old, "a") as handle:  # what latentz wrote before the widefield group
        del handle["widefield"]
        del handle.attrs["widefield"]
        handle.attrs["format"] = json.dumps("latentz-calibration/1")
    back = Calibration.load(old)
    assert "widefield" not in back._cache
    spots = traces_table(traces.subset([3, 4, 5]))
    pd.testing.assert_frame_equal(wide.apply(spots), back.apply(spots))


@pytest.mark.parametrize("damage", ["group", "part"])
def test_a_missing_widefield_dataset_is_a_damaged_file(zernike_file, tmp_path, damage):
    import shutil

    import h5py

    from latentz.calibration.result import Calibration

    _, _, path = zernike_file
    bad = tmp_path / "bad.h5"
    shutil.copy(path, bad)
    with h5py.File(bad, "a") as handle:
        del handle["widefield" if damage == "group" else "widefield/dx/coefficients"]
    with pytest.raises(ValueError, match="bad.h5 is a damaged latentz calibration"):
        Calibration.load(bad)


def test_a_tiff_path_with_a_single_bead_and_explicit_position(tmp_path):
    tifffile = pytest.importorskip("tifffile")
    from latentz.fit import render_rois

    z = np.linspace(-1500.0, 1500.0, 31)
    traces, _ = make_traces(1, z_nm=z, noise=0.0, positions=[[10.3, 9.8]])
    params = np.stack(
        [
            traces["x"][0],
            traces["y"][0],
            traces["amplitude"][0] * 5,
            np.full(z.size, 20.0),
            traces["wx"][0],
            traces["wy"][0],
            traces["rho"][0],
        ],
        axis=1,
    )
    stack = np.random.default_rng(60).poisson(render_rois(params, shape=21)).astype(np.uint16)
    path = tmp_path / "bead.tif"
    tifffile.imwrite(path, stack)
    camera = Camera(offset=0.0, gain=1.0, readnoise=0.0, pixel_size_nm=100.0)
    cal = calibrate(
        path,
        z,
        camera=camera,
        field_model="nearest",
        roi_size=17,
        positions=[(10, 10)],
        progress=True,
    )
    assert len(cal.particles) == 1 and not cal.culled[0]
    # one particle: no population to cull against, and a flat "tilt" plane at its focus
    assert cal.tilt_mrad == 0.0 and cal.particles["z_f_nm"].iloc[0] == 0.0


def test_row_interpolation_matches_numpy_on_each_particles_shifted_grid():
    from latentz.calibration.rows import interp_rows

    rng = np.random.default_rng(5)
    planes = np.linspace(-3000.0, 3000.0, 61)
    grid = planes - rng.uniform(-400, 400, 30)[:, None]  # each particle's tilt-corrected planes
    values = rng.uniform(1, 50, grid.shape)
    rows = rng.integers(0, 30, 500)
    z = rng.uniform(-3600, 3600, 500)  # some beyond a row's grid: the end value is held
    z[:5] = np.nan
    expected = np.array([np.interp(zk, grid[r], values[r]) for r, zk in zip(rows, z, strict=True)])
    np.testing.assert_allclose(interp_rows(grid, values, rows, z), expected, rtol=1e-12)


def test_a_one_particle_rho_a_calibration_is_its_own_reference():
    """With a lone particle, its own A at ρ0 normalises every spot: its own images give back
    its own z axis, with finite errors."""
    traces, _ = make_traces(1, seed=40)
    cal = calibrate_traces(traces, camera=CAM, shape="rho_A", field_model="nearest")
    out = cal.apply(traces_table(traces))
    inside = out["in_range"].to_numpy()
    assert inside.mean() > 0.5
    error = out["z_nm"].to_numpy()[inside] - cal.local.z_nm[0][inside]
    assert np.sqrt(np.mean(error**2)) < 3 * np.median(out["z_err_nm"].to_numpy()[inside])
    assert np.isfinite(out.loc[inside, "z_err_nm"]).all()
