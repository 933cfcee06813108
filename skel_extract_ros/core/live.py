r"""Live joints: the learned LBS model fitted to one new frame at a time.

After Alg. 2 has run, the skeleton (rest points Q (M, 3), weights W, joints c_jk, bone
tree) is fixed; for every later frame only the bone transforms change. Two trackers fit
them, with Alg. 2's LBS and bone-block update (core.articulated) on one frame:

`LiveJointTracker`, on a *registered* frame Y (M, 3) (offline `run`, frames that are not
key frames): the single-frame part of Eq. (12) without the GMM term,

    zeta/2 sum_m |y_m - x_m|^2 + alpha/2 sum_<j,k> |(R_j - R_k) c_jk + T_j - T_k|^2
    + gamma/2 sum_j |T_j - T_j^init|^2,       x_m = sum_j w_mj (R_j q_m + T_j)   (Eq. 8)

from per-bone rigid fits (Eq. 9).

`ArticulatedTracker`, on the *observed* subject points V (N, 3) of a camera frame, with
no registration at all (the live path): the single-frame part of Eq. (12) without the
registration term,

    E_GMM(V; x, tau) + alpha/2 E_Joint + gamma/2 sum_j |T_j - T_j^pred|^2

by EM: the truncated E-step of core.gmm (Eq. 11) against the LBS-deformed rest points, the
bone blocks with the data term lambda = P1_m w_mj^2 / tau, tau by Eq. (7); and, for a
camera:
- *prediction*: each bone starts from its constant-velocity prediction (its motion from
  two frames back to the last, applied once more), and E_small pulls towards it;
- *reach*: each frame starts at tau = max(the last frame's converged tau, the mean squared
  distance of the observations to the predicted model / 3); each iteration first moves
  the whole skeleton rigidly onto the E-step's targets, then runs the bone blocks with
  alpha growing geometrically from LIVE_ALPHA_START zeta M to Alg. 2's zeta M at the last
  iteration. At Alg. 2's alpha from the start, the bone-by-bone update cannot move a
  chain (each bone is held at its joints by neighbours not yet moved): a person who
  walked 20 cm, or an arm that swung, since the starting pose stayed there;
- *unseen parts*: a point with no observation near it has P1 = 0 and only the joint term
  and the prediction move its bone;
- *losing the subject*: a frame whose fit leaves tau far above the tracking noise is
  `diverged`; one that also leaves a bone without data is `lost`.
`CameraTracker` is the joint node's live path (live_frames camera): every camera frame is
fitted from the model's fit of the newest registered frame at or before it (up to a
second old once tracking), a diverged frame gets that registered pose.

    >>> tracker = ArticulatedTracker(model, JointParams())
    >>> tracker.seed(rotations, translations)           # (B, 3, 3), (B, 3): a known pose
    >>> positions = tracker.track(observed_points)      # (J, 3) metres, the cloud's frame
"""
from __future__ import annotations

import time

import numpy as np
from scipy.spatial import cKDTree

from .articulated import BoneBlocks
from .confidence import half_residual, joint_confidence, outside_silhouette
from .gmm import CandidateCache
from .joints import JointParams
from .limb_poses import LimbPoses
from .point_sets import finite_rows, median_spacing, strided_subset, subset_stride
from .registration.visibility import ObservedView
from .rigid import fit_rigid_segments, weighted_rigid_fit
from .skeleton_model import SkeletonModel
from .joint_centres import joint_trajectories

# a bone whose points get less than this share of the frame's average posterior mass has
# lost its data (core.recapture uses the same level for the registration's graph nodes)
LOST_SUPPORT = 0.1
# bones this small (points of the model subset) are not counted when deciding `lost`
LOST_MIN_POINTS = 10
# the live fit's joint weight in its first EM iteration, relative to Alg. 2's zeta * M (it
# grows geometrically to zeta * M at the last): loose enough for a chain to follow its
# data, not so loose that the joints come apart in the first iteration
LIVE_ALPHA_START = 1e-4
# reweighting rounds of the whole-body move (Cauchy weights, the scale the median residual):
# a limb bent otherwise than its starting pose should not turn the body
WHOLE_BODY_ROUNDS = 3
# observed points a camera frame's confidence is measured on at most (a strided subset)
CONFIDENCE_SAMPLES = 1000
# the model points and observations one camera-frame fit uses at most (strided subsets):
# its E-steps and data sums grow with both, the joints need neither all of them
FIT_POINTS = 600
FIT_OBSERVED = 1000


def silhouette_view(observed: np.ndarray) -> ObservedView | None:
    """The ObservedView of a frame's observed points (N, 3) m (non-finite rows left out), or
    None when they make no silhouette (fewer than two rays, or all along one)."""
    observed = np.asarray(observed, dtype=np.float64)
    observed = observed[finite_rows(observed)]
    view = ObservedView(observed) if len(observed) >= 2 else None
    return view if view is not None and view.ray_spacing > 0 else None


class _BoneBlocks:
    """One frame of a fixed SkeletonModel: its LBS (Eq. 8) and the block update of Eq.
    13-15 (core.articulated.BoneBlocks, with one frame), on a strided subset of its points
    when max_points is given."""

    def __init__(self, model: SkeletonModel, params: JointParams | None, sweeps: int,
                 max_points: int | None = None):
        if sweeps < 0:
            raise ValueError(f'sweeps must be >= 0, got {sweeps}')
        self.model = model
        self.params = params or JointParams()
        self.sweeps = int(sweeps)
        rest = np.asarray(model.rest_points, dtype=np.float64)
        # max_points: fit an evenly strided subset of the model (the rest points are in
        # no spatial order, so a stride keeps every bone's share)
        stride = 1 if max_points is None else subset_stride(len(rest), max_points)
        self._subset = np.arange(0, len(rest), stride)
        rest = rest[self._subset]
        self._rest = rest
        influences = np.asarray(model.influences)[self._subset]
        weights = np.asarray(model.weights, dtype=np.float64)[self._subset]
        # the bone each point follows most: the rigid initialisation fits those points
        self._dominant = influences[np.arange(len(rest)), np.argmax(weights, axis=1)]
        self._parents = np.asarray(model.parents)
        self._joints = np.asarray(model.rest_joints, dtype=np.float64)
        self._alpha = self.params.zeta * len(rest)
        self._half_residual = half_residual(model.noise_m)
        self._blocks = BoneBlocks(rest, influences, weights, self._parents)
        # the confidence counts each point towards every bone it follows, by its weight: a
        # bone whose points all follow a neighbour more still has its share of them
        self._influences, self._weights = influences, weights

    @property
    def n_bones(self) -> int:
        return len(self._parents)

    def deform(self, rotations: np.ndarray, translations: np.ndarray) -> np.ndarray:
        """(M, 3) LBS-deformed rest points (Eq. 8) for rotations (B, 3, 3), translations (B, 3)."""
        return self._blocks.deform(rotations[None], translations[None])[0]

    def sweep(self, targets: np.ndarray, point_weights, rotations: np.ndarray, translations: np.ndarray,
              anchors: tuple | None = None, alpha: float | None = None) -> np.ndarray:
        """`self.sweeps` passes of the block update, in place on rotations (B, 3, 3) and
        translations (B, 3). targets (M, 3) m; point_weights: the data term's weight per
        point (M,) or one for all (1/m^2); anchors: (rotations, translations) E_small pulls
        towards (None: each bone's current transform, a proximal step); alpha: the joint
        weight (None: Alg. 2's zeta M). Returns the (M, 3) deformed rest points of the new
        transforms (Eq. 8)."""
        anchors = None if anchors is None else (anchors[0][None], anchors[1][None])
        return self._blocks.update(np.asarray(targets, dtype=np.float64)[None], np.asarray(point_weights),
                                   rotations[None], translations[None], self._joints,
                                   self._alpha if alpha is None else alpha, self.params.gamma, anchors,
                                   self.sweeps)[0]

    def move_whole_body(self, targets: np.ndarray, point_weights: np.ndarray, deformed: np.ndarray,
                        rotations: np.ndarray, translations: np.ndarray) -> None:
        """The whole skeleton (one tree: the structure's spanning tree) moved as one rigid
        body from its deformed points (M, 3) onto the targets (M, 3) with weights (M,) (the
        weighted Procrustes fit, reweighted robustly so that the body's majority decides),
        in place on rotations (B, 3, 3) and translations (B, 3); every joint stays together.

        Why: with the joint term as stiff as Alg. 2's, the bone-by-bone update cannot move
        the body: each bone is held at its joints by neighbours that have not moved yet, so
        a person who stepped 20 cm since the registered frame stays where that frame put
        them. Sub-chains are not moved this way: a limb bent differently would pull the fit
        of everything it hangs from.
        """
        if point_weights.sum() <= 1e-12:
            return
        R, t = weighted_rigid_fit(deformed, targets, point_weights)
        for _ in range(WHOLE_BODY_ROUNDS):
            residual = np.linalg.norm(deformed @ R.T + t - targets, axis=1)
            scale = max(float(np.median(residual[point_weights > 0])), 1e-6)
            R, t = weighted_rigid_fit(deformed, targets, point_weights / (1.0 + (residual / scale) ** 2))
        rotations[:] = R @ rotations
        translations[:] = translations @ R.T + t

    def joints_of(self, rotations: np.ndarray, translations: np.ndarray) -> np.ndarray:
        """(J, 3) joint positions for one frame's bone transforms."""
        return joint_trajectories(rotations[None], translations[None], self._joints, self._parents)[0]

    def confidence(self, rotations: np.ndarray, translations: np.ndarray, points: np.ndarray,
                   corresponding: bool, observed: np.ndarray | None = None,
                   view: ObservedView | None = None) -> np.ndarray:
        """(J,) per-joint confidence in [0, 1] (core.confidence) of the pose (rotations
        (B, 3, 3), translations (B, 3)) against a frame's points, m: its registered points
        (M, 3), which correspond to the model's (corresponding=True), or its observed subject
        points (N, 3), each matched to the nearest posed model point. observed (N, 3) m: the
        frame's observed subject points, whose silhouette the posed bones must lie in (the
        observed `points` themselves when not corresponding; None with registered points:
        the residual alone); view: their `silhouette_view`, when the caller has it (a frame
        whose fits are compared builds it once)."""
        posed = self.deform(rotations, translations)
        points = np.asarray(points, dtype=np.float64)
        if not corresponding:
            observed = points
        outside = None
        if observed is not None:
            view = silhouette_view(observed) if view is None else view
            if view is not None:
                outside = outside_silhouette(self.n_bones, self._influences, posed, view, self._weights)
        if corresponding:
            squared = np.sum((points[self._subset] - posed) ** 2, axis=1)
            return joint_confidence(self._parents, self._influences, squared, outside, self._half_residual,
                                    self._weights)
        points = points[finite_rows(points)]
        # a strided subset, as the fit uses: the mean residual per bone needs no more
        points = strided_subset(points, CONFIDENCE_SAMPLES)
        if len(points) == 0:
            return np.zeros(self.n_bones)
        distance, nearest = cKDTree(posed).query(points)
        return joint_confidence(self._parents, self._influences[nearest], distance ** 2, outside,
                                self._half_residual, self._weights[nearest])


class LiveJointTracker(_BoneBlocks):
    """Per-frame bone transforms and joints of a fixed SkeletonModel from registered frames.

    sweeps: bone-by-bone passes of the exact block update after the rigid initialisation
    (0 = rigid fits only). The joint weight alpha is Alg. 2's starting value zeta * M.
    """

    def __init__(self, model: SkeletonModel, params: JointParams | None = None, sweeps: int = 2):
        super().__init__(model, params, sweeps)

    def fit(self, registered: np.ndarray) -> tuple:
        """Bone transforms for one frame: registered (M, 3) -> rotations (B, 3, 3),
        translations (B, 3), rest -> frame. Raises ValueError on a wrong shape."""
        registered = np.asarray(registered, dtype=np.float64)
        if registered.shape != self._rest.shape:
            raise ValueError(f'registered frame has shape {registered.shape}, the model has '
                             f'{self._rest.shape[0]} points')
        rotations, translations = fit_rigid_segments(self._rest, registered[None], self._dominant, self.n_bones)
        rotations, translations = rotations[0], translations[0]
        self.sweep(registered, self.params.zeta, rotations, translations)
        return rotations, translations

    def track(self, registered: np.ndarray) -> np.ndarray:
        """(J, 3) joint positions (metres, the registered frame's coordinates)."""
        return self.joints_of(*self.fit(registered))


class ArticulatedTracker(_BoneBlocks):
    """The learned model fitted directly to each frame's observed subject points.

    iterations: EM iterations per frame; sweeps: block passes per iteration; max_points /
    max_observed: the model points and observations the fit uses at most (strided subsets:
    the cost of a frame is linear in both, the joints need neither all of them);
    lost_tau_factor: a frame whose converged tau exceeds this many times the running
    tracking noise (the median converged tau of the recent frames) is `diverged`; a
    diverged frame, or one that leaves a bone of at least LOST_MIN_POINTS points without
    data, is `lost`; reach: the whole-body move and the joint weight ramp of each
    iteration (False: the bone blocks at Alg. 2's alpha only, as before; bench_live's
    `bones` scheme). State: the last two frames' bone transforms (for the prediction) and
    tau.
    """

    def __init__(self, model: SkeletonModel, params: JointParams | None = None, sweeps: int = 1,
                 iterations: int = 5, max_points: int = FIT_POINTS, max_observed: int = FIT_OBSERVED,
                 lost_tau_factor: float = 9.0, reach: bool = True):
        super().__init__(model, params, sweeps, max_points)
        self.reach = bool(reach)
        if iterations < 1:
            raise ValueError(f'iterations must be >= 1, got {iterations}')
        if max_observed < 10:
            raise ValueError(f'max_observed must be >= 10, got {max_observed}')
        self.iterations = int(iterations)
        self.max_observed = int(max_observed)
        self.lost_tau_factor = float(lost_tau_factor)
        self._history = []          # up to two (rotations, translations), newest last
        self.tau = None             # converged tau of the last frame (m^2)
        self._recent_tau = []       # converged tau of recent good frames
        self.lost = False           # the last frame's fit is not to be trusted
        self.diverged = False       # ... because it explains the data far worse than usual
        self._counts = np.maximum(np.bincount(self._dominant, minlength=self.n_bones), 1)
        # the model points' spacing: moving less keeps the E-step's candidate lists
        self._spacing = median_spacing(self._rest)

    def seed(self, rotations: np.ndarray, translations: np.ndarray, tau: float | None = None) -> None:
        """Start (again) from a known pose: rotations (B, 3, 3), translations (B, 3), e.g.
        Alg. 2's or LiveJointTracker's fit of the newest registered frame; tau (m^2) its
        noise, when known (None: the next frame's misfit sets it). Forgets the velocity."""
        rotations = np.array(rotations, dtype=np.float64)
        translations = np.array(translations, dtype=np.float64)
        if rotations.shape != (self.n_bones, 3, 3) or translations.shape != (self.n_bones, 3):
            raise ValueError(f'a seed needs ({self.n_bones}, 3, 3) rotations and ({self.n_bones}, 3) '
                             f'translations, got {rotations.shape} and {translations.shape}')
        self._history = [(rotations, translations)]
        self.tau = None if tau is None else max(float(tau), self.params.min_tau)
        self.lost = self.diverged = False

    def predict(self) -> tuple:
        """Constant-velocity prediction (rotations (B, 3, 3), translations (B, 3)): the motion
        D = A_1 A_2^-1 from two frames back to the last, applied to the last pose."""
        rotations, translations = self._history[-1]
        if len(self._history) < 2:
            return rotations.copy(), translations.copy()
        rotations_2, translations_2 = self._history[-2]
        step = rotations @ np.transpose(rotations_2, (0, 2, 1))                    # (B, 3, 3)
        return step @ rotations, np.einsum('bij,bj->bi', step, translations - translations_2) + translations

    def fit(self, observed: np.ndarray) -> tuple:
        """Bone transforms (rotations (B, 3, 3), translations (B, 3)) for observed (N, 3)
        subject points of the next frame (m; non-finite rows are ignored). Raises ValueError
        before a seed or on a cloud without finite points."""
        if not self._history:
            raise ValueError('the tracker has no pose yet: seed it from a registered frame')
        observed = np.asarray(observed, dtype=np.float64)
        if observed.ndim != 2 or observed.shape[1] != 3:
            raise ValueError(f'observed points must be (N, 3), got shape {observed.shape}')
        observed = observed[finite_rows(observed)]
        if len(observed) == 0:
            raise ValueError('observed points: none is finite')
        observed = strided_subset(observed, self.max_observed)
        params = self.params
        rotations, translations = self.predict()
        anchors = (rotations.copy(), translations.copy())
        deformed = self.deform(rotations, translations)
        # One k-d tree query at the prediction serves the reach and the E-steps: each
        # observation keeps its nearest model points, however far, as candidates until a
        # model point has moved a rest spacing (core.gmm.CandidateCache), instead of a query
        # for every E-step.
        cache = CandidateCache(observed, self._spacing, params.e_step_neighbours, radius_margin=np.inf)
        candidates = cache.candidates_for(deformed)
        # reach: the prediction's own misfit sets the first tau (see the module docstring)
        reach = float(np.mean(np.sum((observed - deformed[candidates[:, 0]]) ** 2, axis=1))) / 3.0
        tau = max(reach, self.tau or params.initial_tau, params.min_tau)
        tau, stats = self._em(cache, rotations, translations, anchors, tau, deformed)
        support = self._support(stats)
        noise = float(np.median(self._recent_tau)) if self._recent_tau else tau
        self.diverged = bool(tau > self.lost_tau_factor * noise or stats is None)
        self.lost = bool(self.diverged or (support[self._counts >= LOST_MIN_POINTS] < LOST_SUPPORT).any())
        if not self.diverged:
            self._recent_tau = (self._recent_tau + [tau])[-30:]
        self.tau = tau
        self._history = (self._history + [(rotations.copy(), translations.copy())])[-2:]
        return rotations, translations

    def _em(self, cache: CandidateCache, rotations, translations, anchors, tau, deformed) -> tuple:
        """`iterations` EM iterations in place on (rotations, translations) from the deformed
        model (M, 3), over the frame's observations in `cache`; returns (tau, the last
        E-step's statistics, or None when no observation was in reach)."""
        params = self.params
        stats = None
        for iteration in range(self.iterations):
            stats = cache.posteriors(deformed, tau, params.omega, params.truncation_sigmas)
            if stats.Np < 1e-9:
                return tau, None
            targets, weights = stats.targets(), stats.P1 / tau
            alpha = None
            if self.reach:
                self.move_whole_body(targets, weights, deformed, rotations, translations)
                if self.iterations > 1:
                    alpha = self._alpha * LIVE_ALPHA_START ** (1.0 - iteration / (self.iterations - 1))
            deformed = self.sweep(targets, weights, rotations, translations, anchors, alpha)
            tau = max(stats.squared_residual(deformed) / (3.0 * stats.Np), params.min_tau)
        return tau, stats

    def _support(self, stats) -> np.ndarray:
        """(B,) posterior mass per point each bone's points received, relative to the
        frame's average (1: as well observed as the rest, 0: no data)."""
        if stats is None:
            return np.zeros(self.n_bones)
        per_point = np.bincount(self._dominant, weights=stats.P1, minlength=self.n_bones) / self._counts
        return per_point / max(stats.Np / len(self._rest), 1e-12)

    def track(self, observed: np.ndarray) -> np.ndarray:
        """(J, 3) joint positions (metres, the observed cloud's coordinates)."""
        return self.joints_of(*self.fit(observed))


class CameraTracker:
    """Joints for every camera frame of a fixed SkeletonModel (the joint node's live path).

    Each camera frame is fitted from its observed points alone, started from the model's
    fit of the newest registered frame at or before it (the registration answers every
    8-90 frames once a skeleton is tracked, by the machine: that pose is up to seconds old,
    and the fit's reach carries body and limbs to where the points are now). With a
    `chain` tracker the frame is also fitted from the pose served for the frame before
    (its constant-velocity prediction), and the fit whose joints the frame's points
    support better (the higher mean confidence, core.confidence: the residual and the
    silhouette) is served. Why both: from the registered pose a hand that moved 40-90 cm
    since is out of reach; a fit carried from frame to frame alone drifts (a walker's
    legs), and a drifted pose leaves the silhouette or the points, which the confidence
    sees. A fit that diverges (ArticulatedTracker.diverged: it explains the data far worse
    than the recent frames) is no candidate; with none, the frame gets the registered
    pose's joints. Given a deadline, the second fit is made only when the time the last
    one and its confidence took still fits before it (a machine that cannot fit twice a
    frame answers every frame from the registered pose rather than fewer frames). With
    `limb_poses`, the fit from the registered pose starts with each limb the frame's points
    show elsewhere put in the key frames' pose that explains them best
    (core.limb_poses.LimbPoses): a hand that swung beyond the fit's reach since the
    registered frame is started where this subject's hand has been.

    tracker: the ArticulatedTracker started from the registered pose; fit: a
    LiveJointTracker of the same model (registered points -> bone transforms); chain: a
    second ArticulatedTracker of the model, or None (one fit a frame); limb_poses: the
    model's LimbPoses, or None (the registered pose as it is). Stamps are integers (ns).
    `counts['reposed']`: the frames whose registered start had a limb re-posed.
    """

    def __init__(self, tracker: ArticulatedTracker, fit: LiveJointTracker, chain: ArticulatedTracker | None = None,
                 limb_poses: LimbPoses | None = None):
        for other in (fit, chain):
            if other is not None and other.n_bones != tracker.n_bones:
                raise ValueError(f'the trackers have {other.n_bones} and {tracker.n_bones} bones')
        self.tracker, self.fit, self.chain, self.limb_poses = tracker, fit, chain, limb_poses
        self._registered = None                      # (stamp, rotations, translations), newest
        self._fitted = None                          # the last frame's fitted transforms, if fitted
        self.pose = None                             # the last frame's served transforms (any outcome)
        self.confidence = None                       # (J,) the served pose's, against the last frame's points
        self.counts = {'fitted': 0, 'chained': 0, 'lost': 0, 'registered': 0, 'reposed': 0}
        self.chain_skipped = 0                       # frames whose second fit the deadline left out
        self._chain_seconds = 0.0                    # the last second fit's time, with its confidence

    @classmethod
    def for_model(cls, model: SkeletonModel, params: JointParams | None, fit: LiveJointTracker,
                  iterations: int, chain: bool = False, sweeps: int = 1, reach: bool = True,
                  key_poses: tuple | None = None) -> 'CameraTracker':
        """The joint node's camera tracker of `model` (fit: its LiveJointTracker): one
        ArticulatedTracker (iterations, sweeps, reach as there) on FIT_POINTS model points and
        FIT_OBSERVED observations, or with `chain` two, each on half of them: the two cost
        about 1.5 times one (the rest of a fit is numpy's per-call overhead in the bone
        updates) and a fit on half the points follows real motion as well as one on all
        (bench/README.md, the live fit's table). key_poses: (rotations (K, B, 3, 3),
        translations (K, B, 3)) of the frames the model was learned on, for its LimbPoses
        (None: the registered start as it is)."""
        share = 2 if chain else 1
        trackers = [ArticulatedTracker(model, params, sweeps=sweeps, iterations=iterations, reach=reach,
                                       max_points=FIT_POINTS // share, max_observed=FIT_OBSERVED // share)
                    for _ in range(share)]
        limb_poses = None if key_poses is None else LimbPoses(model, *key_poses)
        return cls(trackers[0], fit, trackers[1] if chain else None, limb_poses)

    def registered(self, stamp: int, registered_points: np.ndarray) -> None:
        """Take the registered frame at `stamp` (registered_points (M, 3) m, the model's
        points) as the start of the next camera frames' fits; an older or repeated stamp is
        ignored (nothing is fitted again)."""
        stamp = int(stamp)
        if self._registered is None or stamp > self._registered[0]:
            self._registered = (stamp, *self.fit.fit(registered_points))

    def track(self, stamp: int, observed: np.ndarray, deadline: float | None = None) -> tuple:
        """(positions (J, 3) m, outcome) for the camera frame at `stamp` with observed (N, 3)
        subject points: outcome 'registered' (its own registered frame is in: its fit),
        'fitted' (from the registered pose), 'chained' (from the last frame's pose), or
        'lost' (no fit converged: the newest registered pose's joints). deadline: a
        time.perf_counter() value the frame should be done by (None: no limit). Sets `pose`
        and `confidence` (the served pose's). Raises ValueError before any registered
        frame, and as ArticulatedTracker.fit on bad points."""
        if self._registered is None:
            raise ValueError('no registered frame yet: nothing to start the live fit from')
        registered_stamp, rotations, translations = self._registered
        outcome = 'registered'
        confidence = None
        view = silhouette_view(observed)            # one silhouette for every fit compared
        if registered_stamp != int(stamp):
            start = (rotations, translations)
            if self.limb_poses is not None:
                *start, reposed = self.limb_poses.repose(rotations, translations, observed)
                self.counts['reposed'] += bool(reposed)
            self.tracker.seed(*start)
            candidates = [('fitted', self.tracker)]
            if self.chain is not None and self.pose is not None:
                candidates.append(('chained', self.chain))
            best = -1.0
            for name, tracker in candidates:     # one or two fits
                started = time.perf_counter()
                if name == 'chained' and deadline is not None and started + self._chain_seconds > deadline:
                    self.chain_skipped += 1
                    continue
                fitted = tracker.fit(observed)
                scores = None if tracker.diverged else self.tracker.confidence(*fitted, observed, False, view=view)
                if name == 'chained':
                    self._chain_seconds = time.perf_counter() - started
                elif self._chain_seconds == 0.0:
                    self._chain_seconds = time.perf_counter() - started      # until a second fit is timed
                if scores is not None and scores.mean() > best:
                    outcome, (rotations, translations), confidence, best = name, fitted, scores, scores.mean()
            if best < 0.0:
                outcome = 'lost'
        if confidence is None:
            # the registered pose served: what it explains of this frame
            confidence = self.tracker.confidence(rotations, translations, observed, False, view=view)
        if self.chain is not None and outcome != 'chained':
            # the next frame's second start is the pose served now (its velocity unknown)
            self.chain.seed(rotations, translations)
        self._fitted = (rotations, translations) if outcome in ('fitted', 'chained') else None
        self.pose, self.confidence = (rotations, translations), confidence
        self.counts[outcome] += 1
        return self.fit.joints_of(rotations, translations), outcome

    def posed_points(self) -> np.ndarray | None:
        """(M, 3) the model's points (the registered points' order) posed by LBS at the last
        frame's fit, or None when that frame was not fitted (lost, or its own registered
        frame): where the registration may start that frame's successors from."""
        return None if self._fitted is None else self.fit.deform(*self._fitted)
