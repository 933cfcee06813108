"""Organized clouds (a depth camera's pixel grid): motion against a few frames ago, regions
split at depth jumps, the moving region and the parts of the subject it reaches, and the
subject of a large image at full resolution from its working grid."""
from __future__ import annotations

import numpy as np
from scipy import ndimage
from scipy.spatial import cKDTree

from .params import STATUS_NOBODY, STATUS_SUBJECT, Segmentation


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


class OrganizedSegmentation:
    """Mixin of SubjectSegmenter for organized clouds: needs its state (see
    SubjectSegmenter.reset) and BackgroundModel's planes and noise."""

    def _organized(self, points: np.ndarray, valid: np.ndarray) -> Segmentation:
        """The subject of an organized cloud points (H, W, 3) with valid (H, W): motion,
        planes, regions split at depth jumps, the moving region and the parts it reaches."""
        shape = valid.shape
        if self._shape != shape:
            self.reset()
            self._shape = shape
            self._history = np.zeros(shape, dtype=np.float32)
        # Depth along the optical axis: the noise of depth cameras grows with it (sigma =
        # c z^2) and every comparison below is per pixel, along the pixel's own ray.
        depth = points[..., 2]
        far = np.where(valid, depth, np.inf)              # no return = far away, for motion
        c, sigma = self._motion(far, depth, valid)
        if self._frames_since_planes is None or self._frames_since_planes >= self.params.plane_refresh:
            still = valid & (self._history == 0.0)
            if self._subject is not None:
                still &= ~ndimage.binary_dilation(self._subject, iterations=3)
            self._maybe_refit_planes(points.reshape(-1, 3), still.reshape(-1), shape)
        else:
            self._frames_since_planes += 1
        candidates = valid & ~(self._on_planes(points, sigma) & valid)
        jump, labels, n_regions = self._depth_regions(far, depth, valid, sigma, candidates)
        joined = self._join_subject(points, far, labels, n_regions) if n_regions else None
        if joined is None:
            return self._nobody(valid, c)
        near, n_moving = joined
        subject = np.concatenate([[False], near])[labels]
        self._give_back_boundary(subject, candidates, far, jump)
        if subject.sum() < self.params.min_subject_points:
            return self._nobody(valid, c)
        self._subject = subject
        border = subject[0].any() or subject[-1].any() or subject[:, 0].any() or subject[:, -1].any()
        return Segmentation(subject.reshape(-1), STATUS_SUBJECT, int(valid.sum()), n_moving, bool(border),
                            c, len(self._planes))

    def _motion(self, far: np.ndarray, depth: np.ndarray, valid: np.ndarray) -> tuple:
        """Motion against motion_lag frames ago into the faded evidence `self._history`;
        the noise from frame-to-frame differences until a plane gives a better measure.
        Returns (c, sigma (H, W) m)."""
        p = self.params
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
            moved = np.zeros(valid.shape, dtype=bool)
        self._ranges.append(far)
        if len(self._ranges) > p.motion_lag:
            self._ranges.pop(0)
        self._history -= 1.0 / p.motion_memory
        np.maximum(self._history, 0.0, out=self._history)
        self._history[moved] = 1.0
        return c, sigma

    def _depth_regions(self, ranges, depth, valid, sigma, candidates) -> tuple:
        """(jump (H, W) m, labels (H, W), n_regions): the candidate pixels split into
        connected regions at depth jumps, a jump being more than the noise and more than a
        slanted surface's step between neighbouring pixels (4 pixel footprints)."""
        shape = valid.shape
        footprint = np.where(valid, depth, 0.0) / max(shape) * 2.0
        jump = np.maximum(self.params.noise_sigmas * sigma * 2.0, 4.0 * footprint)
        finite = np.where(valid, ranges, np.nan)
        edge = np.zeros(shape, dtype=bool)
        with np.errstate(invalid='ignore'):
            dy = np.abs(np.diff(finite, axis=0)) > np.minimum(jump[1:], jump[:-1])
            dx = np.abs(np.diff(finite, axis=1)) > np.minimum(jump[:, 1:], jump[:, :-1])
        edge[1:] |= dy
        edge[:-1] |= dy
        edge[:, 1:] |= dx
        edge[:, :-1] |= dx
        labels, n_regions = ndimage.label(candidates & ~edge)
        return jump, labels, n_regions

    def _join_subject(self, points, ranges, labels, n_regions) -> tuple | None:
        """(near (n_regions,) bool: the subject's regions, n_moving_regions), or None when
        no region moves or overlaps the last subject. The primary region has the most
        motion evidence (the last subject's regions keep it while it pauses); the parts of
        the subject that depth jumps split off (a forearm in front of the torso, a leg in
        front of the body) join when their points come within attach_distance of it."""
        p = self.params
        shape = labels.shape
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
            return None
        score = motion + 10.0 * overlap
        primary = int(np.argmax(np.where(chosen_from, score, -1.0)))
        # Regions near the primary in the image (a cheap first cut) are tested in 3-D.
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
        # tighter box that rules more regions out without a query.
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
        return near, n_moving

    @staticmethod
    def _give_back_boundary(subject, candidates, ranges, jump) -> None:
        """Give back the subject's (H, W) own boundary pixels (they are "edges" against the
        background), in place, unless they lie behind it: mixed pixels between it and the
        wall. Within the subject's box and 4 pixels more (the ring is 2 pixels wide, the
        depth it is compared with 2 more), which is all these filters can reach."""
        rows, cols = np.flatnonzero(subject.any(axis=1)), np.flatnonzero(subject.any(axis=0))
        box = (slice(max(rows[0] - 4, 0), rows[-1] + 5), slice(max(cols[0] - 4, 0), cols[-1] + 5))
        inside = subject[box]
        ring = ndimage.binary_dilation(inside, iterations=2) & candidates[box] & ~inside
        with np.errstate(invalid='ignore'):
            nearest = ndimage.maximum_filter(np.where(inside, ranges[box], -np.inf), size=5)
            inside |= ring & (ranges[box] <= nearest + jump[box])

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
        # the working grid's depth-jump threshold between neighbouring cells (see _depth_regions)
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
