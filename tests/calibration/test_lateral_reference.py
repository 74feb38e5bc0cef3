"""The lateral σ holds the particles' own reference where coma varies across the field.

Δx', Δy' are measured from each particle's fitted centre at its best focus. With coma that
centre moves through focus, and the particle's place lies somewhere along that path, off its
centre at focus by an amount that follows the coma across the field. Here each microscope's
images move in y by α(place) · (z − z_f − t*) · SLOPE: a smooth random coma field α of the
place (not a plane) and a place that lies on the path at t* from focus. Over the microscopes t*
steps evenly across the depth of focus (where the image's amplitude is at least
:data:`~latentz.calibration.errors.DEPTH_FRACTION` of its peak, from the image model of
``calib_synthetic``), and emitters between the particles are read with the particles'
calibration. Truth is geometric: where each emitter was put.
"""

import numpy as np
import pytest
from calib_synthetic import make_traces, widths

from latentz.calibration import calibrate_traces
from latentz.calibration.errors import DEPTH_FRACTION
from latentz.calibration.traces import Traces, traces_table

Z = np.arange(-2000.0, 2000.1, 50.0)
SLOPE = 0.2 / 1000  # px of y per nm of z per unit of α
MICROSCOPES = 8


def _coma(rng, wavelength_px: float = 250.0, waves: int = 8):
    """A smooth random field α (RMS 1) of (n, 2) places (px)."""
    angle, phase = rng.uniform(0, 2 * np.pi, waves), rng.uniform(0, 2 * np.pi, waves)
    k = 2 * np.pi / wavelength_px * np.column_stack([np.cos(angle), np.sin(angle)])
    return lambda p: np.sqrt(2 / waves) * np.cos(p @ k.T + phase).sum(axis=1)


def _half_depth_nm() -> float:
    """Half the z extent where the images' amplitude N / (2π σ1 σ2) is at least
    :data:`DEPTH_FRACTION` of its peak."""
    t = np.linspace(-3000.0, 3000.0, 60001)
    _, _, _, s1, s2 = widths(t, 0.0, theta=np.pi / 4)
    inside = t[s1 * s2 <= np.min(s1 * s2) / DEPTH_FRACTION]
    return float(inside[-1] - inside[0]) / 2


def _with_coma(traces: Traces, truth: dict, alpha: np.ndarray, t_star: float) -> Traces:
    """``traces`` with y moved by α · (z − z_f − t*) · SLOPE."""
    data = dict(traces.data)
    shift = alpha[:, None] * (traces.z_nm[None] - truth["z_f"][:, None] - t_star) * SLOPE
    data["y"] = data["y"] + shift
    return Traces(traces.z_nm, data)


def _microscope(seed: int, t_star: float):
    """(calibration, its emitters' spots, their true y in px, t*)."""
    rng = np.random.default_rng(seed)
    coma = _coma(rng)
    gx, gy = np.meshgrid(np.arange(25.0, 500.0, 50.0), np.arange(25.0, 500.0, 50.0))
    places = np.column_stack([gx.ravel(), gy.ravel()]) + rng.normal(0, 4.0, (gx.size, 2))
    traces, truth = make_traces(len(places), z_nm=Z, positions=places, noise=0.02, seed=seed)
    cal = calibrate_traces(_with_coma(traces, truth, coma(places), t_star), shape="rho",
                           field_model="curves", cull=False, tilt=False)  # fmt: skip
    emitters = rng.uniform(50.0, 450.0, (40, 2))
    test, test_truth = make_traces(len(emitters), z_nm=np.arange(-600.0, 600.1, 100.0),
                                   positions=emitters, noise=0.02, seed=seed + 100)  # fmt: skip
    spots = traces_table(_with_coma(test, test_truth, coma(emitters), t_star))
    return cal, spots, np.repeat(emitters[:, 1], test.z_nm.size), t_star


@pytest.fixture(scope="module")
def microscopes():
    half = _half_depth_nm()
    steps = (np.arange(MICROSCOPES) + 0.5) / MICROSCOPES * 2 - 1  # evenly over (−1, 1)
    return [_microscope(seed, step * half) for seed, step in enumerate(steps)]


def test_y_sigma_holds_the_particles_reference_under_coma(microscopes):
    """Off one plane (as the scoring takes off), the emitters' y errors are their particles'
    references, α · t* · SLOPE, and the reference part of σ_y² is the mean square of α's
    travel off the plane within the depth of focus ±h, α² · SLOPE² · h²/3: per microscope
    mean(err²) / mean(σ_y²) is about t*² / (h²/3), which averages 1 over the t*. Without the
    reference part (``lateral_reference="focus"``) σ_y holds the fits and the field model
    alone: that ratio is 0.4–18 (7 on average)."""
    half = _half_depth_nm()
    measured, expected = [], []
    for cal, spots, true_y, t_star in microscopes:
        out = cal.apply(spots)
        keep = out["in_range"].to_numpy()
        assert keep.mean() > 0.9
        err = out["y_nm"].to_numpy()[keep] - true_y[keep] * cal.camera.pixel_size_nm
        design = np.column_stack([np.ones(keep.sum()), out[["x", "y"]].to_numpy()[keep]])
        err -= design @ np.linalg.lstsq(design, err, rcond=None)[0]
        measured.append(np.mean(err**2) / np.mean(out["y_err_nm"].to_numpy()[keep] ** 2))
        expected.append(t_star**2 / (half**2 / 3))
    print("mean(err²) / mean(σ²):", np.round(measured, 2), "expected:", np.round(expected, 2))
    assert 0.5 <= np.mean(measured) / np.mean(expected) <= 1.5
