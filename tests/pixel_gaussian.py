"""A Gaussian integrated over each pixel: test images whose truth is where the spot was put,
made without latentz's own renderer."""

import numpy as np
from scipy.special import erf


def pixel_profile(centre_px: np.ndarray, sigma_px: np.ndarray, n: int) -> np.ndarray:
    """(m, n) share of a unit 1D Gaussian in each of ``n`` pixels (pixel k spans k − ½ … k + ½),
    one row per centre ``centre_px`` (m,) and standard deviation ``sigma_px`` (m,), px."""
    edges = np.arange(n + 1) - 0.5
    centre = np.asarray(centre_px, float)[:, None]
    scaled = (edges[None, :] - centre) / (np.sqrt(2) * np.asarray(sigma_px, float)[:, None])
    return np.diff(erf(scaled), axis=1) / 2
