"""Which model points the camera could have seen in a frame (self-occlusion, the back of a
turned body): the E-step's view of the frame."""
from __future__ import annotations

import numpy as np
from scipy.spatial import cKDTree


class ObservedView:
    """What the camera saw of one frame, as directions and ranges from the camera (the
    origin of the cloud frame), to tell which model points it could have seen.

    A model point is hidden when an observation lies on (nearly) the same ray and is
    closer to the camera by more than `margin`: the surface there is in front of it. That
    covers self-occlusion (the torso behind an arm) and the back of a turned body (behind
    its front) alike. Rays are compared on the unit sphere (k-d tree over the observed
    directions), so any camera orientation works.

    observed: (N, 3) metres.
    """

    def __init__(self, observed: np.ndarray):
        ranges = np.linalg.norm(observed, axis=1)
        self.ranges = ranges
        directions = observed / np.maximum(ranges, 1e-9)[:, None]
        self.tree = cKDTree(directions)
        # the angular pixel footprint: how far apart neighbouring rays are
        self.ray_spacing = float(np.median(self.tree.query(directions, k=2)[0][:, 1]))

    def visible(self, points: np.ndarray, margin: float) -> np.ndarray:
        """(M,) bool: no observation within 1.5 ray spacings of the point's ray is more
        than `margin` (m) nearer the camera. points (M, 3)."""
        ranges = np.linalg.norm(points, axis=1)
        _, nearest = self.tree.query(points / np.maximum(ranges, 1e-9)[:, None], k=4,
                                     distance_upper_bound=1.5 * self.ray_spacing)
        found = nearest < len(self.ranges)
        in_front = np.where(found, self.ranges[np.where(found, nearest, 0)], np.inf)
        return (in_front.min(axis=1) >= ranges - margin)
