"""The random family of validation microscopes: what is drawn, the truth, and defaults on it.

The family's optics are tested in test_microscope.py; here the draws' spread, the pupil
quadrature of the hardest draws, the geometric scoring, and (slow, about a minute) a small
family of four draws calibrated with defaults only, held to the family's criteria per draw.
"""

import warnings
from dataclasses import replace

import numpy as np
import pandas as pd
import pytest

from latentz.validation import FAMILY_SIZES, FORMS, draw_microscope, family_data
from latentz.validation.family import MEDIA
from latentz.validation.truth import coverage_interval, remove_planes, summary

DRAWS = [draw_microscope(seed) for seed in range(300)]


def test_draws_span_the_family():
    na = np.array([d.na for d in DRAWS])
    assert na.min() < 0.45 and na.max() > 1.45  # NA 0.4-1.49
    for medium, (n, lo, hi) in MEDIA.items():
        own = [d.na for d in DRAWS if d.medium == medium]
        assert len(own) > 50 and lo <= min(own) and max(own) <= min(hi, n)
    pixel = np.array([d.pixel_size_nm for d in DRAWS])
    assert 65 <= pixel.min() < 70 and 155 < pixel.max() <= 160
    assert {d.form for d in DRAWS} == set(FORMS)
    # astigmatism from none to cylindrical-lens strength (focal lines ~1 µm apart)
    separation = np.array([4 * np.sqrt(6) * d.n_medium * d.astigmatism_nm / d.na**2
                           for d in DRAWS])  # fmt: skip
    assert separation.min() < 20 and separation.max() > 950
    beads = np.array([d.bead_nm for d in DRAWS])
    assert np.mean(beads == 0) > 0.3 and beads.max() > 190
    assert len({d.z_step_nm for d in DRAWS}) > 5 and len({round(d.z_half_nm) for d in DRAWS}) > 50
    assert all(d.test_photons[1] == pytest.approx(10 * d.test_photons[0]) for d in DRAWS)


@pytest.mark.parametrize("key", ["na", "pixel_size_nm"])
def test_pupil_quadrature_has_converged_on_the_hardest_draws(key):
    # the draw of highest NA or coarsest pixel (largest lateral and axial phase ramps), a defocused
    # aberrated image at the patch's size: doubling the nodes moves no pixel by 1e-3 of the peak
    draw = max(DRAWS[:60], key=lambda d: getattr(d, key))
    patch = FAMILY_SIZES["full"]["patch_px"]
    scope = draw.microscope(patch)
    fine = replace(scope, radial_nodes=2 * scope.radial_nodes,
                   azimuth_nodes=2 * scope.azimuth_nodes)  # fmt: skip
    wave = {mode: c for mode, c in draw.mean_nm.items()}
    z = [-draw.z_half_nm, 0.0, draw.z_half_nm]
    a = scope.pixel_image(0.3, -0.2, scope.wavefront_nm(wave), z, patch)
    b = fine.pixel_image(0.3, -0.2, fine.wavefront_nm(wave), z, patch)
    assert np.abs(a - b).max() < 1e-3 * b.max()


def test_a_few_gross_errors_do_not_set_the_plane():
    """2 % of spots read 2 µm off (on the wrong side of a shape's turn) keep their errors, and
    the others are scored against the true plane, not one pulled 40 nm towards them."""
    rng = np.random.default_rng(1)
    n = 600
    x, y = rng.uniform(0, 256, n), rng.uniform(0, 256, n)
    sigma = rng.uniform(20.0, 80.0, n)
    gross = np.arange(n) < 12
    err = rng.normal(size=n) * sigma + 30.0 - 0.2 * x + np.where(gross, 2000.0, 0.0)
    errors = pd.DataFrame({"x": x, "y": y, "in_range": True, "err_x_nm": 0.0, "err_y_nm": 0.0,
                           "err_z_nm": err, "x_err_nm": 1.0, "y_err_nm": 1.0,
                           "z_err_nm": sigma})  # fmt: skip
    got = remove_planes(errors)["err_z_nm"].to_numpy()
    assert np.all(got[gross] > 1900.0)
    assert abs(np.mean(got[~gross])) < 3 * np.sqrt(np.mean(sigma**2) / n)  # 7 nm; 40 by LS
    cover = np.mean(np.abs(got[~gross]) <= sigma[~gross])
    assert cover == pytest.approx(0.683, abs=3 * np.sqrt(0.683 * 0.317 / n))


def test_scoring_removes_one_plane_per_axis_and_nothing_else():
    rng = np.random.default_rng(0)
    n = 4000
    x, y = rng.uniform(0, 256, n), rng.uniform(0, 256, n)
    sigma = rng.uniform(2.0, 30.0, (n, 3))
    noise = rng.normal(size=(n, 3)) * sigma
    plane = 40.0 + 0.3 * x - 0.2 * y
    bump = 25.0 * np.exp(-((x - 128) ** 2 + (y - 128) ** 2) / (2 * 20.0**2))  # not a plane
    columns = {f"err_{a}_nm": noise[:, i] + plane for i, a in enumerate("xyz")}
    columns |= {f"{a}_err_nm": sigma[:, i] for i, a in enumerate("xyz")}
    errors = pd.DataFrame({"x": x, "y": y, "in_range": True, **columns})
    errors["err_z_nm"] += bump
    got = summary(remove_planes(errors))
    # the plane goes; the noise stays: 1σ covers 68.3 % within 3 binomial SE (0.7 % at n=4000)
    for axis in "xy":
        assert got[f"cover_{axis}"] == pytest.approx(0.683, abs=3 * np.sqrt(0.683 * 0.317 / n))
        rms = np.sqrt(np.mean(noise[:, "xyz".index(axis)] ** 2))
        assert got[f"rmse_{axis}"] == pytest.approx(rms, rel=0.01)
    # the bump is not removed: z's RMS holds the bump's RMS (about its own mean) beside the noise
    rest = bump - bump.mean()
    expected = np.sqrt(np.mean(noise[:, 2] ** 2) + np.mean(rest**2))
    assert got["rmse_z"] == pytest.approx(expected, rel=0.05)


def test_family_data_refuses_an_unknown_size_before_work():
    with pytest.raises(ValueError, match="size"):
        family_data(DRAWS[0], "huge")
    with pytest.raises(ValueError, match="size"):
        draw_microscope(0, "huge")


def test_a_size_holds_the_drawn_stack_to_its_bounds():
    for seed in range(40):
        draw = draw_microscope(seed, "ci")
        (lo, hi), (step_lo, step_hi) = (FAMILY_SIZES["ci"][k] for k in ("z_half_nm", "z_step_nm"))
        assert lo <= draw.z_half_nm <= hi and step_lo <= draw.z_step_nm <= step_hi
        full = DRAWS[seed]
        assert (draw.na, draw.form, draw.bead_nm) == (full.na, full.form, full.bead_nm)


def test_the_coverage_interval_holds_right_errors_shared_by_each_emitters_spots():
    # 24 spots of 6 emitters, 9.5 nm of each spot's 10 nm σ shared by its emitter's spots: right
    # errors scored as the family scores them (one plane removed) fall inside the 99 % interval
    # in about 99 % of tables; the interval of independent spots (no shared part) holds 76 % of
    # them and the binomial band 64 %
    rng = np.random.default_rng(7)
    emitter = np.repeat(np.arange(6), 4)
    place = rng.uniform(0, 72, (6, 2))[emitter]
    sigma, shared = np.full(24, 10.0), 9.5
    table = pd.DataFrame({"emitter": emitter, "x": place[:, 0], "y": place[:, 1],
                          "in_range": True, "x_err_nm": sigma, "y_err_nm": 1.0, "z_err_nm": 1.0,
                          "err_x_nm": 0.0, "err_y_nm": 0.0, "err_z_nm": 0.0})  # fmt: skip
    low, high = coverage_interval(table, "x", shared)
    band = 2.576 * np.sqrt(0.683 * 0.317 / 24)
    inside = binomial = 0
    for _ in range(2000):
        errors = shared * rng.standard_normal(6)[emitter] + 3.12 * rng.standard_normal(24)
        cover = summary(remove_planes(table.assign(err_x_nm=errors)))["cover_x"]
        inside += low <= cover <= high
        binomial += abs(cover - 0.683) <= band
    assert inside / 2000 >= 0.98
    assert binomial / 2000 < 0.9


# A small family in CI: four draws at the "ci" size (72 x 72 px, 9 calibration particles in
# each of two stacks through at most +-1 um, 24 test spots of 6 emitters), calibrated with
# defaults only: every draw calibrates, and z RMSE <= 3x its oracle floor wherever the floor
# itself calibrates. At least 8 spots are scored: a 19 px ROI (draw 1's) flags the spots within
# 9.5 px of this small field's edge, two thirds of them, which the scoring leaves out. 1σ
# coverage of each axis lies in the 99 % interval of a right error model on the draw's own
# spots (truth.coverage_interval: the particles' own lateral reference is shared by an
# emitter's spots, and the scoring's plane is fitted to 6 emitters), not the family's
# 50-85 %, which ~20 spots cannot resolve. Measured figures: docs/validation-family.md.
FAMILY_SEEDS = (0, 1, 2, 3)


@pytest.fixture(scope="module")
def ci_family():
    from latentz.validation.study import run_defaults

    return {seed: run_defaults(seed, "ci") for seed in FAMILY_SEEDS}


@pytest.mark.slow
@pytest.mark.parametrize("seed", FAMILY_SEEDS)
def test_defaults_hold_on_a_small_random_family(seed, ci_family):
    row = ci_family[seed]
    print(row)
    assert not row.get("fails"), f"draw {seed} does not calibrate: {row.get('fails')}"
    assert row["spots"] >= 8
    if not row.get("floor fails"):
        assert row["ratio"] <= 3.0, f"z RMSE on the floor's spots is {row['ratio']:.2f}x the floor"
    for axis in "xyz":
        low, high = row[f"cov {axis} low"], row[f"cov {axis} high"]
        assert low <= row[f"cov {axis}"] <= high, f"{axis}: {row[f'cov {axis}']:.1%}"


@pytest.mark.slow
def test_the_oracle_floor_exists_on_most_of_the_small_family(ci_family):
    assert sum(not row.get("floor fails") for row in ci_family.values()) >= 3


@pytest.mark.slow
def test_auto_field_model_never_loses_to_nearest_on_a_smooth_random_field():
    """Draw 5 at the ci size is the first of the family's smooth random (non-polynomial) fields
    whose calibration keeps the 12 particles a field model needs. Against geometric truth, the
    model `auto` picks localizes the test spots no worse than `nearest` at the same ROI and
    shape, within twice the relative standard error of an RMSE from n spots (1/sqrt(2n), 14 %
    at 24), and it loses no held-out particle."""
    from latentz.calibration import calibrate
    from latentz.calibration.crossval import crossval_summary
    from latentz.validation.truth import localize_test, score

    draw = draw_microscope(5, "ci")
    assert draw.form == "smooth"
    data = family_data(draw)
    auto = calibrate(data.stacks, data.z_nm, camera=data.camera)
    assert auto.kept.size >= 12
    nearest = calibrate(data.stacks, data.z_nm, camera=data.camera, roi_size=auto.roi_size,
                        shape=auto.shape, field_model="nearest")  # fmt: skip
    got = {name: summary(score(data, cal.apply(localize_test(data, calibration=cal))))
           for name, cal in (("auto", auto), ("nearest", nearest))}  # fmt: skip
    n = got["nearest"]["spots"]
    assert got["auto"]["spots"] >= n
    assert got["auto"]["rmse_z"] <= got["nearest"]["rmse_z"] * (1 + 2 / np.sqrt(2 * n))
    assert crossval_summary(auto.crossval).loc[auto.field_model, "lost"] == 0


@pytest.fixture(scope="module")
def draw_17():
    """Draw 17 (oil NA 1.47, 57 nm astigmatism, a vectorial PSF) at the ci size, and its
    calibration at a 15 px ROI with the `nearest` field model (what defaults choose there)."""
    from latentz.calibration import calibrate

    draw = draw_microscope(17, "ci")
    assert draw.medium == "oil" and draw.na > 1.45
    data = family_data(draw)
    cal = calibrate(data.stacks, data.z_nm, camera=data.camera, roi_size=15, shape="auto",
                    field_model="nearest")  # fmt: skip
    return data, cal


@pytest.mark.slow
def test_a_high_na_spot_from_past_the_turn_of_its_shape_value_is_not_read_inside(draw_17):
    """Draw 17 (oil NA 1.47, 57 nm astigmatism) at the ci size: far from focus the fitted
    widths of its vectorial PSF stop growing in a 15 px ROI and the one shape value turns back,
    so a spot 600-900 nm from focus has the shape value of one 300-450 nm from it. Point
    emitters at six test places (never calibration particles), noise-free fits at 2·10⁴
    photons, z from geometry (defocus plus the focal surface there; one offset, from the spots
    within 300 nm of focus). Every spot within 300 nm is read in range, and every spot read in
    range lies within 100 nm of its place: near focus the nearest particle's models err by at
    most 57 nm here, and the far spots were read 100-680 nm off, in range."""
    from latentz.validation.floor import emitter_fits

    data, cal = draw_17
    defocus = np.array([-900, -800, -700, -600, -300, -150, 0, 150, 300, 600, 700, 800, 900.0])
    found, error = [], []
    for x, y in data.test_truth.drop_duplicates("emitter")[["x", "y"]].to_numpy():
        fits = emitter_fits(data, x, y, defocus, roi_size=15, photons=2e4)
        fits.attrs["roi_size"] = 15
        located = cal.apply(fits)
        true = defocus + data.fields.focal_surface_nm(np.full(defocus.size, x),
                                                      np.full(defocus.size, y))  # fmt: skip
        found.append(located["in_range"].to_numpy(bool))
        error.append(located["z_nm"].to_numpy() - true)
    found, error = np.concatenate(found), np.concatenate(error)
    near = np.abs(np.tile(defocus, len(found) // defocus.size)) <= 300
    assert found[near].all()
    error -= np.median(error[near])
    assert np.all(np.abs(error[found]) <= 100.0), np.round(error[found])


def _dim_spots(data, cal, microscope) -> pd.DataFrame:
    """Noise-free fits of point emitters of ``microscope`` at the draw's test places (never
    calibration particles), each 2,400 photons (the draw's dimmest) at 9 defocus within
    ±400 nm of its focal surface, each in a frame of its own, located by ``cal`` and assessed."""
    from latentz.localization.quality import assess
    from latentz.validation.floor import emitter_fits

    places = data.test_truth.drop_duplicates("emitter")[["x", "y"]].to_numpy()
    spots = replace(data, microscope=microscope)
    defocus = np.linspace(-400.0, 400.0, 9)
    fits = pd.concat([emitter_fits(spots, x, y, defocus, roi_size=15, photons=2.4e3)
                      for x, y in places], ignore_index=True)  # fmt: skip
    fits = fits.assign(frame=np.arange(len(fits)))
    fits.attrs["roi_size"] = 15
    return assess(cal.apply(fits), cal)


@pytest.mark.slow
@pytest.mark.parametrize("wavelength", [1.0, 1.2])
def test_dim_high_na_molecules_condemn_a_wrong_calibration_and_never_the_right_one(
    draw_17, wavelength
):
    """With the vectorial PSF of draw 17, dim point emitters fit wider than the calibration
    particles (points too here), not narrower: a fixed photon slope (dim spots narrower) read
    their log width ratio as +0.14 against the 0.02 limit and condemned the right calibration.
    Carried to the calibration's brightness by its own dimmed refits, they fit it (+0.01 ±
    0.01); emitters at 1.2x the calibration's wavelength (a calibration made at another
    wavelength) still condemn it (+0.075 ± 0.011)."""
    from latentz._shared.sanity import LatentzWarning
    from latentz.localization.mismatch import check_calibration_fits

    data, cal = draw_17
    microscope = replace(data.microscope, wavelength_nm=wavelength * data.microscope.wavelength_nm)
    spots = _dim_spots(data, cal, microscope)
    assert spots["in_range"].mean() >= 0.8
    if wavelength == 1.0:
        with warnings.catch_warnings():
            warnings.filterwarnings("error", message="The calibration does not fit")
            checked = check_calibration_fits(spots, cal)
        assert checked["good"].any()
    else:
        with pytest.warns(LatentzWarning, match="their widths are 1"):
            check_calibration_fits(spots, cal)


def test_kept_renders_are_reused_only_for_the_same_draw_size_and_code(tmp_path, monkeypatch):
    from latentz.validation import family

    made = []

    def render(draw, size):
        made.append((draw.seed, size))
        return {"seed": draw.seed, "size": size}

    monkeypatch.setattr(family, "_render", render)
    first = family_data(DRAWS[5], "ci", renders=tmp_path)
    again = family_data(DRAWS[5], "ci", renders=tmp_path)
    assert first == again == {"seed": 5, "size": "ci"} and made == [(5, "ci")]
    family_data(DRAWS[5], "tiny", renders=tmp_path)
    family_data(DRAWS[6], "ci", renders=tmp_path)
    family_data(replace(DRAWS[5], na=0.5), "ci", renders=tmp_path)
    assert made == [(5, "ci"), (5, "tiny"), (6, "ci"), (5, "ci")]
    # a change to the imaging code makes the kept render stale
    source = tmp_path / "src"
    source.mkdir()
    for name in family.RENDER_MODULES:
        (source / f"{name}.py").write_text(f"# {name}, edited\n")
    monkeypatch.setattr(family, "__file__", str(source / "family.py"))
    family_data(DRAWS[5], "ci", renders=tmp_path)
    assert made[-1] == (5, "ci") and len(made) == 5
