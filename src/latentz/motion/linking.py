"""Linking 3D localizations into particle tracks across motion cycles (trackpy).

A gear rotating by ~98 mrad per cycle moves particles at its rim by ~15 µm, more than the spacing
of neighbouring particles, so plain nearest-neighbour linking needs a large search range and risks
swaps. With ``predict=True`` each particle's next position is predicted by the rigid transform
of the previous cycle (fitted by Kabsch to the particles linked in the last two frames; for the
first cycle, found by ICP), so the search range only has to cover the play.
"""

from __future__ import annotations

import warnings
from collections import deque

import numpy as np
import pandas as pd
import trackpy
from scipy.spatial.transform import Rotation
from trackpy.predict import NullPredict

from latentz._shared.validate import check_columns, check_int, check_positive
from latentz.motion.rigid import POSITION_COLUMNS, RigidTransform, icp, kabsch

__all__ = ["link"]


class _RigidPredict(NullPredict):
    """trackpy predictor: apply the mean rigid transform of the recent cycles once per elapsed
    frame. Play makes each cycle's transform scatter about the nominal step, so the mean of
    several predicts better than the last one alone."""

    def __init__(self, initial: RigidTransform, span: int):
        self.pos_columns = list(POSITION_COLUMNS)
        self.recent: deque[tuple[np.ndarray, np.ndarray]] = deque(maxlen=span)
        self.recent.append((initial.rotation, initial.translation_nm))
        self.transform = initial
        self.previous: pd.DataFrame | None = None

    def observe(self, frame: pd.DataFrame) -> None:
        current = frame.set_index("particle")[self.pos_columns]
        if self.previous is not None:
            common = self.previous.index.intersection(current.index)
            if common.size >= 3:
                rot, trans = kabsch(
                    self.previous.loc[common].to_numpy(), current.loc[common].to_numpy()
                )
                self.recent.append((rot, trans))
                rotations = np.array([r for r, _ in self.recent])
                mean = Rotation.from_matrix(rotations).mean().as_matrix()
                shift = np.mean([t for _, t in self.recent], axis=0)
                self.transform = RigidTransform(mean, shift)
        self.previous = current

    def predict(self, t1, particles):
        for particle in particles:
            pos = np.asarray(particle.pos, dtype=float)
            for _ in range(max(1, int(round(t1 - particle.t)))):
                pos = self.transform.rotation @ pos + self.transform.translation_nm
            yield pos


def _first_transform(locs: pd.DataFrame, max_distance_nm: float) -> RigidTransform:
    frames = np.unique(locs["frame"])
    cols = list(POSITION_COLUMNS)
    first = locs.loc[locs["frame"] == frames[0], cols].to_numpy(float)
    second = locs.loc[locs["frame"] == frames[1], cols].to_numpy(float)
    if min(len(first), len(second)) < 3:
        return RigidTransform(np.eye(3), np.zeros(3))
    result = icp(first, second, max_distance_nm=max_distance_nm)
    return result.transform if result else RigidTransform(np.eye(3), np.zeros(3))


def link(
    locs: pd.DataFrame,
    *,
    search_range_nm: float,
    memory: int = 0,
    predict: bool = False,
    first_cycle_range_nm: float | None = None,
) -> pd.DataFrame:
    """Link localizations into tracks; adds an integer column ``particle``.

    Parameters
    ----------
    locs : DataFrame
        frame, x_nm, y_nm, z_nm (and any other columns, kept).
    search_range_nm : float
        Largest distance a particle may move between frames (or, with ``predict``, from its
        predicted position).
    memory : int
        Number of frames a particle may be missed and still keep its identity.
    predict : bool
        Predict positions by the previous cycle's rigid transform (for large rotations per cycle).
    first_cycle_range_nm : float, optional
        With ``predict``, the largest displacement in the first cycle, where no transform is known
        yet and ICP finds it (default: ``20 × search_range_nm``).

    Returns
    -------
    DataFrame
        A copy of ``locs`` sorted by frame with the ``particle`` column.
    """
    check_columns("locs", locs, ("frame", *POSITION_COLUMNS))
    search = check_positive("search_range_nm", search_range_nm)
    memory = check_int("memory", memory, minimum=0)
    if len(locs) == 0:
        raise ValueError("Expected `locs` to hold at least one localization, got 0 rows.")
    if not np.isfinite(locs[list(POSITION_COLUMNS)].to_numpy(float)).all():
        raise ValueError("`locs` has non-finite positions in x_nm, y_nm or z_nm.")
    table = locs.drop(columns="particle", errors="ignore").sort_values("frame", kind="stable")
    table = table.reset_index(drop=True)
    options = {"memory": memory, "pos_columns": list(POSITION_COLUMNS), "t_column": "frame"}
    trackpy.quiet()
    if not predict or table["frame"].nunique() < 2:
        with warnings.catch_warnings():  # trackpy's own use of a deprecated pandas keyword
            warnings.filterwarnings("ignore", message="The inplace keyword", module="trackpy")
            linked = trackpy.link(table, search, **options)
    else:
        first_range = check_positive(
            "first_cycle_range_nm",
            20.0 * search if first_cycle_range_nm is None else first_cycle_range_nm,
        )
        predictor = _RigidPredict(_first_transform(table, first_range), span=8)
        linked = predictor.link_df(table, search, **options)
    linked = linked.sort_values(["frame", "particle"], kind="stable").reset_index(drop=True)
    linked["particle"] = linked["particle"].astype(np.int64)
    return linked
