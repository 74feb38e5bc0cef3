"""The "calibration quality" section that opens every report: the uncertainties that latentz
reports against the errors it actually makes, and what the calibration used and kept.

Actual errors come from truth when there is one (the demo) and otherwise from the calibration's
leave-one-particle-out cross-validation (``cal.crossval``), when the calibration carries it.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np
import pandas as pd

from latentz.calibration.heights import describe as describe_heights
from latentz.report import Section

if TYPE_CHECKING:
    from latentz.calibration.result import Calibration

__all__ = ["coverage_table", "quality_section", "SHAPE_NAMES"]

#: How each shape parameter is written in the report (the paper's eqs. 4–6 and latentz's "auto").
SHAPE_NAMES = {
    "rho": "ρ (eq. 4)",
    "rho_w": "ρ_w (eq. 5)",
    "rho_A": "ρ_A (eq. 6)",
    "auto": "e_θ, the ellipticity along the fitted astigmatism angle (intensity-free)",
    "auto_A": "e_θ / A_n, the ellipticity along the fitted astigmatism angle over amplitude",
}
_FIELD_NAMES = {
    "zernike": "Zernike polynomials over the field",
    "natural": "natural-neighbour interpolation between particles",
    "curves": "the particles' own shape curves, interpolated across the field (thin-plate spline)",
    "nearest": "the nearest calibration particle's own models",
}


def coverage_table(errors: pd.DataFrame, *, source: str) -> pd.DataFrame:
    """Reported uncertainty against actual error, per axis.

    ``errors`` holds, for each axis a of x, y, z present, the actual error ``err_a_nm`` and the
    reported one-sigma uncertainty ``a_err_nm`` (nm) of the same localizations. One global offset
    per axis is removed from the actual errors first (an origin, not an error of the method).
    Returns one row per axis: median reported σ, actual RMS error, their ratio and the
    fraction of errors within 1σ (68 % expected).
    """
    rows = []
    for axis in "xyz":
        actual_col, sigma_col = f"err_{axis}_nm", f"{axis}_err_nm"
        if not {actual_col, sigma_col} <= set(errors.columns):
            continue
        both = errors[[actual_col, sigma_col]].dropna()
        if both.empty:
            continue
        actual = both[actual_col] - both[actual_col].mean()
        sigma = both[sigma_col]
        rms = float(np.sqrt(np.mean(actual**2)))
        rows.append(
            {
                "axis": axis,
                "median reported σ (nm)": float(sigma.median()),
                "actual RMS error (nm)": rms,
                "RMS error / median σ": rms / float(sigma.median()),
                "within 1σ (%)": 100.0 * float(np.mean(np.abs(actual) <= sigma)),
                "localizations": len(both),
                "errors from": source,
            }
        )
    return pd.DataFrame(rows)


def _verdict(table: pd.DataFrame) -> str:
    if table.empty:
        return ""
    bad = table[(table["within 1σ (%)"] < 50) | (table["within 1σ (%)"] > 85)]
    if bad.empty:
        return (
            "The reported uncertainties are honest here: 1σ covers 50–85 % of the actual errors "
            "on every axis (68 % expected)."
        )
    parts = [
        f"{row['axis']} against {row['errors from']} (1σ covers "
        f"{row['within 1σ (%)']:.0f} %, the actual RMS error is "
        f"{row['RMS error / median σ']:.1f} × the median σ)"
        for _, row in bad.iterrows()
    ]
    return (
        "Warning: the reported uncertainties do not describe the actual errors on "
        + "; ".join(parts)
        + ". Read the x_err_nm, y_err_nm, z_err_nm columns of these localizations with that "
        "factor in mind."
    )


def _crossval_errors(cal: Calibration) -> pd.DataFrame | None:
    """The calibration's leave-one-particle-out prediction errors, if it carries them."""
    table = getattr(cal, "crossval", None)
    if callable(table):
        table = table()
    return table if isinstance(table, pd.DataFrame) and len(table) else None


def _why(cal: Calibration, key: str, default: str) -> str:
    """Why ``calibrate`` chose the shape, ``roi_size`` or field model, else ``default``."""
    reasons = {
        "shape": (cal.shape_choice or {}).get("reason"),
        "roi_size": cal.options.get("roi_size_reason"),
        "field_model": "chosen by leave-one-particle-out cross-validation of the whole prediction"
        if cal.options.get("field_model") == "auto"
        else None,
    }
    return str(reasons[key] or default)


def quality_section(
    cal: Calibration, *, name: str = "", truth: dict[str, pd.DataFrame] | None = None
) -> Section:
    """What a reader must know before trusting the rest of a report on calibration ``cal``.

    Parameters
    ----------
    cal : Calibration
    name : str
        The calibration's file or run name, for the title.
    truth : dict of DataFrame, optional
        Actual errors against truth (``err_x_nm`` …) with the reported ``x_err_nm`` … of the same
        localizations (the demo), by what they are (e.g. "gear particles against simulated
        truth"); otherwise the calibration's cross-validation is used.
    """
    particles = cal.particles
    n, n_kept = len(particles), int((~particles["culled"]).sum())
    reasons = particles.loc[particles["culled"], "reason"].str.split(",").explode().value_counts()
    culled_text = (
        f"{n - n_kept} culled ("
        + ", ".join(f"{count} {reason}" for reason, count in reasons.items())
        + "; listed under Calibration)"
        if n > n_kept
        else "none culled"
    )
    roi = cal.options.get("roi_size")
    roi_text = (
        f"{roi} × {roi} px ({roi * cal.camera.pixel_size_nm / 1000:.2f} µm)" if roi else "default"
    )
    asked = "as requested when calibrating"
    text = [
        f"Shape parameter: {SHAPE_NAMES.get(cal.shape, cal.shape)}; {_why(cal, 'shape', asked)}. "
        f"ROI: {roi_text}; {_why(cal, 'roi_size', asked)}. Field model: "
        f"{_FIELD_NAMES.get(cal.field_model, cal.field_model)}; "
        f"{_why(cal, 'field_model', asked)}.",
        f"Particles: {n} found, {n_kept} kept, {culled_text}. Pixel size "
        f"{cal.camera.pixel_size_nm:.2f} nm; substrate tilt {cal.tilt_mrad:.2f} mrad removed. "
        + describe_heights(cal.options.get("particle_heights")),
    ]
    tables = {}
    if truth:
        table = pd.concat(
            [coverage_table(errors, source=label) for label, errors in truth.items()],
            ignore_index=True,
        )
    else:
        crossval = _crossval_errors(cal)
        table = (
            coverage_table(crossval, source="leave-one-particle-out cross-validation")
            if crossval is not None
            else pd.DataFrame()
        )
    if table.empty:
        text.append(
            "This calibration carries no cross-validation, so the reported uncertainties "
            "(x_err_nm, y_err_nm, z_err_nm) could not be checked against actual errors here: "
            "recalibrate with a latentz that records `crossval`, or localize particles of known "
            "position."
        )
    else:
        text.append(
            "Reported uncertainty against actual error: a reported 1σ should cover about 68 % of "
            "the actual errors, and the RMS error should be about the median σ."
        )
        text.append(_verdict(table))
        tables["Reported uncertainty against actual error"] = table
    title = f"Calibration quality: {name}" if name else "Calibration quality"
    return Section(title, "\n\n".join(text), tables=tables)
