"""The calibration-quality section: reported uncertainty against actual error."""

import numpy as np
import pandas as pd

from latentz.report.calibration_quality import coverage_table


def test_coverage_of_honest_and_of_overconfident_uncertainties():
    rng = np.random.default_rng(0)
    sigma = rng.uniform(1.0, 3.0, 20000)
    errors = pd.DataFrame(
        {
            "err_x_nm": 50.0 + rng.normal(0.0, sigma),  # a global offset is not an error
            "x_err_nm": sigma,
            "err_z_nm": rng.normal(0.0, 4 * sigma),
            "z_err_nm": sigma,  # four times too small
        }
    )
    table = coverage_table(errors, source="truth").set_index("axis")
    assert list(table.index) == ["x", "z"]
    # 20000 normal errors: 68.3 % ± 0.3 % (1 standard deviation) within 1σ
    assert abs(table.loc["x", "within 1σ (%)"] - 68.3) < 1.5
    # P(|N(0, 16)| <= 1) = 19.7 %
    assert abs(table.loc["z", "within 1σ (%)"] - 19.7) < 1.5
    assert table.loc["z", "RMS error / median σ"] > 3.5


def test_the_section_says_why_each_choice_was_made(small_calibration):
    """Defaults chose the shape and the ROI; the field model was given ("nearest")."""
    from latentz.report.calibration_quality import quality_section

    text = quality_section(small_calibration).text
    assert small_calibration.shape_choice["reason"] in text
    reason = small_calibration.options["roi_size_reason"]
    assert "expected z error" in reason and f"ROI: {small_calibration.roi_size} × " in text
    assert reason in text
    assert text.count("as requested when calibrating") == 1  # the field model only
