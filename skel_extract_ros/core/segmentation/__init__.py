"""Finding the subject in a depth camera's view of a room: the connected region that moves.

A camera in a room sees floors, walls, tables and still objects beside the subject. Per
frame (organized clouds, the common case of a still depth camera):

1. **Planes** (floor, walls, large table tops) are found by RANSAC (core/point_sets.py) on a
   subsample of the pixels that have not moved recently, refreshed every `plane_refresh`
   frames, and kept only if they extend at least `min_plane_extent` in both directions (a
   torso is a plane too, but a small one). A pixel is on a plane when its depth along its
   own ray is within `noise_sigmas` noise deviations of the plane's: at grazing angles (the
   floor near the feet) a perpendicular distance would eat the feet.
2. **Regions**: the remaining pixels are split at depth jumps into connected regions
   (scipy.ndimage.label), so the subject is apart from the wall behind it.
3. **Motion** is the evidence: a pixel moved when its depth changed by more than
   `noise_sigmas` noise deviations since `motion_lag` frames ago (appearing and vanishing
   count); isolated flickers are opened away and the evidence fades over `motion_memory`
   frames. The subject is the region with the most motion evidence; it stays the subject
   while it pauses (regions overlapping the last subject mask keep it), parts split off by
   self-occlusion (a forearm in front of the torso) are joined when they are within
   `attach_distance` in 3-D, a still object never moves and never becomes the subject, and a
   second moving region is reported (`n_moving_regions`) but not followed.

Images larger than `max_pixels` (a 640x480 camera) go through these steps on every k-th row
and column; the subject then comes back at full resolution: the pixels of its cells and of
the cells beside them that lie within its depths and off the planes. The cost per frame
follows the working grid, not the camera.

The noise is measured on the sequence itself: the depth deviation sigma(r) = c r^2 (r the
range, as for structured-light and time-of-flight cameras) with c from the ray residuals of
the largest plane, else from frame-to-frame differences, never below `min_noise_c`.

Unorganized clouds (no pixel grid) take the same steps on a voxel grid: planes by RANSAC,
regions by DBSCAN (Open3D), motion by nearest-neighbour distance to the previous frame.

No rclpy here: `skel-extract run`, `replay` and the nodes all use `SubjectSegmenter`.

The module per part: `params` (SegmentationParams, Segmentation), `background` (noise and
planes), `organized` (the pixel grid), `unorganized` (voxel grid); SubjectSegmenter, here,
holds the state and dispatches.
"""
from __future__ import annotations

import numpy as np

from ..point_sets import finite_rows
from .background import BackgroundModel
from .organized import OrganizedSegmentation
from .params import STATUS_NOBODY, STATUS_OFF, STATUS_SUBJECT, Segmentation, SegmentationParams
from .unorganized import UnorganizedSegmentation

__all__ = ['STATUS_NOBODY', 'STATUS_OFF', 'STATUS_SUBJECT', 'Segmentation', 'SegmentationParams',
           'SubjectSegmenter']


class SubjectSegmenter(OrganizedSegmentation, UnorganizedSegmentation, BackgroundModel):
    """Stateful per-frame subject segmentation (see the module docstring).

    >>> segmenter = SubjectSegmenter()
    >>> result = segmenter(points, height, width)     # (H*W, 3) organized or (N, 3), NaN allowed
    >>> subject = points[result.mask]
    """

    def __init__(self, params: SegmentationParams | None = None):
        self.params = params or SegmentationParams()
        self.reset()

    def reset(self) -> None:
        """Forget the background: planes, motion evidence, the subject (a moved camera)."""
        self._planes = []                  # list of (normal (3,), offset d): n.p + d = 0
        self._frames_since_planes = None
        self._history = None               # (H, W) motion evidence in [0, 1]
        self._ranges = []                  # last motion_lag + 1 range images
        self._subject = None               # (H, W) bool last subject mask
        self._shape = None
        self.noise_c = None
        self._previous_points = None       # unorganized: last frame's subsampled points
        self._previous_subject = None

    # ------------------------------------------------------------------------------------
    def __call__(self, points: np.ndarray, height: int = 1, width: int | None = None) -> Segmentation:
        points = np.asarray(points)
        if points.dtype not in (np.float32, np.float64):
            points = points.astype(np.float64)
        valid = finite_rows(points)
        if not self.params.enabled:
            return Segmentation(valid, STATUS_OFF, int(valid.sum()))
        width = len(points) if width is None else int(width)
        if height > 1 and height * width == len(points):
            grid, grid_valid = points.reshape(height, width, 3), valid.reshape(height, width)
            step = int(np.ceil(np.sqrt(height * width / self.params.max_pixels)))
            if step == 1:
                return self._organized(grid.astype(np.float64, copy=False), grid_valid)
            # a large image: the working grid (a copy, in float64), then its subject at full size
            coarse = self._organized(grid[::step, ::step].astype(np.float64), grid_valid[::step, ::step])
            return self._full_resolution(coarse, grid, grid_valid, step)
        return self._unorganized(points.astype(np.float64, copy=False), valid)
