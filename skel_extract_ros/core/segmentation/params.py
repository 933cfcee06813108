"""Parameters and per-frame result of the subject segmentation."""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

STATUS_SUBJECT = 'subject'
STATUS_NOBODY = 'nobody'
STATUS_OFF = 'off'


@dataclass
class SegmentationParams:
    """Subject segmentation parameters.

    enabled: find the subject (default); off = every valid point is the subject.
    noise_sigmas: a depth change or a distance to a plane counts when it exceeds this many
        measured noise deviations.
    min_noise_c: floor of the noise coefficient c in sigma(r) = c r^2 (1/m); 0.001 is 9 mm
        at 3 m, below what consumer depth cameras reach.
    motion_lag: frames between the depths compared for motion (slow motion adds up).
    motion_memory: frames over which motion evidence fades (60 = 2 s at 30 Hz).
    max_planes: planes (floor, walls, table tops) removed at most.
    min_plane_extent: m; a plane smaller than this in either direction is kept (it may be
        the subject's torso or back).
    plane_refresh: frames between plane fits (planes of a still camera do not change).
    attach_distance: m; a moving region this close to the subject in 3-D is part of it.
    min_subject_points: a subject region smaller than this (pixels of the working grid,
        points of an unorganized cloud) is nobody.
    max_pixels: the organized analysis (motion, planes, regions) runs on a working grid of
        at most this many pixels, every k-th row and column (a 640x480 camera works at
        320x240 with the default); the subject's pixels at full resolution are then those
        of its grid cells (and the cells beside it) within a depth jump of it and off the
        planes. The cost per frame follows the grid, not the camera.
    seed: RANSAC seed.
    """

    enabled: bool = True
    noise_sigmas: float = 3.0
    min_noise_c: float = 0.001
    motion_lag: int = 3
    motion_memory: int = 60
    max_planes: int = 4
    min_plane_extent: float = 0.8
    plane_refresh: int = 30
    attach_distance: float = 0.15
    min_subject_points: int = 200
    max_pixels: int = 320 * 240
    seed: int = 0

    def __post_init__(self):
        checks = {'noise_sigmas': self.noise_sigmas > 0, 'min_noise_c': self.min_noise_c > 0,
                  'motion_lag': self.motion_lag >= 1, 'motion_memory': self.motion_memory >= 1,
                  'max_planes': self.max_planes >= 0, 'min_plane_extent': self.min_plane_extent > 0,
                  'plane_refresh': self.plane_refresh >= 1, 'attach_distance': self.attach_distance >= 0,
                  'min_subject_points': self.min_subject_points >= 1, 'max_pixels': self.max_pixels >= 1000}
        bad = [name for name, ok in checks.items() if not ok]
        if bad:
            raise ValueError('segmentation parameter(s) out of range: '
                             + ', '.join(f'{n}={getattr(self, n)}' for n in bad))


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
