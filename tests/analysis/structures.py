"""Localization tables of known geometry for the analysis tests: rings, blinking emitters in 3D,
fiducial beads, and a known drift. The truth is where the simulation put each emitter."""

from __future__ import annotations

import numpy as np
import pandas as pd


def rings(
    rng: np.random.Generator,
    *,
    n_rings: int,
    diameter_nm: float,
    precision_nm: float,
    per_ring: int,
    field_nm: float,
) -> tuple[pd.DataFrame, np.ndarray]:
    """Localizations on ``n_rings`` circles of ``diameter_nm`` (uniform angle, Gaussian error of
    ``precision_nm`` in x, y, 2.5 times that in z; each ring at a random depth, ``z_true``) at
    random places at least 3 diameters apart; returns the table (``per_ring`` rows per ring, in
    order) and the true centres (n_rings, 2)."""
    centres: list[np.ndarray] = []
    while len(centres) < n_rings:
        c = rng.uniform(2 * diameter_nm, field_nm - 2 * diameter_nm, 2)
        if all(np.hypot(*(c - o)) > 3 * diameter_nm for o in centres):
            centres.append(c)
    centres = np.array(centres)
    ring = np.repeat(np.arange(n_rings), per_ring)
    angle = rng.uniform(0, 2 * np.pi, ring.size)
    depth = rng.uniform(-300, 300, n_rings)[ring]
    n = ring.size
    table = pd.DataFrame(
        {
            "frame": rng.integers(0, 1000, n),
            "x_nm": centres[ring, 0]
            + diameter_nm / 2 * np.cos(angle)
            + rng.normal(0, precision_nm, n),
            "y_nm": centres[ring, 1]
            + diameter_nm / 2 * np.sin(angle)
            + rng.normal(0, precision_nm, n),
            "z_nm": depth + rng.normal(0, 2.5 * precision_nm, n),
            "z_true": depth,
            "x_err_nm": precision_nm,
            "y_err_nm": precision_nm,
            "z_err_nm": 2.5 * precision_nm,
        }
    )
    return table, centres


def known_drift(frames: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    """Drift (n, 3) in nm at ``frames`` of a 10^4-frame movie: linear plus a slow oscillation
    (one period over the movie, random phase), 100 nm in x and y and 50 nm in z from end to end
    of the linear part."""
    t = frames / 10_000
    phase = rng.uniform(0, 2 * np.pi, 3)
    amplitude = np.array([100.0, 100.0, 50.0])
    return amplitude * (0.7 * t[:, None] + 0.3 * np.sin(2 * np.pi * t[:, None] + phase))


def blinking_emitters(
    rng: np.random.Generator,
    *,
    n_emitters: int,
    n_frames: int,
    p_on: float,
    field_nm: float,
    precision_nm: float,
    depth_nm: float = 800.0,
) -> pd.DataFrame:
    """Emitters at random 3D places, each seen in a frame with probability ``p_on``; x, y error
    ``precision_nm``, z error 2.5 times that. Columns: frame, emitter, the true and measured
    x_nm, y_nm, z_nm, their errors, and photons (a column to carry through)."""
    where = np.column_stack(
        [
            rng.uniform(0, field_nm, (n_emitters, 2)),
            rng.uniform(-depth_nm / 2, depth_nm / 2, n_emitters),
        ]
    )
    counts = rng.binomial(n_frames, p_on, n_emitters)
    emitter = np.repeat(np.arange(n_emitters), counts)
    frame = rng.integers(0, n_frames, emitter.size)
    return _measured(rng, where[emitter], frame, emitter, precision_nm)


def fiducials(
    rng: np.random.Generator, *, n_beads: int, n_frames: int, field_nm: float, precision_nm: float
) -> pd.DataFrame:
    """Static beads seen in 95 % of the frames, precision ``precision_nm`` (z 2.5 times)."""
    where = np.column_stack(
        [rng.uniform(0.1 * field_nm, 0.9 * field_nm, (n_beads, 2)), rng.uniform(-200, 200, n_beads)]
    )
    frame = np.tile(np.arange(n_frames), n_beads)
    bead = np.repeat(np.arange(n_beads), n_frames)
    seen = rng.random(frame.size) < 0.95
    table = _measured(rng, where[bead[seen]], frame[seen], bead[seen] - n_beads, precision_nm)
    return table


def _measured(rng, truth: np.ndarray, frame: np.ndarray, emitter: np.ndarray, precision_nm: float):
    n = len(frame)
    error = rng.normal(0, 1, (n, 3)) * precision_nm * np.array([1.0, 1.0, 2.5])
    return pd.DataFrame(
        {
            "frame": frame,
            "emitter": emitter,
            "x_true": truth[:, 0],
            "y_true": truth[:, 1],
            "z_true": truth[:, 2],
            "x_nm": truth[:, 0] + error[:, 0],
            "y_nm": truth[:, 1] + error[:, 1],
            "z_nm": truth[:, 2] + error[:, 2],
            "x_err_nm": precision_nm,
            "y_err_nm": precision_nm,
            "z_err_nm": 2.5 * precision_nm,
            "photons": rng.gamma(4.0, 500.0, n),
        }
    )
