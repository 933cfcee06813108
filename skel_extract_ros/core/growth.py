"""A skeleton that grows over a long sequence: every window's evidence goes into one model.

A person waves the left arm, then the right, then walks: each joint moves at some time but
no window of a minute's frames sees all of them. Windows are therefore not learned one by
one: the frames the model is learned from are a bounded set of *key frames*, the most
different poses seen so far, and every new window competes for a place in it. A joint
that moved once keeps the frames that show it bent, so it stays in the model after its
part has stopped moving, and appears as soon as its part has moved.

Key frames: each registered frame (M, 3) is brought back onto the rest pose by its own best
rigid motion (so walking or turning is no difference in pose), and the key frames are a
farthest-point sample, in RMS distance between these aligned frames, of the previous key
frames and the new window (at most `max_key_frames`; until then, every frame). Step 2
(and Step 3 when the observed points are given) then runs on the key frames.

Stable joints: joint b is the joint between bone b and its parent (the root's is its
centre). After each update the root joint keeps the root's id, and the other new joints
are matched (rest frame, core.matching's gated assignment) to every joint the model has
ever had, within `joint_match_fraction` of the subject size; a matched joint keeps its id,
a new one gets the next id, and names are `joint_<id>`, so consumers keying on names see
the same joint across updates. A skeleton started after another (a new rest pose) begins
at the other's `next_id`, so a name is never given to two joints. `GrowthUpdate.changes`
says what changed: joints added, removed, re-parented, or moved by more than the match
radius over two.
"""
from __future__ import annotations

import time
from dataclasses import dataclass, field

import numpy as np

from .joints import JointEstimate, JointEstimation, JointParams
from .matching import gated_assignment
from .parameters import parameter, validate
from .rigid import fit_rigid_segments
from .skeleton_model import SkeletonModel
from .structure import SkeletalStructure, StructureParams, extract_structure

# poses are compared on this many rest points (spread over the subject): enough to see a
# finger bend, independent of M
POSE_SAMPLES = 256


@dataclass
class GrowthSchedule:
    """When the skeleton is learned from the frames as they come (the accumulator node and
    `skel-extract run` alike): once `window_size` registered frames are in, on them; with
    `sliding`, again every `stride` frames after, on the last `window_size` frames (which
    compete for the key frames). A window that shows no articulation is retried on the
    next `window_size` frames (without sliding) or at the next stride."""

    window_size: int = parameter(60, 'registered frames collected before the skeletal structure is extracted',
                                 2, 100_000, live=True)
    sliding: bool = parameter(False, 'keep growing the skeleton: every `stride` frames the last window_size '
                              'frames compete for the key frames and the structure is learned again', live=True)
    stride: int = parameter(30, 'registered frames between extractions when sliding', 1, 100_000, live=True)

    def __post_init__(self):
        validate(self)

    def due(self, since_extraction: int, extracted_once: bool) -> bool:
        """Whether to learn now, `since_extraction` frames after the last extraction (or
        since the start), `extracted_once` telling whether one has run."""
        if not extracted_once:
            return since_extraction >= self.window_size
        return self.sliding and since_extraction >= self.stride


@dataclass
class GrowthUpdate:
    """What one update did: structure (on the key frames), estimate (Alg. 2 on them; None
    without observed points, or when the skeleton did not change), joint_ids (B,) stable ids, key_stamps (K,) the key frames'
    stamps, changed: whether the skeleton differs from the previous update's, changes:
    {'added': [names], 'removed': [names], 'reparented': [names], 'moved': [names]};
    model: the learned skeleton (None without Alg. 2)."""

    structure: SkeletalStructure
    estimate: JointEstimate | None
    joint_ids: np.ndarray
    key_stamps: np.ndarray
    changed: bool
    changes: dict = field(default_factory=dict)
    model: SkeletonModel | None = None

    @property
    def joint_names(self) -> list:
        return joint_names(self.joint_ids)


def joint_names(ids) -> list:
    """The published name of each joint id (as SkeletonModel.joint_names)."""
    return [f'joint_{int(i)}' for i in ids]


def aligned_poses(rest: np.ndarray, registered: np.ndarray, samples: np.ndarray) -> np.ndarray:
    """(F, S * 3): frames (F, M, 3) at the rest points `samples` (S,), each moved back onto
    the rest pose (M, 3) by its own best rigid motion (Kabsch)."""
    rest_samples = rest[samples]
    frames = registered[:, samples]
    rotations, translations = fit_rigid_segments(rest_samples, frames, np.zeros(len(samples), dtype=int), 1)
    # R^T (y - T) for every frame: the frame in the rest pose's placement
    aligned = np.einsum('fji,fsj->fsi', rotations[:, 0], frames - translations[:, 0, None, :])
    return aligned.reshape(len(frames), -1)


def farthest_poses(poses: np.ndarray, count: int) -> np.ndarray:
    """Indices of `count` rows of poses (F, D) picked greedily, each the farthest (RMS) from
    those already picked, starting with row 0; all rows, in order, when F <= count."""
    n = len(poses)
    if n <= count:
        return np.arange(n)
    picked = [0]
    nearest = np.linalg.norm(poses - poses[0], axis=1)
    for _ in range(count - 1):     # a loop over picked frames (<= count), vectorised over frames
        index = int(np.argmax(nearest))
        picked.append(index)
        nearest = np.minimum(nearest, np.linalg.norm(poses - poses[index], axis=1))
    return np.sort(np.array(picked))


class SkeletonGrowth:
    """One skeleton model over a sequence registered to one rest pose, updated per window.

    rest: (M, 3) rest points (m). structure_params.max_key_frames: the most frames the model
    is learned from (bounds memory and the time of an update); .joint_match_fraction: joints
    of two updates within this share of the subject size are the same joint. Joint ids
    follow the structure's joints (as the accumulator node keys them). Updates given the
    observed points also run Step 3 (Alg. 2) with joint_params when the skeleton changed
    (as the joint node, which gets only changed structures).

        >>> growth = SkeletonGrowth(rest)
        >>> update = growth.update(stamps, registered, observed)   # per window
        >>> update.joint_names, update.changes
    """

    def __init__(self, rest: np.ndarray, structure_params: StructureParams | None = None,
                 joint_params: JointParams | None = None, first_id: int = 0):
        self.rest = np.asarray(rest, dtype=np.float64)
        # ids start here: a node that starts a new skeleton (a new rest pose) gives it ids
        # the previous one never used, so a name never means two joints to a consumer
        self.first_id = int(first_id)
        self.structure_params = structure_params or StructureParams()
        self.joint_params = joint_params or JointParams()
        self.max_key_frames = self.structure_params.max_key_frames
        size = float(np.linalg.norm(np.ptp(self.rest, axis=0)))
        self.match_radius = self.structure_params.joint_match_fraction * size
        self._samples = np.unique(np.linspace(0, len(self.rest) - 1, min(POSE_SAMPLES, len(self.rest))).astype(int))
        self.key_stamps = np.empty(0, dtype=np.int64)
        self.key_registered = np.empty((0, len(self.rest), 3), dtype=np.float32)
        self.key_observed = []
        self._key_poses = np.empty((0, 3 * len(self._samples)))
        self.known_positions = np.empty((0, 3))     # rest-frame position of every joint id ever seen
        self.known_members = np.empty((0, len(self.rest)), dtype=bool)   # and its child bone's rest points
        self.ids = np.empty(0, dtype=int)           # ids of the current joints
        self.parent_ids = np.empty(0, dtype=int)
        self.last = None

    def add_frames(self, stamps, registered: np.ndarray, observed: list | None = None) -> None:
        """Let frames (stamps (F,), registered (F, M, 3), observed F arrays (N_t, 3) or None)
        compete for the key frames. Non-finite frames are skipped."""
        registered = np.asarray(registered, dtype=np.float32)
        if registered.ndim != 3 or registered.shape[1:] != self.rest.shape:
            raise ValueError(f'registered frames must be (F, {len(self.rest)}, 3), got {registered.shape}')
        stamps = np.asarray(stamps, dtype=np.int64)
        if len(stamps) != len(registered) or (observed is not None and len(observed) != len(registered)):
            raise ValueError('stamps, registered and observed must have one entry per frame')
        finite = np.isfinite(registered).all(axis=(1, 2)) & ~np.isin(stamps, self.key_stamps)
        if not finite.any():
            return
        new = np.flatnonzero(finite)
        poses = np.vstack([self._key_poses, aligned_poses(self.rest, registered[new].astype(np.float64),
                                                           self._samples)])
        stamps_all = np.concatenate([self.key_stamps, stamps[new]])
        registered_all = np.concatenate([self.key_registered, registered[new]])
        if observed is not None:
            observed_all = list(self.key_observed) + [np.asarray(observed[i], dtype=np.float32) for i in new]
        else:
            observed_all = [None] * len(stamps_all)
        keep = farthest_poses(poses, self.max_key_frames)
        order = keep[np.argsort(stamps_all[keep], kind='stable')]
        self.key_stamps, self.key_registered = stamps_all[order], registered_all[order]
        self.key_observed = [observed_all[i] for i in order]
        self._key_poses = poses[order]

    def update(self, stamps, registered: np.ndarray, observed: list | None = None) -> GrowthUpdate:
        """Add a window (see add_frames; none if stamps is empty) and learn the model again on
        the key frames; seconds_ then holds the time of Step 2 and Step 3.

        Raises StructureError when the key frames show no articulation (yet)."""
        if len(stamps):
            self.add_frames(stamps, registered, observed)
        window = self.key_registered.astype(np.float64)
        started = time.perf_counter()
        structure = extract_structure(self.rest, window, self.structure_params,
                                      None if self.last is None else self.last.structure.labels)
        self.seconds_ = {'structure': time.perf_counter() - started, 'joints': 0.0}
        # joint ids and changes from the structure's joints, as the accumulator node keys them
        joints, parents = structure.joints, structure.parents
        previous = dict(zip(self.ids.tolist(), zip(self.parent_ids.tolist(), self._current_positions())))
        members = np.arange(len(parents))[:, None] == structure.labels[None, :]        # (B, M) child bone points
        ids = self._assign_ids(joints, members, int(np.flatnonzero(parents < 0)[0]))
        parent_ids = np.where(parents >= 0, ids[np.maximum(parents, 0)], -1)
        changes = self._changes(previous, ids, parent_ids, joints)
        self.ids, self.parent_ids = ids, parent_ids
        self.known_positions[ids] = joints
        self.known_members[ids] = members
        changed = any(changes.values()) or self.last is None
        # Step 3 (Alg. 2) only for a skeleton that changed: the joint node runs it only on
        # the structures the accumulator publishes, which are the changed ones
        estimate = model = None
        if changed and all(o is not None for o in self.key_observed):
            started = time.perf_counter()
            estimate = JointEstimation(self.joint_params).fit(self.rest, window, self.key_observed, structure)
            self.seconds_['joints'] = time.perf_counter() - started
            model = estimate.model(self.rest, structure.labels, ids + self.first_id)
        self.last = GrowthUpdate(structure, estimate, ids + self.first_id, self.key_stamps.copy(), changed, changes,
                                 model)
        return self.last

    # ------------------------------------------------------------------------------------
    @property
    def next_id(self) -> int:
        """The first id this skeleton has not used (a next skeleton's first_id)."""
        return self.first_id + len(self.known_positions)

    def _current_positions(self):
        return [self.known_positions[i] for i in self.ids]

    def _assign_ids(self, joints: np.ndarray, members: np.ndarray, root: int) -> np.ndarray:
        """(B,) ids: the root keeps the root's id (its joint is the root bone's centre, which
        moves when the root bone grows or shrinks); each other joint is matched to a known one
        by its position and its child bone's points (members (B, M)): the cost is the smaller
        of distance / match_radius and (1 - Jaccard overlap of the child bones) + distance /
        (2 match_radius), and a match costs at most 1 (within the radius; or the same bone
        up to twice as far). The bone keeps a joint's identity when the joint solve moves it
        by more than the radius between updates; the position, when the tree turns the edge
        round (the joint is then stored on the other bone)."""
        ids = np.full(len(joints), -1)
        previous_root = self.ids[self.parent_ids < 0] if len(self.ids) else []
        if len(previous_root):
            ids[root] = previous_root[0]
        if len(self.known_positions):
            distance = np.linalg.norm(joints[:, None, :] - self.known_positions[None, :, :], axis=2)
            common = members.astype(float) @ self.known_members.T.astype(float)          # (B, K)
            union = members.sum(axis=1)[:, None] + self.known_members.sum(axis=1)[None, :] - common
            cost = np.minimum(distance / self.match_radius,
                              (1.0 - common / np.maximum(union, 1.0)) + distance / (2.0 * self.match_radius))
            if len(previous_root):
                cost[root] = np.inf
                cost[:, previous_root[0]] = np.inf
            rows, cols = gated_assignment(cost, 1.0)
            free = ids[rows] < 0
            ids[rows[free]] = cols[free]
        new = np.flatnonzero(ids < 0)
        ids[new] = len(self.known_positions) + np.arange(len(new))
        self.known_positions = np.vstack([self.known_positions, joints[new]])
        self.known_members = np.vstack([self.known_members, members[new]])
        return ids

    def _changes(self, previous: dict, ids, parent_ids, joints) -> dict:
        now = set(ids.tolist())
        added = sorted(now - set(previous))
        removed = sorted(set(previous) - now)
        reparented, moved = [], []
        for joint_id, parent_id, position in zip(ids.tolist(), parent_ids.tolist(), joints):
            if joint_id in previous:
                old_parent, old_position = previous[joint_id]
                if old_parent != parent_id:
                    reparented.append(joint_id)
                if np.linalg.norm(position - old_position) > 0.5 * self.match_radius:
                    moved.append(joint_id)
        def names(internal):
            return joint_names(np.asarray(internal, dtype=int) + self.first_id)
        return {'added': names(added), 'removed': names(removed), 'reparented': names(reparented),
                'moved': names(moved)}
