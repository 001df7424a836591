"""Starting points for the nonlinear loop: the given values, or a global initialization.

"chordal": rotations by chordal relaxation, then translations by linear least squares
(``initialization.chordal``), the field's standard start for pose graphs (Carlone et al. 2015);
the anchor is the pose of a prior (kept where it is) or the first pose.
"""

from __future__ import annotations

import numpy as np

from ..initialization.chordal import chordal_initialization

INITIALIZATIONS = ("file", "chordal")


def chordal_state(linearizer, state, solver: str = "direct"):
    """The chordal initialization of a pure pose graph as a new linearizer state (None if the
    linearizer cannot describe its graph as one, e.g. with landmarks)."""
    graph = linearizer.pose_graph() if hasattr(linearizer, "pose_graph") else None
    if graph is None or graph["between"] is None:
        return None, "not a pure Pose2/Pose3 graph: initialization skipped"
    b, prior = graph["between"], graph["prior"]
    if prior is not None and len(prior["j"]):
        anchor, anchor_pose = int(prior["j"][0]), (prior["R"][0], prior["t"][0])
    else:
        anchor, anchor_pose = 0, None
    result = chordal_initialization(graph["n"], np.column_stack([b["i"], b["j"]]), b["R"], b["t"], b["information"],
                                    anchor=anchor, anchor_pose=anchor_pose, solver=solver)
    if anchor_pose is None:  # no prior: keep the first pose where the given values have it
        geometry = linearizer.geometry(state)
        if geometry is not None:
            R0, p0 = geometry.rotations[0], geometry.positions[0]
            result.rotations[:] = R0 @ result.rotations
            result.positions[:] = (result.positions @ R0.T) + p0
    new = linearizer.with_poses(state, result.rotations, result.positions)
    info = result.info
    iterations = info.get("rotation_iterations", []) + info.get("translation_iterations", [])
    how = f"CG, {sum(iterations)} iterations" if solver == "cg" else "direct"
    return new, f"chordal: {info['seconds']:.2f} s ({how})"
