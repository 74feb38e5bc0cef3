"""ICP where linking leaves a cycle ambiguous: the body slips farther than the linker's search
range in one cycle, some particles are missed and spurious spots appear."""

import numpy as np
import pandas as pd
import pytest

from latentz.cli.steps import track_tables
from latentz.motion.linking import link
from latentz.motion.rigid import resolve_by_icp, rigid_motion
from latentz.simulate.gear_motion import gear_trajectory

SLIP_FRAME = 6
SEARCH_NM = 5000.0


def _slipping_detections(seed=1):
    """Gear particles with 2 nm lateral and 80 nm axial noise, 5 % missed; from SLIP_FRAME on the
    whole body is displaced by 9 µm (beyond the 5 µm search range plus the ~1 µm play), and 3
    spurious spots (truth −1) appear in the slip frame."""
    rng = np.random.default_rng(seed)
    locs = gear_trajectory(12, seed=3).positions.copy()
    locs[["x_nm", "y_nm"]] += rng.normal(0.0, 2.0, (len(locs), 2))
    locs["z_nm"] += rng.normal(0.0, 80.0, len(locs))
    locs.loc[locs["frame"] >= SLIP_FRAME, "x_nm"] += 9000.0
    locs = locs[rng.random(len(locs)) >= 0.05].rename(columns={"particle": "truth"})
    spurious = locs[locs["frame"] == SLIP_FRAME].sample(3, random_state=seed).copy()
    spurious[["x_nm", "y_nm"]] += rng.uniform(-60_000.0, 60_000.0, (3, 2))
    spurious["truth"] = -1
    return locs, pd.concat([locs, spurious], ignore_index=True)


def test_icp_recovers_the_cycle_that_linking_loses():
    truth_locs, locs = _slipping_detections()
    linked = rigid_motion(
        link(locs.drop(columns="truth"), search_range_nm=SEARCH_NM, memory=3, predict=True)
    )
    # the reference: Kabsch on the true identities (no linking, no spurious spot), same centre
    direct = rigid_motion(
        truth_locs.rename(columns={"truth": "particle"}), centre_nm=linked.attrs["centre_nm"]
    )
    slip = int(np.flatnonzero(linked["frame"].to_numpy() == SLIP_FRAME)[0])
    # linking alone loses the slip: fewer than 3 particles linked across it, no motion
    assert linked["n_particles"].iloc[slip] < 3 and np.isnan(linked["gamma"].iloc[slip])

    resolved = resolve_by_icp(linked, locs, max_distance_nm=SEARCH_NM)
    assert resolved["method"].iloc[slip] == "icp"
    # ICP matched every particle seen in both frames (no spurious spot): the same fit as Kabsch
    # on the true identities, to rounding
    assert resolved["n_particles"].iloc[slip] == direct["n_particles"].iloc[slip]
    for column in ("gamma", "beta", "dx_nm", "dy_nm", "dz_nm"):
        np.testing.assert_allclose(
            resolved[column].iloc[slip], direct[column].iloc[slip], rtol=1e-9, atol=1e-6
        )
    # the cycles linking resolved are left as they were
    others = resolved["method"] == "kabsch"
    np.testing.assert_allclose(resolved.loc[others, "gamma"], linked.loc[others, "gamma"])


def test_the_track_pipeline_uses_icp_for_the_lost_cycle():
    truth_locs, locs = _slipping_detections()
    direct = rigid_motion(truth_locs.rename(columns={"truth": "particle"}))
    tables = track_tables(
        locs.drop(columns="truth").assign(in_range=True), search_range_nm=SEARCH_NM, n_sim=50
    )
    motion = tables["motion"].set_index("frame")
    assert motion.loc[SLIP_FRAME, "method"] == "icp"
    assert np.isfinite(motion["gamma"]).all()
    # gamma does not depend on the centre of rotation. The slip frame also swaps a spurious spot
    # into a track in the next cycle; ICP drops it (and one true pair with it), so that cycle
    # agrees with the true-identity fit within gamma's precision, 2 nm / (100 µm × √24) ≈ 4e-6
    # rad, and every other cycle to rounding
    assert (motion.loc[SLIP_FRAME + 1, "method"], motion.loc[SLIP_FRAME + 1, "rms_x_nm"]) == (
        "icp",
        pytest.approx(2.5, abs=1.0),
    )
    np.testing.assert_allclose(motion["gamma"], direct.set_index("frame")["gamma"], atol=2e-5)
    same = motion.index != SLIP_FRAME + 1
    np.testing.assert_allclose(
        motion.loc[same, "gamma"], direct.set_index("frame").loc[same, "gamma"], atol=1e-9
    )


def test_resolve_refuses_a_table_without_its_centre():
    _, locs = _slipping_detections()
    linked = rigid_motion(link(locs.drop(columns="truth"), search_range_nm=SEARCH_NM))
    linked.attrs.clear()
    with pytest.raises(ValueError, match="centre_nm"):
        resolve_by_icp(linked, locs, max_distance_nm=SEARCH_NM)
