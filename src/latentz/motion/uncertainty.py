"""Monte Carlo uncertainty of rigid motion in six degrees of freedom (paper, Supp. Note 2).

The procedure of the paper, step by step (step 2 differs, see "Why per transition"):

1. Replay the measured transforms in series on the particle positions of the first frame, giving
   synthetic positions identical to the data except for localization noise. (A particle first seen
   later is carried back to frame 0 by the inverse of the composed transforms.)
2. Take each particle's experimental residual vector (x, y, z) in each transition as the scale of
   its noise in that transition (the paper takes each particle's mean and variance per axis over
   all transitions; see "Why per transition").
3. For each transition, add to the synthetic positions of the later frame that vector times one
   standard normal per particle, refit the rigid transform from the noise-free earlier frame, and
   record the error of each degree of freedom against the replayed (true) motion.
4. Scale the noise variance per axis (the paper's "additional variance of 8 % to 15 %") so that the
   RMS residuals of the synthetic fits match the experimental ones (Supp. Table 4): a residual
   loses the variance that the fit absorbs, so noise matched to residuals alone is too small.
5. Pool the standard deviations of the errors over transitions (root mean of the variances).

The experimental residual of a transition carries the noise of both frames, so noise of that size
on one side of the synthetic fit reproduces the errors of the real two-sided fit.

Why per transition: localization errors are not the same size in every cycle. A particle near the
edge of the field, or partly outside it, is localized tens of nm off in a few cycles and to a few
nm in the others. A variance pooled over a particle's transitions spreads those few large errors
over every cycle, so every simulated cycle is as noisy as the worst ones. Those errors are also
mostly radial (along the line from the field's centre, near the gear's), which does not turn the
gear; variances drawn independently per axis point them in every direction, and over a revolution
they turn it. Both made σ too wide: in the full demo γ was covered in 92 % of the cycles and Δx in
88 %. Noise along each transition's own residual keeps the quiet cycles quiet, the bad ones bad
and radial errors radial: ``sigma`` then describes the bulk of the cycles, ``std`` (larger where a
few cycles are bad) their RMS, and ``per_transition=True`` gives each cycle its own standard
deviation.

Speed: the Kabsch estimate depends on the noisy positions only through ``H = A_cᵀ N`` and the mean
noise ``n̄`` (``A_c``: the centred, noise-free earlier constellation). These 12 numbers are linear
in the particles' standard normals, so they are formed directly from them (n normals and 12 n
products per simulation instead of 3 n noise values and a fit of n positions), exactly equivalent
to drawing every particle's noise. The rotations come from the batched numba Kabsch kernel; work
is chunked over simulations to bound memory.
"""

from __future__ import annotations

import numpy as np
import pandas as pd

from latentz._shared.validate import check_columns, check_int
from latentz.motion._axis_angle import decompose_rotation
from latentz.motion.rigid import (
    DOF_COLUMNS,
    _centre,
    _fit_transitions,
    kabsch,
    rotation_from_angles,
    rotations_from_covariance,
    tracks_to_array,
)

__all__ = ["motion_uncertainty", "representative_simulation"]

_CHUNK_MATRICES = 400_000
_PILOT_RESIDUALS = 200_000


def _wrap(angle: np.ndarray) -> np.ndarray:
    return (angle + np.pi) % (2.0 * np.pi) - np.pi


def _measured_transforms(pos, frames, motion):
    """R (T, 3, 3), t (T, 3) of the measured motion and the residuals of the data about them."""
    rot, trans, res, both = _fit_transitions(pos)
    if motion is None:
        return rot, trans, res, both
    check_columns("motion", motion, ("frame", *DOF_COLUMNS))
    if len(motion) != frames.size - 1 or not np.array_equal(motion["frame"], frames[1:]):
        raise ValueError(
            f"`motion` must have one row per transition of `tracks` ({frames.size - 1}, the "
            f"frames after the first), got {len(motion)} rows."
        )
    rot = rotation_from_angles(motion["gamma"], motion["beta"], motion["alpha"])
    trans = motion[["dx_nm", "dy_nm", "dz_nm"]].to_numpy(float)
    prev = np.where(both[..., None], pos[:-1], 0.0)
    res = pos[1:] - np.einsum("tij,tkj->tki", rot, prev) - trans[:, None, :]
    res[~both] = np.nan
    return rot, trans, res, both


def _replay(pos, rot, trans, valid):
    """Noise-free synthetic positions (F, P, 3): the measured transforms applied in series."""
    n_frames = pos.shape[0]
    pose_r = np.empty((n_frames, 3, 3))
    pose_t = np.empty((n_frames, 3))
    pose_r[0], pose_t[0] = np.eye(3), 0.0
    for k in range(1, n_frames):
        r, t = (rot[k - 1], trans[k - 1]) if valid[k - 1] else (np.eye(3), np.zeros(3))
        pose_r[k] = r @ pose_r[k - 1]
        pose_t[k] = r @ pose_t[k - 1] + t
    seen = np.isfinite(pos).all(-1)
    first = seen.argmax(axis=0)
    cols = np.arange(pos.shape[1])
    local = pos[first, cols] - pose_t[first]
    q0 = np.einsum("pji,pj->pi", pose_r[first], local)
    return np.einsum("kij,pj->kpi", pose_r, q0) + pose_t[:, None, :]


def _noise_vectors(res, both):
    """Noise scale (T, P, 3) of every particle in every transition: its own residual there (0
    where it is not in both frames). The noise is this vector times one standard normal."""
    return np.where(both[..., None], res, 0.0)


def _explicit_fits(q_prev, q_next, mask, vectors, rng, n):
    """``n`` simulations with every particle's noise drawn explicitly: residuals (n, T, P, 3),
    NaN where a particle is not in both frames, and the fitted R (n, T, 3, 3), t (n, T, 3)."""
    shape = (n,) + q_next.shape
    noise = vectors * rng.standard_normal(shape[:-1] + (1,))
    src = np.broadcast_to(q_prev, shape)
    dst = q_next + noise
    w = np.broadcast_to(mask, shape[:-1]).astype(float)
    r, t = kabsch(src, dst, weights=w)
    res = dst - np.matmul(src, np.swapaxes(r, -1, -2)) - t[..., None, :]
    return np.where(w[..., None] > 0, res, np.nan), r, t


def _pilot_rms(q_prev, q_next, mask, vectors, scale, rng, n_pilot):
    """RMS residual per axis of synthetic fits with explicitly drawn per-particle noise."""
    res, _, _ = _explicit_fits(q_prev, q_next, mask, vectors * np.sqrt(scale), rng, n_pilot)
    return np.sqrt(np.nanmean(res**2, axis=(0, 1, 2)))


def _errors(rot, trans, truth):
    """Errors (..., T, 6) of fitted rotations (..., T, 3, 3) and translations (..., T, 3)
    against the true (γ, β, α, t) of each transition."""
    gamma, beta, alpha, _ = decompose_rotation(rot)
    g0, b0, a0, t0 = truth
    return np.stack(
        [gamma - g0, beta - b0, _wrap(alpha - a0), *np.moveaxis(trans - t0, -1, 0)], axis=-1
    )


def _statistics(q_prev, q_next, mask, vectors):
    """Loadings (T, 3, 4, P) of each particle's standard normal on (H columns, mean noise)."""
    n = mask.sum(axis=1).astype(float)
    a_bar = (mask[..., None] * q_prev).sum(1) / n[:, None]
    a_c = np.where(mask[..., None], q_prev - a_bar[:, None, :], 0.0)
    m = np.concatenate([a_c, mask[..., None] / n[:, None, None]], axis=2)  # (T, P, 4)
    loadings = np.einsum("tpk,tpl->tlkp", m, vectors)
    b = np.where(mask[..., None], q_next, 0.0)
    h0 = np.einsum("tpk,tpl->tkl", a_c, b)
    b_bar = b.sum(1) / n[:, None]
    return loadings, h0, a_bar, b_bar


def _simulate_chunk(rng, n_sim, stats, truth):
    """Errors (S, T, 6) of ``n_sim`` simulated fits of every transition."""
    loadings, h0, a_bar, b_bar = stats
    z = rng.standard_normal((loadings.shape[0], loadings.shape[-1], n_sim))
    s = np.einsum("tlkp,tps->tlsk", loadings, z)  # (T, l=3, S, 4)
    h = h0[:, None] + np.transpose(s[..., :3], (0, 2, 3, 1))  # H[k, l] += Σ a_k n_l
    rot = rotations_from_covariance(h).reshape(h.shape)
    trans = b_bar[:, None] + np.swapaxes(s[..., 3], 1, 2) - np.einsum("tsij,tj->tsi", rot, a_bar)
    errors = _errors(rot, trans, tuple(np.asarray(v)[:, None] for v in truth))
    return np.swapaxes(errors, 0, 1)


class _ErrorStats:
    """Streaming statistics of simulated errors (S, T, 6) over chunks of simulations.

    Keeps per-transition sums for the standard deviations, and a log-binned histogram of
    ``|error − mean|`` pooled over transitions for the 68.27 % coverage half-width. The centring
    means come from the first chunk.
    """

    _BINS = 4000
    _DECADES = (-5.0, 3.0)

    def __init__(self, first: np.ndarray):
        self.centre = np.nanmean(first, axis=0)
        spread = np.sqrt(np.nanmean((first - self.centre) ** 2, axis=(0, 1)))
        self.log_scale = np.log10(np.where(spread > 0, spread, 1.0))
        self.total = np.zeros(first.shape[1:])
        self.total_sq = np.zeros(first.shape[1:])
        self.count = np.zeros(first.shape[1:])
        self.hist = np.zeros((first.shape[2], self._BINS + 1))

    def _edges(self, dof: int) -> np.ndarray:
        lo, hi = self._DECADES
        return 10.0 ** (self.log_scale[dof] + np.linspace(lo, hi, self._BINS + 1))

    def add(self, err: np.ndarray) -> None:
        ok = np.isfinite(err)
        zeroed = np.where(ok, err, 0.0)
        self.total += zeroed.sum(0)
        self.total_sq += (zeroed**2).sum(0)
        self.count += ok.sum(0)
        lo, hi = self._DECADES
        step = (hi - lo) / self._BINS
        with np.errstate(divide="ignore", invalid="ignore"):
            level = np.log10(np.abs(err - self.centre)) - self.log_scale
        for dof in range(err.shape[2]):
            values = level[..., dof][ok[..., dof]]
            index = np.clip(np.ceil((values - lo) / step), 0, self._BINS).astype(np.int64)
            self.hist[dof] += np.bincount(index, minlength=self._BINS + 1)

    def std_per_transition(self) -> np.ndarray:
        with np.errstate(invalid="ignore", divide="ignore"):
            variance = (self.total_sq - self.total**2 / self.count) / (self.count - 1)
        return np.sqrt(np.clip(variance, 0.0, None))

    def pooled_std(self) -> np.ndarray:
        return np.sqrt(np.nanmean(self.std_per_transition() ** 2, axis=0))

    def coverage_halfwidth(self, coverage: float = 0.6827) -> np.ndarray:
        """Smallest bin edge below which ``coverage`` of the pooled |error − mean| lies."""
        out = np.empty(self.hist.shape[0])
        for dof, counts in enumerate(self.hist):
            cumulative = np.cumsum(counts)
            k = int(np.searchsorted(cumulative, coverage * cumulative[-1]))
            out[dof] = self._edges(dof)[min(k, self._BINS)]
        return out


def motion_uncertainty(
    tracks: pd.DataFrame,
    motion: pd.DataFrame | None = None,
    *,
    n_sim: int = 10000,
    seed: int = 0,
    per_transition: bool = False,
) -> pd.DataFrame:
    """Standard uncertainty of each degree of freedom by the Monte Carlo of Supp. Note 2.

    Parameters
    ----------
    tracks : DataFrame
        Linked localizations: frame, particle, x_nm, y_nm, z_nm.
    motion : DataFrame, optional
        The measured motion (from :func:`latentz.motion.rigid_motion` on ``tracks``); computed if
        None. Its ``attrs["centre_nm"]`` is used as the centre of rotation when present.
    n_sim : int
        Number of simulations (10,000 in the paper).
    seed : int
        Seed; results are reproducible.
    per_transition : bool
        If True, return the standard deviation of each degree of freedom for each transition
        (columns frame, gamma, beta, alpha, dx_nm, dy_nm, dz_nm) instead of the pooled values.

    Returns
    -------
    DataFrame
        Indexed by degree of freedom (gamma, beta, alpha in rad; dx_nm, dy_nm, dz_nm in nm) with
        columns ``sigma``, the half-width of the 68.27 % coverage interval of the errors pooled
        over transitions (the paper's stated meaning of its uncertainty; to bin precision 0.5 %),
        and ``std``, the pooled standard deviation (root mean over transitions of the variance of
        the errors, the paper's computation). They agree for normal errors; ``std`` is larger
        where errors are heavy-tailed, as α is when β is a few times its own uncertainty.
        ``attrs`` holds ``experimental_rms_nm`` and ``synthetic_rms_nm`` (x, y, z residuals,
        Supp. Table 4), ``extra_variance`` (the relative variance added per axis to match them)
        and ``n_sim``.
    """
    n_sim = check_int("n_sim", n_sim, minimum=2)
    seed = check_int("seed", seed, minimum=0)
    model = _noise_model(tracks, motion, seed)
    chunk = max(1, _CHUNK_MATRICES // model["q_prev"].shape[0])
    starts = range(0, n_sim, chunk)
    stats = _statistics(model["q_prev"], model["q_next"], model["mask"], model["vectors"])
    accumulator = None
    for start, chunk_seed in zip(starts, model["seeds"].spawn(len(starts)), strict=True):
        rng = np.random.default_rng(chunk_seed)
        err = _simulate_chunk(rng, min(chunk, n_sim - start), stats, model["truth"])
        accumulator = accumulator or _ErrorStats(err)
        accumulator.add(err)
    if per_transition:
        table = pd.DataFrame(accumulator.std_per_transition(), columns=list(DOF_COLUMNS))
        table.insert(0, "frame", model["frames"])
    else:
        table = pd.DataFrame(
            {"sigma": accumulator.coverage_halfwidth(), "std": accumulator.pooled_std()},
            index=pd.Index(DOF_COLUMNS, name="dof"),
        )
    table.attrs.update(
        experimental_rms_nm=model["experimental_rms"].tolist(),
        synthetic_rms_nm=model["synthetic_rms"].tolist(),
        extra_variance=(model["scale"] - 1.0).tolist(),
        n_sim=n_sim,
    )
    return table


def _noise_model(tracks: pd.DataFrame, motion: pd.DataFrame | None, seed: int) -> dict:
    """Steps 1, 2 and 4 of the module notes: the replayed (true) positions of every valid
    transition, the per-particle noise scaled to match the experimental residuals, and the seed
    sequence for the simulations."""
    frames, _, pos = tracks_to_array(tracks)
    if frames.size < 2:
        raise ValueError(f"Expected `tracks` to span at least 2 frames, got {frames.size}.")
    centre = motion.attrs.get("centre_nm") if motion is not None else None
    pos = pos - _centre(tracks, centre)
    rot, trans, res, both = _measured_transforms(pos, frames, motion)
    valid = np.isfinite(trans).all(1) & (both.sum(1) >= 3)
    if not valid.any():
        raise ValueError("No transition of `tracks` has 3 or more particles seen in both frames.")
    vectors = _noise_vectors(res, both)[valid]
    synthetic = _replay(pos, rot, trans, valid)
    q_prev, q_next, mask = synthetic[:-1][valid], synthetic[1:][valid], both[valid]
    g0, b0, a0, _ = decompose_rotation(rot[valid])
    pilot_seed, seeds = np.random.SeedSequence(seed).spawn(2)
    pilot_rng = np.random.default_rng(pilot_seed)
    experimental = np.sqrt(np.nanmean(res[both] ** 2, axis=0))
    n_pilot = int(np.clip(_PILOT_RESIDUALS // mask.sum(), 2, 32))
    # The fitted residual variance is linear in the noise variance: one rescaling matches it.
    first = _pilot_rms(q_prev, q_next, mask, vectors, np.ones(3), pilot_rng, n_pilot)
    scale = np.where(first > 0, (experimental / first) ** 2, 1.0)
    return {
        "frames": frames[1:][valid],
        "q_prev": q_prev,
        "q_next": q_next,
        "mask": mask,
        "vectors": vectors * np.sqrt(scale),
        "scale": scale,
        "truth": (g0, b0, a0, trans[valid]),
        "residuals": res[valid],
        "experimental_rms": experimental,
        "synthetic_rms": _pilot_rms(q_prev, q_next, mask, vectors, scale, pilot_rng, n_pilot),
        "seeds": seeds,
    }


def representative_simulation(
    tracks: pd.DataFrame, motion: pd.DataFrame | None = None, *, seed: int = 0
) -> dict[str, pd.DataFrame]:
    """One simulation of :func:`motion_uncertainty`'s Monte Carlo, drawn explicitly (Supp. Fig. 17).

    Returns
    -------
    dict
        ``residuals``: the rigid-fit residuals of the experimental and of the synthetic
        positions, columns ``source`` ("experimental", "synthetic"), ``x_nm``, ``y_nm``,
        ``z_nm``; ``errors``: one row per transition, ``frame`` and the error of each degree of
        freedom (rad, nm) in this simulation.
    """
    seed = check_int("seed", seed, minimum=0)
    model = _noise_model(tracks, motion, seed)
    rng = np.random.default_rng(model["seeds"])
    res, rot, trans = _explicit_fits(
        model["q_prev"], model["q_next"], model["mask"], model["vectors"], rng, 1
    )
    columns = ["x_nm", "y_nm", "z_nm"]
    experimental = model["residuals"][model["mask"]]
    synthetic = res[0][model["mask"]]
    residuals = pd.concat(
        [
            pd.DataFrame(experimental, columns=columns).assign(source="experimental"),
            pd.DataFrame(synthetic, columns=columns).assign(source="synthetic"),
        ],
        ignore_index=True,
    )
    errors = pd.DataFrame(_errors(rot[0], trans[0], model["truth"]), columns=list(DOF_COLUMNS))
    errors.insert(0, "frame", model["frames"])
    return {"residuals": residuals[["source", *columns]], "errors": errors}
