"""Cross-validation of the widefield prediction, field_model="auto", and the stored table."""

from types import SimpleNamespace

import numpy as np
import pandas as pd
import pytest
from calib_synthetic import make_traces

from latentz.calibration import Calibration, calibrate_traces
from latentz.calibration import crossval as crossval_module
from latentz.calibration.crossval import (
    MIN_FIELD_PARTICLES,
    choose_field_model,
    crossval,
    crossval_summary,
    lost_particles,
)
from latentz.calibration.errors import combine, field_sigma

N_PARTICLES = 60
OFFSET_SD_NM = 40.0


@pytest.fixture(scope="module")
def offset_calibration():
    """Particles whose focus is offset by white noise (no spatial correlation, no plane): each
    particle's z(s) is shifted by its own offset after tilt removal, so predicting it from the
    nearest other particle errs by the difference of two independent offsets."""
    rng = np.random.default_rng(4)
    z_f = rng.normal(0.0, OFFSET_SD_NM, N_PARTICLES)
    traces, truth = make_traces(N_PARTICLES, z_f=z_f, noise=0.02, seed=5)
    cal = calibrate_traces(traces, shape="rho", field_model="nearest", cull=False, tilt=False)
    return cal, truth


def test_nearest_crossval_error_is_the_difference_of_two_offsets(offset_calibration):
    cal, _ = offset_calibration
    summary = crossval_summary(crossval(cal, ("nearest",)))
    expected = np.sqrt(2.0) * OFFSET_SD_NM
    # the sample RMS of ~60 independent differences: relative standard error ~ 1/sqrt(2 * 60)
    assert summary.loc["nearest", "rmse_z_nm"] == pytest.approx(expected, rel=0.25)
    assert summary.loc["nearest", "in_range"] > 0.95


def test_field_sigma_is_the_nearest_particles_own_offset(offset_calibration):
    """Offsets without spatial correlation do not grow with distance: a spot near a particle
    errs by that particle's offset (SD OFFSET_SD_NM), half the held-out errors' variance of two,
    however close it is."""
    cal, _ = offset_calibration
    table = cal.crossval_of("nearest")
    sigma = field_sigma(table, "nearest", "z", np.array([-500.0, 0.0, 500.0, np.nan]), 5.0)
    # the RMS of ~60 independent offsets: relative standard error ~ 1/sqrt(2 * 60), 3 of them
    np.testing.assert_allclose(sigma[:3], OFFSET_SD_NM, rtol=0.25)
    assert np.isnan(sigma[3])


def test_combine_adds_in_quadrature_and_ignores_missing_parts():
    np.testing.assert_allclose(combine(np.array([3.0]), np.array([4.0]), np.nan), [5.0])


def _table(**rows):
    """A crossval table of 10 held-out particles of 10 planes each: per model, its z and
    lateral error (nm) on every plane it predicts and the share of planes it predicts (the
    first ones of the table)."""
    plane = np.arange(100)
    return pd.concat(
        [pd.DataFrame({"model": kind, "particle": plane // 10, "z_nm": 100.0 * (plane % 10),
                       "in_range": plane < round(share * 100), "err_z_nm": z, "err_x_nm": xy,
                       "err_y_nm": xy})
         for kind, (z, xy, share) in rows.items()],
        ignore_index=True,
    )  # fmt: skip


@pytest.mark.parametrize(
    ("rows", "chosen"),
    [
        ({"nearest": (50, 5, 1.0), "natural": (30, 4, 0.99), "zernike": (40, 4, 1.0)}, "natural"),
        ({"nearest": (50, 5, 1.0), "natural": (30, 4, 0.6), "zernike": (40, 4, 1.0)}, "zernike"),
        ({"nearest": (50, 5, 1.0), "natural": (30, 6, 1.0), "zernike": (60, 4, 1.0)}, "nearest"),
    ],
)
def test_auto_picks_the_best_model_never_worse_than_nearest(rows, chosen):
    assert choose_field_model(_table(**rows)) == chosen


def test_auto_ranks_by_the_typical_emitters_error_not_the_rms_of_the_range_ends():
    """Model a errs 300 nm at the 4 end planes and 10 nm elsewhere, b 200 nm and 20 nm, and an
    emitter's own σ_fit is 500 nm at the ends and 20 nm elsewhere: b has the smaller RMS, a the
    smaller total error sqrt(σ_fit² + err²) for the typical plane, so auto takes a."""
    sigma = np.r_[np.full(4, 500.0), np.full(96, 20.0)]
    errors = {"nearest": (400.0, 40.0), "a": (300.0, 10.0), "b": (200.0, 20.0)}
    table = pd.concat(
        [
            pd.DataFrame(
                {
                    "model": kind,
                    "particle": np.arange(100) // 10,
                    "z_nm": 100.0 * (np.arange(100) % 10),
                    "in_range": True,
                    "err_x_nm": 1.0,
                    "err_y_nm": 1.0,
                    "err_z_nm": np.r_[np.full(4, ends), np.full(96, rest)],
                }
            )  # fmt: skip
            for kind, (ends, rest) in errors.items()
        ],
        ignore_index=True,
    )
    with_sigma = crossval_summary(table, np.tile(sigma, 3))
    assert with_sigma.loc["a", "rmse_z_nm"] > with_sigma.loc["b", "rmse_z_nm"]
    assert choose_field_model(table, np.tile(sigma, 3)) == "a"
    assert choose_field_model(table) == "b"  # without σ_fit: the RMS


def test_auto_compares_the_models_on_the_planes_each_of_them_predicts():
    """``a`` predicts all 100 held-out planes, ``b`` all but the far end of 4 particles (96 %),
    where an emitter's σ_fit is 500 nm and ``a`` errs 300 nm; elsewhere ``a`` errs 10 nm, ``b``
    20 and ``nearest`` 40. Over the planes each predicts ``b``'s typical error is the smaller
    (28 nm against 45, which the 4 far planes rule); on the planes both predict it is ``a``'s
    (22 nm against 28), and auto takes ``a``."""
    table = _table(nearest=(40.0, 5.0, 1.0), a=(10.0, 4.0, 1.0), b=(20.0, 4.0, 1.0))
    far = (table["particle"] < 4) & (table["z_nm"] == 900.0)
    table.loc[far & (table["model"] == "a"), "err_z_nm"] = 300.0
    table.loc[far & (table["model"] == "b"), "in_range"] = False
    sigma = np.where(far, 500.0, 20.0)
    summary = crossval_summary(table, sigma)
    assert summary.loc["b", "typical_z_nm"] < summary.loc["a", "typical_z_nm"]
    assert choose_field_model(table, sigma) == "a"


def test_auto_takes_nearest_where_the_models_share_no_held_out_plane():
    table = _table(nearest=(40.0, 5.0, 0.0), a=(10.0, 4.0, 1.0))
    assert choose_field_model(table) == "nearest"


def test_auto_with_too_few_particles_says_so_and_uses_nearest():
    traces, _ = make_traces(MIN_FIELD_PARTICLES - 2, noise=0.02, seed=1)
    cal = calibrate_traces(traces, shape="rho", cull=False)
    assert cal.options["field_model"] == "auto"
    with pytest.warns(UserWarning, match="using 'nearest'"):
        assert cal.field_model == "nearest"


@pytest.mark.slow
def test_auto_calibration_round_trips_with_its_crossval(offset_calibration, tmp_path):
    cal, truth = offset_calibration
    auto = calibrate_traces(cal.traces, shape="rho", field_model="auto", cull=False, tilt=False)
    spots = pd.DataFrame(
        {
            "x": truth["positions"][:20, 0] + 0.3,
            "y": truth["positions"][:20, 1] - 0.2,
            **{c: auto.traces[c][:20, 60] for c in ("amplitude", "wx", "wy", "rho")},
        }
    )
    before = auto.apply(spots)
    auto.save(tmp_path / "cal.h5")
    loaded = Calibration.load(tmp_path / "cal.h5")
    assert loaded.field_model == auto.field_model
    pd.testing.assert_frame_equal(loaded.crossval_of(auto.field_model),
                                  auto.crossval_of(auto.field_model))  # fmt: skip
    pd.testing.assert_frame_equal(loaded.apply(spots), before)


def test_a_model_that_loses_held_out_particles_is_counted_and_never_chosen():
    """Ten held-out particles of 20 planes each; ``nearest`` predicts every plane, ``zernike``
    errs less where it predicts but predicts only 5 planes (under half) of particles 0-3, and
    ``curves`` predicts 12 of every particle's planes (not lost, but 60 % coverage)."""
    rows = []
    for particle in range(10):
        planes = np.arange(20)
        for kind, err, predicted in (("nearest", 30.0, 20), ("zernike", 10.0, 5 if particle < 4
                                      else 20), ("curves", 20.0, 12)):  # fmt: skip
            rows.append(pd.DataFrame({"model": kind, "particle": particle, "z_nm": 100.0 * planes,
                                      "in_range": planes < predicted, "err_x_nm": 1.0,
                                      "err_y_nm": 1.0, "err_z_nm": err}))  # fmt: skip
    table = pd.concat(rows, ignore_index=True)
    lost, held_out = lost_particles(table)
    assert held_out == 10 and lost.to_dict() == {"curves": 0, "nearest": 0, "zernike": 4}
    summary = crossval_summary(table)
    assert summary.loc["zernike", "rmse_z_nm"] < summary.loc["nearest", "rmse_z_nm"]
    assert choose_field_model(table) == "nearest"  # zernike loses 4, curves covers 60 %
    assert choose_field_model(table[table["model"] != "zernike"], coverage=0.5) == "curves"

    # `auto` names the losing model and its count, in whole particles
    view = SimpleNamespace(kept=np.arange(MIN_FIELD_PARTICLES), crossval=table)
    with pytest.warns(UserWarning, match=r"'zernike' loses 4 of 10 held-out") as caught:
        with pytest.MonkeyPatch.context() as patch:
            patch.setattr(
                crossval_module, "emitter_sigma_z", lambda cal, t: np.full(len(t), np.nan)
            )
            assert crossval_module.resolve_auto(view) == "nearest"
    assert len(caught) == 1
