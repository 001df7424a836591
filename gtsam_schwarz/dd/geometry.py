"""Where the vertices are: positions and rotations of the poses at the linearization point."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True)
class VertexGeometry:
    """Variable positions and rotations at the linearization point (Pose2: d = 2, Pose3: d = 3),
    used for the rigid-body modes of the coarse space."""

    positions: np.ndarray  # (n_vertices, d)
    rotations: np.ndarray  # (n_vertices, d, d), world-from-body

    @property
    def d(self) -> int:
        return self.positions.shape[1]
