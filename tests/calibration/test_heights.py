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
