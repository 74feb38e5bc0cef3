"""Rigid-body tracking in six degrees of freedom (paper eqs. 7–14, Table 1, Supp. Note 2).

Link localizations into tracks, fit rigid transforms between motion cycles, decompose them into
γ, β, α and Δx, Δy, Δz about the centre of rotation, evaluate their uncertainty by Monte Carlo,
and analyse play, flexure and drift.
"""

from latentz.motion._axis_angle import decompose_rotation
from latentz.motion.analyses import (
    OutOfPlanePlay,
    centroid_trajectory,
    nominal_orientation,
    out_of_plane_play,
    peak_period,
    planar_residuals,
    play,
    residual_correlation,
    residual_spectrum,
)
from latentz.motion.figures import (
    figure_centroid,
    figure_flexure,
    figure_monte_carlo,
    figure_motion,
    figure_out_of_plane_play,
    figure_play,
    figure_residuals,
    motion_figures,
    save_figure,
)
from latentz.motion.linking import link
from latentz.motion.rigid import (
    IcpResult,
    RigidTransform,
    icp,
    icp_motion,
    kabsch,
    resolve_by_icp,
    rigid_motion,
    rigid_residuals,
    rotation_from_angles,
)
from latentz.motion.summary import drift, table1
from latentz.motion.uncertainty import motion_uncertainty, representative_simulation

__all__ = [
    "IcpResult",
    "OutOfPlanePlay",
    "RigidTransform",
    "centroid_trajectory",
    "decompose_rotation",
    "drift",
    "figure_centroid",
    "figure_flexure",
    "figure_monte_carlo",
    "figure_motion",
    "figure_out_of_plane_play",
    "figure_play",
    "figure_residuals",
    "icp",
    "icp_motion",
    "kabsch",
    "resolve_by_icp",
    "link",
    "motion_figures",
    "motion_uncertainty",
    "nominal_orientation",
    "out_of_plane_play",
    "peak_period",
    "planar_residuals",
    "play",
    "residual_correlation",
    "representative_simulation",
    "residual_spectrum",
    "rigid_motion",
    "rigid_residuals",
    "rotation_from_angles",
    "save_figure",
    "table1",
]
