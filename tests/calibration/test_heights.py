"""Each calibration particle's own height, from its brightness (latentz.calibration.heights).

Truth: latentz's simulator draws bead diameters (the paper's 1000 ± 24 nm), puts each centre d/2
above the substrate and gives each bead photons in proportion to d³; the estimator knows none of
this (it fits the slope of best focus against log brightness freely). The independent validation
microscope's beads are all of one size, so there the correction must stay off.
"""

import numpy as np
import pytest

import latentz as lz

pytestmark = pytest.mark.slow
ROI = 15


@pytest.fixture(scope="module")
def polydisperse():
    from latentz import simulate as sim
    from latentz.calibration import calibrate_traces

    field = (384, 384)
    data = sim.calibration_dataset(
        n_particles=40,
        z_nm=np.linspace(-1500, 1500, 31),
        seed=2,
        n_stage_positions=1,
        frame_shape=field,
        min_spacing_px=40.0,
        aberrations=sim.AberrationMap.default(seed=2, field_shape=field),
    )
    options = {"camera": data.camera, "shape": "rho_w", "roi_size": ROI, "field_model": "nearest"}
    cal = lz.calibrate(data.stacks, data.z_nm, **options)
    return data, cal, calibrate_traces(cal.traces, heights=False, **options)


def _true_heights(data, cal) -> np.ndarray:
    """Each particle's centre height above the substrate, less the mean, matched by position."""
    truth = data.truth
    xy = truth[["field_x", "field_y"]].to_numpy()
    index = np.argmin(np.linalg.norm(cal.positions[:, None, :] - xy[None], axis=2), axis=1)
    half = truth["diameter_nm"].to_numpy()[index] / 2
    return half - half[~cal.culled].mean()


def test_bead_heights_are_found_from_brightness(polydisperse):
    data, cal, _ = polydisperse
    fit = cal.options["particle_heights"]
    assert fit["applied"] and fit["p_value"] < 1e-6
    # volume-dyed beads: |δ| = (d̄ / 6) ln(N / N̄), 167 nm per e-fold for 1 µm
    assert abs(abs(fit["slope_nm"]) - 1000 / 6) < 3 * fit["slope_err_nm"]
    true = _true_heights(data, cal)[~cal.culled]
    assert true.std() > 9  # the paper's 24 nm s.d. of diameter: 12 nm of height


def test_moving_each_particle_by_its_height_levels_the_focus(polydisperse):
    data, cal, plain = polydisperse
    kept = ~cal.culled
    true = _true_heights(data, cal)[kept]

    def scatter(c) -> float:
        """RMS of the kept particles' z_f about a cubic surface of best focus (nm)."""
        u = (c.positions[kept] - 192.0) / 192.0
        design = np.column_stack([u[:, 0] ** i * u[:, 1] ** j for i in range(4)
                                  for j in range(4 - i)])  # fmt: skip
        zf = c.local.z_f[kept]
        return float(
            np.sqrt(np.mean((zf - design @ np.linalg.lstsq(design, zf, rcond=None)[0]) ** 2))
        )

    before, after = scatter(plain), scatter(cal)
    print(f"\nbest focus about a smooth surface: {before:.1f} -> {after:.1f} nm RMS; true "
          f"heights {true.std():.1f} nm")  # fmt: skip
    assert before > 0.8 * true.std()
    assert after < 0.5 * before
    # what moved is each particle's own height (0.89 correlated with it, measured), not the field
    moved = plain.local.z_f[kept] - cal.local.z_f[kept]
    assert abs(np.corrcoef(moved, true)[0, 1]) > 0.8


def test_beads_of_one_size_are_left_where_they_are():
    from latentz.validation import make_data

    data = make_data("small", seed=1, n_frames=1)
    cal = lz.calibrate(data.stacks, data.z_nm, camera=data.camera, shape="rho_w", roi_size=ROI,
                       field_model="nearest")  # fmt: skip
    fit = cal.options["particle_heights"]
    assert fit["particles"] >= 20
    assert not fit["applied"], fit


def _synthetic(slope_nm: float, width_px: float, seed: int = 0):
    """Traces-like columns of 40 particles whose best focus is a smooth surface plus
    ``slope_nm`` times their log brightness (7 % s.d.), imaged ``width_px`` wide in focus."""
    from latentz.fit._model import photons_of

    rng = np.random.default_rng(seed)
    n, z = 40, np.linspace(-1000.0, 1000.0, 21)
    position = rng.uniform(0, 400, (n, 2))
    log_n = rng.normal(0.0, 0.07, n)
    z_f = 1e-3 * (position[:, 0] - 200) ** 2 + slope_nm * log_n + rng.normal(0.0, 1.0, n)
    width = np.full((n, z.size), width_px)
    unit = photons_of(np.ones_like(width), width, width, np.zeros_like(width))
    traces = {"amplitude": np.exp(12 + log_n)[:, None] / unit, "wx": width, "wy": width,
              "rho": np.zeros_like(width)}  # fmt: skip
    return traces, np.tile(z, (n, 1)), z_f, position, log_n


@pytest.mark.parametrize(("slope_nm", "applied"), [(150.0, True), (3000.0, False)])
def test_a_slope_implying_beads_wider_than_their_images_is_not_applied(slope_nm, applied):
    # 2.5 px of 100 nm in focus: FWHM 589 nm, so beads up to 883 nm; 4|k| = 600 and 12,000 nm
    from latentz.calibration.heights import particle_heights

    traces, z_nm, z_f, position, log_n = _synthetic(slope_nm, 2.5)
    heights, fit = particle_heights(traces, z_nm, z_f, position, np.ones(40, bool),
                                    pixel_size_nm=100.0)  # fmt: skip
    assert fit["p_value"] < 1e-6  # significant either way
    assert fit["implied_diameter_nm"] == pytest.approx(4 * slope_nm, rel=0.05)
    assert fit["applied"] is applied
    if applied:  # the slope times the brightness less its cubic trend over 40 particles (0.86)
        assert np.corrcoef(heights, log_n)[0, 1] > 0.8
    else:
        assert not heights.any()
