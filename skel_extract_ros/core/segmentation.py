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
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy import ndimage
from scipy.spatial import cKDTree

from .point_sets import finite_rows, ransac_plane, voxel_centroids

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


def _opening3x3(mask: np.ndarray) -> np.ndarray:
    """ndimage.binary_opening(mask (H, W) bool, np.ones((3, 3))), outside the image False:
    the erosion and the dilation each as two separable passes of shifted ANDs / ORs of
    the boolean image. The same pixels as scipy's filters at a small part of their cost:
    this runs for every camera frame."""
    rows = np.zeros_like(mask)
    rows[:, 1:-1] = mask[:, :-2] & mask[:, 1:-1] & mask[:, 2:]
    eroded = np.zeros_like(mask)
    eroded[1:-1] = rows[:-2] & rows[1:-1] & rows[2:]
    columns = eroded.copy()
    columns[:, 1:] |= eroded[:, :-1]
    columns[:, :-1] |= eroded[:, 1:]
    opened = columns.copy()
    opened[1:] |= columns[:-1]
    opened[:-1] |= columns[1:]
    return opened


def _plane_depth(points: np.ndarray, normal: np.ndarray, offset: float) -> np.ndarray:
    """(...) depth z at which each point's camera ray (through the origin) meets the plane
    normal . p + offset = 0; inf where the ray runs along the plane."""
    with np.errstate(invalid='ignore', divide='ignore'):
        return -offset * points[..., 2] / (points @ normal)


class SubjectSegmenter:
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

    def _full_resolution(self, coarse: Segmentation, points: np.ndarray, valid: np.ndarray,
                         step: int) -> Segmentation:
        """The working grid's subject (every `step`-th pixel of `points` (H, W, 3)) at full
        resolution: a pixel of a subject cell or of a cell beside one is the subject's when
        its depth lies within the neighbourhood's subject depths (widened by the grid's
        depth-jump threshold) and it is off every plane. Only the subject's bounding box
        is visited: the cost follows the subject, not the camera."""
        n_valid = int(valid.sum())
        mask = np.zeros(valid.shape, dtype=bool)
        if coarse.status != STATUS_SUBJECT:
            return Segmentation(mask.reshape(-1), coarse.status, n_valid, coarse.n_moving_regions,
                                coarse.touches_border, coarse.noise_c, coarse.n_planes)
        small = coarse.mask.reshape(self._shape)
        depth = points[::step, ::step, 2]
        # the working grid's depth-jump threshold between neighbouring cells (see _organized)
        jump = np.maximum(self.params.noise_sigmas * 2.0 * coarse.noise_c * depth ** 2,
                          8.0 * depth / max(self._shape))
        with np.errstate(invalid='ignore'):
            near = ndimage.minimum_filter(np.where(small, depth - jump, np.inf), size=3)
            far = ndimage.maximum_filter(np.where(small, depth + jump, -np.inf), size=3)
        rows, cols = np.flatnonzero(np.isfinite(near).any(axis=1)), np.flatnonzero(np.isfinite(near).any(axis=0))
        box = (slice(rows[0], rows[-1] + 1), slice(cols[0], cols[-1] + 1))
        full_box = (slice(rows[0] * step, min((rows[-1] + 1) * step, valid.shape[0])),
                    slice(cols[0] * step, min((cols[-1] + 1) * step, valid.shape[1])))
        shape = (full_box[0].stop - full_box[0].start, full_box[1].stop - full_box[1].start)
        def upsampled(cells):
            return np.repeat(np.repeat(cells[box], step, axis=0), step, axis=1)[:shape[0], :shape[1]]
        box_points = points[full_box].astype(np.float64)
        z = box_points[..., 2]
        with np.errstate(invalid='ignore'):
            inside = valid[full_box] & (z >= upsampled(near)) & (z <= upsampled(far))
        candidates = box_points[inside]
        on_plane = self._on_planes(candidates, coarse.noise_c * candidates[:, 2] ** 2)
        inside[inside] = ~on_plane
        mask[full_box] = inside
        return Segmentation(mask.reshape(-1), STATUS_SUBJECT, n_valid, coarse.n_moving_regions,
                            coarse.touches_border, coarse.noise_c, coarse.n_planes)

    # -- noise ---------------------------------------------------------------------------
    def _update_noise(self, estimate: float | None) -> float:
        p = self.params
        if estimate is not None and np.isfinite(estimate) and estimate > 0:
            # Slow average: one frame of a walking subject must not change the noise model.
            self.noise_c = estimate if self.noise_c is None else 0.9 * self.noise_c + 0.1 * estimate
        return max(self.noise_c if self.noise_c is not None else p.min_noise_c, p.min_noise_c)

    # -- planes --------------------------------------------------------------------------
    def _fit_planes(self, points: np.ndarray, pixels: np.ndarray | None = None,
                    shape: tuple | None = None, max_planes: int | None = None,
                    min_inliers: int | None = None) -> tuple:
        """Planes (normal, d) of `points` (K, 3) extending min_plane_extent both ways, and the
        noise coefficient from the largest one's ray residuals (None if no plane). With the
        points' pixels (K, 2: row, column) in an image of `shape`, a plane must also reach
        the image border: floors and walls run out of view, a still subject's flank (a
        cow's side is a 2 x 1 m plane) lies inside it."""
        p = self.params
        planes, noise = [], None
        remaining = points
        remaining_pixels = pixels
        for _ in range(p.max_planes if max_planes is None else max_planes):
            if len(remaining) < 500:
                break
            threshold = 3.0 * max(self.noise_c or p.min_noise_c, p.min_noise_c) * float(np.median(
                np.linalg.norm(remaining, axis=1))) ** 2
            plane = ransac_plane(remaining, max(threshold, 0.005), 300, np.random.default_rng(p.seed + len(planes)))
            if plane is None or len(plane[2]) < (0.05 * len(points) if min_inliers is None else min_inliers):
                break
            normal, d, inliers = plane
            on = remaining[inliers]
            # extent in the plane: spread along its two in-plane principal directions
            centred = on - on.mean(axis=0)
            _, _, axes = np.linalg.svd(centred[:: max(1, len(on) // 2000)], full_matrices=False)
            spread = np.ptp(centred @ axes[:2].T, axis=0)
            remaining = np.delete(remaining, inliers, axis=0)
            if pixels is not None:
                rows, cols = remaining_pixels[inliers, 0], remaining_pixels[inliers, 1]
                remaining_pixels = np.delete(remaining_pixels, inliers, axis=0)
            if spread.min() < p.min_plane_extent:
                continue
            if pixels is not None:
                margin = 2
                if (rows.min() > margin and cols.min() > margin and rows.max() < shape[0] - 1 - margin
                        and cols.max() < shape[1] - 1 - margin):
                    continue
            planes.append((normal, d))
            if noise is None:
                depth = on[:, 2]
                along = _plane_depth(on, normal, d) - depth      # residual along each ray
                noise = 1.4826 * float(np.median(np.abs(along) / depth ** 2))
        return planes, noise

    def _on_planes(self, points: np.ndarray, sigma: np.ndarray) -> np.ndarray:
        """(...) bool: points (..., 3) within noise_sigmas deviations of a plane, in depth
        along their own ray."""
        on = np.zeros(points.shape[:-1], dtype=bool)
        if not self._planes:
            return on
        # |plane depth - z| = |z| |n.p + d| / |n.p|: compared without the division
        z, allowed = np.abs(points[..., 2]), self.params.noise_sigmas * sigma
        with np.errstate(invalid='ignore'):
            for normal, d in self._planes:
                along = points @ normal
                on |= z * np.abs(along + d) < allowed * np.abs(along)
        return on

    def _maybe_refit_planes(self, points: np.ndarray, still: np.ndarray, shape: tuple) -> None:
        """Refit the planes every plane_refresh frames on the pixels in `still` (H*W,) of
        the organized `points` (H*W, 3)."""
        p = self.params
        if self._frames_since_planes is None or self._frames_since_planes >= p.plane_refresh:
            chosen = np.flatnonzero(still)
            if len(chosen) > 20000:
                rng = np.random.default_rng(p.seed)
                chosen = np.sort(rng.choice(chosen, 20000, replace=False))
            pixels = np.stack(np.divmod(chosen, shape[1]), axis=1)
            sample = points[chosen]
            # Planes of a still camera do not change: keep those the still pixels still
            # support and look for new ones only among the rest (a refit on a view partly
            # hidden by the subject could tilt the floor and leave a strip of it "off plane").
            kept, full = [], len(sample)
            if self._planes:
                sigma = max(self.noise_c or p.min_noise_c, p.min_noise_c) * sample[:, 2] ** 2
                for plane in self._planes:
                    saved, self._planes = self._planes, [plane]
                    on = self._on_planes(sample, sigma)
                    self._planes = saved
                    if on.sum() >= 0.05 * len(sample):
                        kept.append(plane)
                        sample, pixels = sample[~on], pixels[~on]
                        sigma = sigma[~on]
            new, noise = self._fit_planes(sample, pixels, shape, p.max_planes - len(kept), int(0.05 * full))
            self._planes = kept + new
            self._update_noise(noise)
            self._frames_since_planes = 0
        self._frames_since_planes += 1

    # -- organized -----------------------------------------------------------------------
    def _organized(self, points: np.ndarray, valid: np.ndarray) -> Segmentation:
        p = self.params
        shape = valid.shape
        if self._shape != shape:
            self.reset()
            self._shape = shape
            self._history = np.zeros(shape, dtype=np.float32)
        # Depth along the optical axis: the noise of depth cameras grows with it (sigma =
        # c z^2) and every comparison below is per pixel, along the pixel's own ray.
        depth = points[..., 2]
        far = np.where(valid, depth, np.inf)              # no return = far away, for motion

        # Motion against motion_lag frames ago; the noise from frame-to-frame differences
        # until a plane gives a better measure.
        previous = self._ranges[0] if self._ranges else None
        if previous is not None and self.noise_c is None:
            both = valid & np.isfinite(previous)
            if both.sum() > 100:
                change = np.abs(far[both] - previous[both]) / far[both] ** 2
                self._update_noise(1.4826 * float(np.median(change)) / np.sqrt(2.0))
        c = self._update_noise(None)
        sigma = c * np.where(valid, depth, 0.0) ** 2
        if previous is not None:
            with np.errstate(invalid='ignore'):
                tolerance = (p.noise_sigmas * np.sqrt(2.0) * c) * np.maximum(
                    np.where(valid, depth, 0.0), np.where(np.isfinite(previous), previous, 0.0)) ** 2
                changed = np.abs(far - previous) > tolerance
            changed &= valid | np.isfinite(previous)
            moved = _opening3x3(changed)
        else:
            moved = np.zeros(shape, dtype=bool)
        self._ranges.append(far)
        if len(self._ranges) > p.motion_lag:
            self._ranges.pop(0)
        self._history -= 1.0 / p.motion_memory
        np.maximum(self._history, 0.0, out=self._history)
        self._history[moved] = 1.0

        if self._frames_since_planes is None or self._frames_since_planes >= p.plane_refresh:
            still = valid & (self._history == 0.0)
            if self._subject is not None:
                still &= ~ndimage.binary_dilation(self._subject, iterations=3)
            self._maybe_refit_planes(points.reshape(-1, 3), still.reshape(-1), shape)
        else:
            self._frames_since_planes += 1
        on_plane = self._on_planes(points, sigma) & valid
        candidates = valid & ~on_plane
        ranges = far

        # Depth jumps split regions; a jump is more than the noise and more than a slanted
        # surface's step between neighbouring pixels (4 pixel footprints).
        footprint = np.where(valid, depth, 0.0) / max(shape) * 2.0
        jump = np.maximum(p.noise_sigmas * sigma * 2.0, 4.0 * footprint)
        finite = np.where(valid, ranges, np.nan)
        edge = np.zeros(shape, dtype=bool)
        with np.errstate(invalid='ignore'):
            dy = np.abs(np.diff(finite, axis=0)) > np.minimum(jump[1:], jump[:-1])
            dx = np.abs(np.diff(finite, axis=1)) > np.minimum(jump[:, 1:], jump[:, :-1])
        edge[1:] |= dy
        edge[:-1] |= dy
        edge[:, 1:] |= dx
        edge[:, :-1] |= dx
        core = candidates & ~edge
        labels, n_regions = ndimage.label(core)
        if n_regions == 0:
            return self._nobody(valid, c)
        flat_labels = labels.reshape(-1)
        sizes = np.bincount(flat_labels, minlength=n_regions + 1)[1:].astype(float)
        motion = np.bincount(flat_labels, weights=self._history.reshape(-1), minlength=n_regions + 1)[1:]
        overlap = (np.bincount(flat_labels, weights=self._subject.reshape(-1), minlength=n_regions + 1)[1:]
                   if self._subject is not None else np.zeros(n_regions))
        # Evidence that a region moves: more moved pixels than its boundary can flicker.
        moving = (motion >= np.maximum(20.0, 0.02 * sizes)) & (sizes >= 20)
        kept = overlap >= 0.3 * sizes
        chosen_from = moving | kept
        if not chosen_from.any():
            return self._nobody(valid, c)
        score = motion + 10.0 * overlap
        primary = int(np.argmax(np.where(chosen_from, score, -1.0)))
        # Join the parts of the subject that depth jumps split off (a forearm in front of
        # the torso, a leg in front of the body): regions near the primary in the image (a
        # cheap first cut) whose points come within attach_distance of it in 3-D.
        slices = ndimage.find_objects(labels)
        near = np.zeros(n_regions, dtype=bool)
        near[primary] = True
        rows, cols = slices[primary]
        nearest_depth = float(np.min(ranges[slices[primary]][labels[slices[primary]] == primary + 1]))
        margin = int(np.ceil(p.attach_distance / max(nearest_depth / max(shape), 1e-6)))
        window = (slice(max(rows.start - margin, 0), rows.stop + margin),
                  slice(max(cols.start - margin, 0), cols.stop + margin))
        def region_points(region: int) -> np.ndarray:
            return points[slices[region]][labels[slices[region]] == region + 1]

        # Grow from the primary: a region joins when it comes within reach of any region
        # already joined (a hoof joins the leg that joined the body), a few passes at most.
        # A few pixels are noise (a wrong depth here and there), not a body part.
        noise = ~chosen_from & (sizes < max(20.0, 0.002 * sizes[primary]))
        in_window = np.bincount(labels[window].ravel(), minlength=n_regions + 1)[1:] > 0
        candidates_nearby = np.flatnonzero(in_window & ~noise)
        boxes = {}

        def region_box(region: int) -> tuple:
            if region not in boxes:
                boxes[region] = self._region_box(points, labels, slices, region)
            return boxes[region]

        # Each pass tests the regions not yet joined against those the pass before it joined
        # only: against the earlier ones each was tested already and was out of reach, so
        # the result is that of testing against all of them, with a smaller tree and a
        # tighter box that rules more regions out without a query (the same masks, fewer
        # k-d tree queries).
        newly_joined = [region_points(primary)]
        for _ in range(3):
            tree = cKDTree(np.concatenate([pts[:: max(1, len(pts) // 1500)] for pts in newly_joined]))
            newly_joined = []
            for region in candidates_nearby:
                if near[region]:
                    continue
                # A moving part (a hand split off at a depth jump) may be a little farther; a
                # moving region as large as the subject is someone else.
                hand_sized = moving[region] and sizes[region] <= 0.25 * sizes[primary]
                reach = p.attach_distance * (2.0 if hand_sized else 1.0)
                # A still region touching the moving subject is the rest of it (the body of
                # a cow swinging a leg), unless it runs out of the image: room structure
                # that is not a plane (a wall's edge, a doorway), never wholly in view.
                rows, cols = slices[region]
                leaves_view = rows.start == 0 or cols.start == 0 or rows.stop == shape[0] or cols.stop == shape[1]
                if not chosen_from[region] and leaves_view:
                    continue
                region_low, region_high = region_box(region)
                if (region_high < tree.mins - reach).any() or (region_low > tree.maxes + reach).any():
                    continue   # boxes apart: no point can be within reach
                mine = region_points(region)
                distance, _ = tree.query(mine[:: max(1, len(mine) // 500)], distance_upper_bound=reach)
                if np.isfinite(distance).any():
                    near[region] = True
                    newly_joined.append(mine)
            if not newly_joined:
                break
        # Moving regions apart from the subject, together a tenth of its size: another
        # person (reported, not followed).
        others = np.flatnonzero(moving & ~near)
        n_moving = 1 + self._count_groups([region_box(r) for r in others],
                                          sizes[others], 0.1 * sizes[near].sum())
        subject = np.concatenate([[False], near])[labels]
        # Give back the subject's own boundary pixels (they are "edges" against the
        # background) unless they lie behind it: mixed pixels between it and the wall. Within
        # the subject's box and 4 pixels more (the ring is 2 pixels wide, the depth it is
        # compared with 2 more), which is all these filters can reach.
        rows, cols = np.flatnonzero(subject.any(axis=1)), np.flatnonzero(subject.any(axis=0))
        box = (slice(max(rows[0] - 4, 0), rows[-1] + 5), slice(max(cols[0] - 4, 0), cols[-1] + 5))
        inside = subject[box]
        ring = ndimage.binary_dilation(inside, iterations=2) & candidates[box] & ~inside
        with np.errstate(invalid='ignore'):
            nearest = ndimage.maximum_filter(np.where(inside, ranges[box], -np.inf), size=5)
            inside |= ring & (ranges[box] <= nearest + jump[box])
        if subject.sum() < p.min_subject_points:
            return self._nobody(valid, c)
        self._subject = subject
        border = subject[0].any() or subject[-1].any() or subject[:, 0].any() or subject[:, -1].any()
        return Segmentation(subject.reshape(-1), STATUS_SUBJECT, int(valid.sum()), n_moving, bool(border),
                            c, len(self._planes))

    @staticmethod
    def _region_box(points: np.ndarray, labels: np.ndarray, slices: list, region: int) -> tuple:
        """(low (3,), high (3,)) 3-D box of region `region` (0-based) of `labels`."""
        window = slices[region]
        inside = points[window][labels[window] == region + 1]
        return inside.min(axis=0), inside.max(axis=0)

    @staticmethod
    def _count_groups(boxes: list, sizes: np.ndarray, min_size: float, distance: float = 0.3) -> int:
        """How many groups of at least `min_size` pixels the regions (3-D boxes, pixel
        sizes) form when boxes closer than `distance` join."""
        if not boxes:
            return 0
        low = np.array([b[0] for b in boxes])
        high = np.array([b[1] for b in boxes])
        gap = np.maximum(np.maximum(low[:, None] - high[None], low[None] - high[:, None]), 0.0)
        adjacency = np.linalg.norm(gap, axis=-1) <= distance
        from scipy.sparse.csgraph import connected_components
        _, group = connected_components(adjacency, directed=False)
        return int((np.bincount(group, weights=sizes) >= min_size).sum())

    def _nobody(self, valid: np.ndarray, c: float) -> Segmentation:
        self._subject = None
        return Segmentation(np.zeros(valid.size, dtype=bool), STATUS_NOBODY, int(valid.sum()),
                            0, False, c, len(self._planes))

    # -- unorganized ---------------------------------------------------------------------
    def _unorganized(self, points: np.ndarray, valid: np.ndarray) -> Segmentation:
        """Planes, DBSCAN regions and nearest-neighbour motion on a voxel grid."""
        import open3d as o3d  # lazy, for DBSCAN: organized clouds never load it (core/point_sets.py)
        p = self.params
        finite = points[valid]
        if len(finite) < p.min_subject_points:
            return Segmentation(np.zeros(len(points), bool), STATUS_NOBODY, int(valid.sum()))
        extent = float(np.linalg.norm(np.ptp(finite, axis=0)))
        voxel = max(extent / 150.0, 0.01)
        down = voxel_centroids(finite, voxel)
        c = self._update_noise(None)
        sigma = c * down[:, 2] ** 2
        if self._frames_since_planes is None or self._frames_since_planes >= p.plane_refresh:
            self._planes, noise = self._fit_planes(down)
            self._update_noise(noise)
            self._frames_since_planes = 0
        self._frames_since_planes += 1
        keep = ~self._on_planes(down, sigma)
        candidates = down[keep]
        if len(candidates) < 10:
            return Segmentation(np.zeros(len(points), bool), STATUS_NOBODY, int(valid.sum()))
        labels = np.asarray(o3d.geometry.PointCloud(o3d.utility.Vector3dVector(candidates))
                            .cluster_dbscan(eps=3.0 * voxel, min_points=4))
        moved = np.zeros(len(candidates), dtype=bool)
        if self._previous_points is not None and len(self._previous_points):
            distance, _ = cKDTree(self._previous_points).query(candidates)
            moved = distance > max(p.noise_sigmas * float(np.median(sigma)), 1.5 * voxel)
        near_subject = np.zeros(len(candidates), dtype=bool)
        if self._previous_subject is not None and len(self._previous_subject):
            distance, _ = cKDTree(self._previous_subject).query(candidates)
            near_subject = distance <= 2.0 * voxel
        self._previous_points = down
        n_regions = int(labels.max()) + 1 if len(labels) else 0
        if n_regions == 0:
            return Segmentation(np.zeros(len(points), bool), STATUS_NOBODY, int(valid.sum()))
        in_region = labels >= 0
        sizes = np.bincount(labels[in_region], minlength=n_regions)
        motion = np.bincount(labels[in_region], weights=moved[in_region], minlength=n_regions)
        overlap = np.bincount(labels[in_region], weights=near_subject[in_region], minlength=n_regions)
        moving = motion >= np.maximum(5.0, 0.05 * sizes)
        eligible = moving | (overlap >= 0.3 * sizes)
        if not eligible.any():
            self._previous_subject = None
            return Segmentation(np.zeros(len(points), bool), STATUS_NOBODY, int(valid.sum()))
        primary = int(np.argmax(np.where(eligible, motion + 10.0 * overlap, -1.0)))
        subject_down = candidates[labels == primary]
        self._previous_subject = subject_down
        # every input point takes the label of its nearest subsampled candidate
        distance, _ = cKDTree(subject_down).query(finite, distance_upper_bound=1.5 * voxel)
        mask = np.zeros(len(points), dtype=bool)
        mask[np.flatnonzero(valid)[np.isfinite(distance)]] = True
        if mask.sum() < p.min_subject_points:
            return Segmentation(np.zeros(len(points), bool), STATUS_NOBODY, int(valid.sum()))
        n_moving = int(moving.sum())
        return Segmentation(mask, STATUS_SUBJECT, int(valid.sum()), n_moving, False, c, len(self._planes))
