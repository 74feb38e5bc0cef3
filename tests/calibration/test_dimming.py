"""The brightness correction (:mod:`latentz.calibration.dimming`): refitting a bright image of a
non-Gaussian PSF over a raised background predicts the fit of the same PSF as a dim emitter, and
the shape shift it gives is the dim fit's shape value minus the bright one's.

Truth is the fit of the noise-free dim image itself (the validation microscope's pupil PSF, not
a Gaussian), with read noise, at a background chosen so that its ratio c = (b + readnoise²)/A
falls on one of the refit levels."""

import numpy as np
import pandas as pd
import pytest

from latentz.calibration.dimming import (
    EDGE_QUANTILE,
    background_ratio,
    dim_fits,
    dimmest,
    position_shift,
    shape_shift,
)
from latentz.calibration.shape import shape_value
from latentz.fit import PARAMS, fit_arrays

READNOISE = 1.5
LEVEL = 3  # 0.3 times the bright fit's amplitude added to its background


@pytest.fixture(scope="module")
def psf():
    from latentz.validation import AberrationFields, Microscope
    from latentz.validation.datasets import render_patches

    microscope = Microscope()
    fields = AberrationFields.random((64, 64), seed=3, pixel_size_nm=microscope.pixel_size_nm)
    return render_patches(microscope, fields, 32.3, 31.8, np.array([-400.0]), 15)[0]


def _dim_fit(psf: np.ndarray, photons: float, c: float) -> np.ndarray:
    """Fit of the noise-free image ``photons·psf + b``, b set so that the fit's own
    (background + readnoise²) / amplitude is c, as a spot's c is measured."""
    background = 10.0
    for _ in range(8):  # the fitted background moves with b one to one: a few rounds settle it
        fit = fit_arrays((photons * psf + background)[None], readnoise=READNOISE, device="cpu")
        amplitude, fitted = fit.params[0, 2], fit.params[0, 3]
        background += c * amplitude - (fitted + READNOISE**2)
    return fit_arrays((photons * psf + background)[None], readnoise=READNOISE,
                      device="cpu").params[0]  # fmt: skip


def _rho_w(amplitude, wx, wy, rho):
    return shape_value("rho_w", wx, wy, rho, amplitude)


def test_refit_over_a_raised_background_is_the_dim_emitters_fit(psf):
    bright = 2e5 * psf + 10.0
    fit = fit_arrays(bright[None], device="cpu")
    refit = dim_fits(bright[None], fit.params, method="mle", device="cpu")
    # the refit's own c, as a spot's: its fitted background over its amplitude
    c = refit[f"dim{LEVEL}_background"][0] / refit[f"dim{LEVEL}_amplitude"][0]
    dim = _dim_fit(psf, 1500.0, c)
    for name in ("wx", "wy", "rho"):
        got, want = refit[f"dim{LEVEL}_{name}"][0], dim[PARAMS.index(name)]
        # both fits stop within ~0.02 Cramér–Rao σ of their optimum (tol 1e-6 χ² per pixel),
        # ~1e-3 px for the dim one's widths: 3 of those
        assert got == pytest.approx(want, abs=3e-3), name
    # the bias is material: the widths move by far more than the tolerance
    assert abs(fit.params[0, 4] - dim[4]) > 0.03 and abs(fit.params[0, 5] - dim[5]) > 0.03


@pytest.fixture(scope="module")
def bright_traces(psf):
    """The bright image's fit and its refits, as one particle's traces at one plane."""
    bright = 2e5 * psf + 10.0
    fit = fit_arrays(bright[None], device="cpu")
    traces = {
        **dim_fits(bright[None], fit.params, method="mle", device="cpu"),
        **{k: fit.params[:, PARAMS.index(k)] for k in ("amplitude", "wx", "wy", "rho")},
    }
    return fit, traces


def test_shape_shift_is_the_dim_minus_the_bright_shape_value(psf, bright_traces):
    fit, traces = bright_traces
    own_c = (fit.params[0, 3]) / fit.params[0, 2]
    c = 0.5  # between two levels: interpolated in log c
    dim = _dim_fit(psf, 1500.0, c)
    shift = shape_shift(_rho_w, traces.__getitem__, np.array([c]), np.array([own_c]))
    want = _rho_w(*dim[[2, 4, 5, 6]]) - _rho_w(*fit.params[0, [2, 4, 5, 6]])
    assert shift[0] == pytest.approx(want, rel=0.05)
    assert abs(want) > 0.01  # against a range of rho_w of about ±0.5 over ±1 µm
    # as bright as the calibration, no shift
    same = shape_shift(_rho_w, traces.__getitem__, np.array([own_c]), np.array([own_c]))
    assert same[0] == 0.0


def test_the_shift_starts_where_asked(psf, bright_traces):
    fit, traces = bright_traces
    own_c = fit.params[0, 3] / fit.params[0, 2]
    start, c = 0.1, 0.5  # the correction starts at c = 0.1: what a spot dimmer than that gains
    two = {name: np.repeat(value, 2) for name, value in traces.items()}  # two spots
    shift = shape_shift(_rho_w, two.__getitem__, np.array([c, 0.05]), np.full(2, own_c),
                        c_from=np.full(2, start))  # fmt: skip
    want = _rho_w(*_dim_fit(psf, 1500.0, c)[[2, 4, 5, 6]]) - _rho_w(
        *_dim_fit(psf, 1500.0, start)[[2, 4, 5, 6]]
    )
    assert shift[0] == pytest.approx(want, rel=0.05)
    assert abs(want) > 0.01
    assert shift[1] == 0.0  # brighter than where it starts: no shift


@pytest.fixture(scope="module")
def comatic():
    """A water-immersion (NA 1.0) point emitter with 30 / −15 nm RMS of coma at five depths,
    its place 0.3 px right of and 0.2 px above its 15 px patch's centre pixel: (x, y) = (7.3,
    6.8) in the fit's ROI coordinates."""
    from latentz.validation import AberrationFields, Microscope
    from latentz.validation.datasets import render_patches
    from latentz.validation.fields import MODES

    microscope = Microscope(na=1.0, n_medium=1.333, pixel_size_nm=130.0)
    fields = AberrationFields.polynomial(
        (64, 64), degree=1, pixel_size_nm=130.0, mean_nm={"coma_x": 30.0, "coma_y": -15.0},
        std_nm=dict.fromkeys(MODES, 0.0),
    )  # fmt: skip
    z = np.array([-600.0, -300.0, 0.0, 300.0, 600.0])
    return render_patches(microscope, fields, 32.3, 31.8, z, 15), np.array([7.3, 6.8])


@pytest.mark.parametrize("photons", [3000.0, 800.0])
def test_position_shift_moves_a_dim_comatic_emitter_to_where_a_bright_one_is_read(comatic, photons):
    """With coma, a dim emitter's fitted centre lies elsewhere than a bright one's (the far
    wing weighs more against the background). The calibration's Δx'(z) holds the bright
    particle's error about its place; less the position shift, the dim emitter's error about
    its own place is the same."""
    psf, place = comatic
    bright = 2e5 * psf + 10.0
    fit = fit_arrays(bright, device="cpu")
    traces = {
        **dim_fits(bright, fit.params, method="mle", device="cpu"),
        "amplitude": fit.params[:, 2],
        "background": fit.params[:, 3],
    }
    dim = fit_arrays(photons * psf + 10.0, readnoise=READNOISE, device="cpu").params
    c_spot = background_ratio(dim[:, 3], dim[:, 2], READNOISE)
    c_own = fit.params[:, 3] / fit.params[:, 2]  # the bright fit has no read noise
    for j, axis in enumerate("xy"):
        bright_error = fit.params[:, j] - place[j]  # px: what Δx'(z) holds
        dim_error = dim[:, j] - place[j]
        shift = position_shift(traces.__getitem__, c_spot, c_own)[:, j]
        # 0.01 px = 1.3 nm, against dim-minus-bright differences up to 0.26 px (34 nm)
        assert np.abs(dim_error - shift - bright_error) == pytest.approx(0.0, abs=0.01), axis
        assert np.abs(dim_error - bright_error).max() > 0.1, axis


def test_dimmest_is_the_quantile_of_the_particles_at_each_depth():
    rng = np.random.default_rng(0)
    planes = np.arange(-1000.0, 1001.0, 50.0)
    # 4000 particles, each on the same planes shifted by its focus (< half a plane), each with
    # a background ratio c uniform on [1, 2] at every plane
    z = planes[None, :] - rng.uniform(-20, 20, (4000, 1))
    c = rng.uniform(1.0, 2.0, z.shape)
    c[:, :3] = np.nan  # no particle imaged there: no bin
    centres, edge = dimmest(z, c)
    assert np.allclose(centres, planes[3:], atol=20.0)
    assert np.allclose(edge, 1.0 + EDGE_QUANTILE, atol=0.01)


def _dimming_moves(cal, c: float) -> float:
    """How far (nm) the brightness correction moves the z of a spot made of the first kept
    particle's fit 0.4 µm from focus, with its background set for a ratio c."""
    p = int(cal.kept[0])
    plane = cal.traces["amplitude"].shape[1] // 2 + 4
    spot = {k: cal.traces[k][p, plane] for k in ("amplitude", "background", "wx", "wy", "rho")}
    x, y = cal.positions[p]
    table = pd.DataFrame([{**spot, "x": x, "y": y}])
    table["background"] = c * table["amplitude"] - cal.camera.readnoise**2
    with_b = cal.apply(table)["z_nm"].iloc[0]
    return with_b - cal.apply(table.drop(columns="background"))["z_nm"].iloc[0]


def test_spots_within_the_calibrations_brightness_are_not_corrected(small_calibration):
    """Where the calibration's brightness follows its beads' sizes (heights taken off), a spot
    dimmer than its nearest particle but as bright as the calibration's dimmer particles keeps
    its z, and one ten times dimmer than any is moved. With beads of one size, both are."""
    import copy

    cal = small_calibration
    assert cal.options["particle_heights"]["applied"]  # the simulator's beads: 24 nm s.d.
    p = int(cal.kept[0])
    plane = cal.traces["amplitude"].shape[1] // 2 + 4
    c = background_ratio(cal.traces["background"], cal.traces["amplitude"], cal.camera.readnoise)
    own = c[p, plane]
    z_edge, c_edge = dimmest(cal.local.z_nm[cal.kept], c[cal.kept])
    edge = np.interp(cal.local.z_nm[p, plane], z_edge, c_edge)
    assert edge > 1.05 * own  # the test needs a particle brighter than the edge
    within, dim = 0.5 * (own + edge), 10 * edge
    assert _dimming_moves(cal, within) == 0.0
    assert abs(_dimming_moves(cal, dim)) > 1.0  # nm
    one_size = copy.deepcopy(cal)
    one_size.options["particle_heights"]["applied"] = False
    assert abs(_dimming_moves(one_size, within)) > 0.01  # nm
    assert _dimming_moves(one_size, dim) == pytest.approx(_dimming_moves(cal, dim), abs=0.01)
