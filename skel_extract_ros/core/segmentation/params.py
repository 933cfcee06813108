"""Parameters and per-frame result of the subject segmentation."""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..parameters import parameter, validate

STATUS_SUBJECT = 'subject'
STATUS_NOBODY = 'nobody'
STATUS_OFF = 'off'


@dataclass
class SegmentationParams:
    """Subject segmentation parameters. The organized analysis (motion, planes, regions)
    runs on a working grid of at most max_pixels pixels; the subject's pixels at full
    resolution are then those of its grid cells (and the cells beside it) within a depth
    jump of it and off the planes, so the cost per frame follows the grid, not the camera."""

    enabled: bool = parameter(True, 'find the subject (the connected region that moves) and drop the room; '
                              'false = every valid point is the subject')
    noise_sigmas: float = parameter(3.0, 'a depth change or a distance to a plane counts beyond this many '
                                    'standard deviations of the depth noise estimated from the images', 0.5, 100.0)
    min_noise_c: float = parameter(0.001, 'floor of the depth noise coefficient c in sigma = c r^2, 1/m '
                                   '(0.001: 9 mm at 3 m)', 1e-6, 1.0)
    motion_lag: int = parameter(3, 'frames between the depth images compared for motion (slow motion adds up)',
                                1, 1000)
    motion_memory: int = parameter(60, 'frames over which motion evidence fades', 1, 100_000)
    max_planes: int = parameter(4, 'planes (floor, walls, table tops) removed at most', 0, 20)
    min_plane_extent: float = parameter(0.8, 'a plane smaller than this in either direction is kept (it may be '
                                        "the subject's torso or back), m", 0.01, 100.0)
    plane_refresh: int = parameter(30, 'frames between plane fits', 1, 100_000)
    attach_distance: float = parameter(0.15, 'a moving region this close to the subject in 3-D is part of it, m',
                                       0.0, 10.0)
    min_subject_points: int = parameter(200, 'a smaller subject is nobody, pixels of the working grid (points '
                                        'of an unorganized cloud)', 1, 10_000_000)
    max_pixels: int = parameter(320 * 240, 'pixels of the working grid at most: motion, planes and regions are '
                                'found on every k-th row and column of larger images (640x480 at 320x240), the '
                                'subject kept at full resolution; lower it on a slow machine (fewer frames find '
                                'a small subject)', 1000, 100_000_000)
    seed: int = parameter(0, 'RANSAC seed (repeatable plane fits)', 0, 2**31 - 1)

    def __post_init__(self):
        validate(self)


@dataclass
class Segmentation:
    """The subject in one frame.

    mask: (N,) bool over the input points (row-major pixels for organized clouds).
    status: 'subject', 'nobody' (no region has moved, or the subject left) or 'off'.
    n_moving_regions: separate moving regions seen (2 = two people: the one that moves most
        is followed). touches_border: the subject reaches the image border (partly in view).
    background_fraction: share of the valid points that are not the subject.
    """

    mask: np.ndarray
    status: str
    n_valid: int
    n_moving_regions: int = 0
    touches_border: bool = False
    noise_c: float = float('nan')
    n_planes: int = 0
    n_subject: int = -1

    def __post_init__(self):
        if self.n_subject < 0:
            self.n_subject = int(self.mask.sum())

    @property
    def background_fraction(self) -> float:
        return 1.0 - self.n_subject / self.n_valid if self.n_valid else 0.0

    def summary(self) -> 'Segmentation':
        """The same without the mask (for keeping one per frame of a long sequence)."""
        return Segmentation(np.empty(0, dtype=bool), self.status, self.n_valid, self.n_moving_regions,
                            self.touches_border, self.noise_c, self.n_planes, self.n_subject)
