"""The room's still background: the depth noise model sigma(r) = c r^2 and the large planes
(floor, walls, table tops), fitted by RANSAC on the pixels that have not moved."""
from __future__ import annotations

import numpy as np

from ..point_sets import ransac_plane


def _plane_depth(points: np.ndarray, normal: np.ndarray, offset: float) -> np.ndarray:
    """(...) depth z at which each point's camera ray (through the origin) meets the plane
    normal . p + offset = 0; inf where the ray runs along the plane."""
    with np.errstate(invalid='ignore', divide='ignore'):
        return -offset * points[..., 2] / (points @ normal)


class BackgroundModel:
    """Mixin of SubjectSegmenter: needs `self.params`, `self.noise_c`, `self._planes` and
    `self._frames_since_planes` (see SubjectSegmenter.reset)."""

    def _update_noise(self, estimate: float | None) -> float:
        p = self.params
        if estimate is not None and np.isfinite(estimate) and estimate > 0:
            # Slow average: one frame of a walking subject must not change the noise model.
            self.noise_c = estimate if self.noise_c is None else 0.9 * self.noise_c + 0.1 * estimate
        return max(self.noise_c if self.noise_c is not None else p.min_noise_c, p.min_noise_c)

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
