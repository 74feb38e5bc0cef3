"""A simulated movie of isolated emitters (eq. 1 spots + Poisson noise) with ground truth."""

import numpy as np
import pandas as pd

from latentz.fit import amplitude_of, render_rois
from latentz.simulate.molecules import place_edge_molecules

HALF = 10  # spots are rendered into 21 x 21 patches: 5 sd of the widest (2 px) spot


def emitter_movie(
    n_frames, shape, *, seed, spacing=24, background=50.0, photons=(1e3, 1e4), occupancy=0.5
):
    """Emitters on a jittered grid (at least ``spacing - 8`` px apart), in about ``occupancy`` of
    the grid sites per frame: log-uniform photons, wx, wy in [1, 2] px, rho in [-0.5, 0.5].

    Returns the noisy movie (t, H, W) in photoelectrons and the truth table (frame, x, y, ...).
    """
    rng = np.random.default_rng(seed)
    height, width = shape
    start = spacing // 2
    gy, gx = np.mgrid[start : height - start + 1 : spacing, start : width - start + 1 : spacing]
    expected = np.full((n_frames, height, width), float(background))
    truth = []
    for t in range(n_frames):
        on = rng.random(gx.size) < occupancy
        n = int(on.sum())
        x = gx.ravel()[on] + rng.uniform(-4, 4, n)
        y = gy.ravel()[on] + rng.uniform(-4, 4, n)
        table = pd.DataFrame(
            {
                "frame": t,
                "x": x,
                "y": y,
                "photons": np.exp(rng.uniform(*np.log(photons), n)),
                "wx": rng.uniform(1.0, 2.0, n),
                "wy": rng.uniform(1.0, 2.0, n),
                "rho": rng.uniform(-0.5, 0.5, n),
            }
        )
        table["amplitude"] = amplitude_of(table.photons, table.wx, table.wy, table.rho)
        _add_spots(expected[t], table)
        truth.append(table)
    return rng.poisson(expected).astype(np.float64), pd.concat(truth, ignore_index=True)


def _add_spots(expected, table):
    """Add the eq. 1 spots of ``table`` to one frame ``expected`` (H, W), clipped at its edges."""
    height, width = expected.shape
    col, row = np.round(table.x).astype(int), np.round(table.y).astype(int)
    local = table.assign(x=table.x - col + HALF, y=table.y - row + HALF, background=0.0)
    patches = render_rois(local, shape=2 * HALF + 1)
    for k in range(len(table)):
        r0, c0 = row.iloc[k] - HALF, col.iloc[k] - HALF
        rs = slice(max(r0, 0), min(r0 + 2 * HALF + 1, height))
        cs = slice(max(c0, 0), min(c0 + 2 * HALF + 1, width))
        expected[rs, cs] += patches[k, rs.start - r0 : rs.stop - r0, cs.start - c0 : cs.stop - c0]


def edge_movie(n_frames, shape, *, seed, background=30.0, photons=(2e3, 1e4)):
    """Emitters 0–7.5 px from the frame's border and four inside per frame, placed as
    :func:`latentz.simulate.molecules.place_edge_molecules` places molecules (columns
    ``distance_px``, ``across``), as eq. 1 spots as in `emitter_movie`. Returns the noisy movie
    and the truth table."""
    rng = np.random.default_rng(seed)
    placed = place_edge_molecules(rng, n_frames=n_frames, frame_shape=shape, photons=photons)
    n = len(placed)
    truth = placed.assign(
        wx=rng.uniform(1.0, 2.0, n), wy=rng.uniform(1.0, 2.0, n), rho=rng.uniform(-0.5, 0.5, n)
    )
    truth["amplitude"] = amplitude_of(truth.photons, truth.wx, truth.wy, truth.rho)
    expected = np.full((n_frames, *shape), float(background))
    for t, table in truth.groupby("frame"):
        _add_spots(expected[t], table)
    return rng.poisson(expected).astype(np.float64), truth


def match(truth, found, *, radius=2.0):
    """Per frame, pair each true emitter with the nearest detection within ``radius`` px.

    Returns (number of true emitters found, number of detections matched to no emitter).
    """
    from scipy.spatial import cKDTree

    hits = false = 0
    for t, group in found.groupby("frame"):
        true_t = truth[truth.frame == t]
        tree = cKDTree(group[["x", "y"]].to_numpy())
        dist, idx = tree.query(true_t[["x", "y"]].to_numpy(), distance_upper_bound=radius)
        ok = np.isfinite(dist)
        hits += int(ok.sum())
        false += len(group) - len(set(idx[ok]))
    return hits, false
