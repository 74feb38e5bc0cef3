"""A simulated movie of isolated emitters (eq. 1 spots + Poisson noise) with ground truth."""

import numpy as np
import pandas as pd

from latentz.fit import amplitude_of, render_rois

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
        col, row = np.round(x).astype(int), np.round(y).astype(int)
        local = table.assign(x=x - col + HALF, y=y - row + HALF, background=0.0)
        patches = render_rois(local, shape=2 * HALF + 1)
        for k in range(n):
            r0, c0 = row[k] - HALF, col[k] - HALF
            rs = slice(max(r0, 0), min(r0 + 2 * HALF + 1, height))
            cs = slice(max(c0, 0), min(c0 + 2 * HALF + 1, width))
            expected[t, rs, cs] += patches[
                k, rs.start - r0 : rs.stop - r0, cs.start - c0 : cs.stop - c0
            ]
        truth.append(table)
    return rng.poisson(expected).astype(np.float64), pd.concat(truth, ignore_index=True)


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
