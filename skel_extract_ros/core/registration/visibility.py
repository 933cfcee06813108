"""What the camera saw of a frame, ray by ray: which model points it could have seen
(self-occlusion, the back of a turned body) and which lie where it saw nothing (outside the
subject's silhouette)."""
from __future__ import annotations

import numpy as np
from scipy.spatial import cKDTree

# a point is outside the silhouette when no observed ray passes within this many ray
# spacings of its own: the segmentation and the sensor's edge filtering can take a pixel or
# two off a limb's rim, which should not pull the model's rim inwards
SILHOUETTE_SPACINGS = 3.0
# rays the ray spacing (a median) is measured on at most
RAY_SPACING_SAMPLES = 500


def _rays(points: np.ndarray) -> tuple:
    """(ranges (M,) m, unit directions (M, 3)) of points (M, 3) m from the camera."""
    ranges = np.linalg.norm(points, axis=1)
    return ranges, points / np.maximum(ranges, 1e-9)[:, None]


class ObservedView:
    """What the camera saw of one frame, as directions and ranges from the camera (the
    origin of the cloud frame), to tell which model points it could have seen and which lie
    outside the subject's silhouette.

    A model point is hidden when an observation lies on (nearly) the same ray and is
    closer to the camera by more than `margin`: the surface there is in front of it. That
    covers self-occlusion (the torso behind an arm) and the back of a turned body (behind
    its front) alike. Rays are compared on the unit sphere (k-d tree over the observed
    directions), so any camera orientation works.

    observed: (N, 3) metres.
    """

    def __init__(self, observed: np.ndarray):
        self.ranges, self.directions = _rays(observed)
        self.tree = cKDTree(self.directions)
        # the angular pixel footprint: how far apart neighbouring rays are (a median: a
        # strided subset of the rays gives it as well as all of them, in a fraction of the time)
        sample = self.directions[::max(1, len(self.directions) // RAY_SPACING_SAMPLES)]
        self.ray_spacing = float(np.median(self.tree.query(sample, k=2)[0][:, 1]))

    def visible(self, points: np.ndarray, margin: float) -> np.ndarray:
        """(M,) bool: no observation within 1.5 ray spacings of the point's ray is more
        than `margin` (m) nearer the camera. points (M, 3)."""
        ranges, directions = _rays(points)
        _, nearest = self.tree.query(directions, k=4, distance_upper_bound=1.5 * self.ray_spacing)
        found = nearest < len(self.ranges)
        in_front = np.where(found, self.ranges[np.where(found, nearest, 0)], np.inf)
        return (in_front.min(axis=1) >= ranges - margin)

    def _nearest_ray(self, points: np.ndarray) -> tuple:
        """(ranges (M,) m, angles (M,) rad to the nearest observed ray, its index (M,)) of
        points (M, 3) m."""
        ranges, directions = _rays(points)
        # chord between unit vectors: the angle (rad) for the small angles that matter here
        angle, nearest = self.tree.query(directions)
        return ranges, angle, nearest

    def outside(self, points: np.ndarray) -> np.ndarray:
        """(M,) bool: no observed ray passes within SILHOUETTE_SPACINGS ray spacings of the
        ray of each point (M, 3) m: the camera saw nothing there."""
        return self._nearest_ray(points)[1] > SILHOUETTE_SPACINGS * self.ray_spacing

    def silhouette_targets(self, points: np.ndarray, reach: float) -> tuple:
        """Where the silhouette term (RegistrationParams.free_space) pulls points (M, 3) m:
        (outside (M,) bool, targets (M, 3) m). A point is outside when no observed ray passes
        within SILHOUETTE_SPACINGS ray spacings of its ray while one passes within `reach`
        (m) of the point itself, across its ray (farther ones are a lost part's, which the
        nearest ray would hand to whatever limb is next to it); its target lies on the
        nearest observed ray, at the point's own range."""
        ranges, angle, nearest = self._nearest_ray(points)
        outside = (angle > SILHOUETTE_SPACINGS * self.ray_spacing) & (angle * ranges <= reach)
        return outside, self.directions[nearest] * ranges[:, None]
