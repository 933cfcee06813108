"""Geodesic extremities (core.extremities) on hand-made bodies: the limbs' ends found from the
body's centre at any scale, a limb touching the body or a box-like trunk's corner not taken
for an end, the matching of the model's ends to a frame's, and the registration's landmarks
pulling back an arm slid along itself."""
import numpy as np

from skel_extract_ros.core.extremities import Extremities, find_extremities, match_extremities
from skel_extract_ros.core.registration import NonRigidRegistration, RegistrationParams

TORSO_CENTRE = np.array([0.0, 0.0, 0.1])   # about where a body's centroid lies, above the hips
# capsules (start, end, radius), m: torso, neck, head, arms, legs; ends are the limbs' far ends
BODY = [((0.0, 0.0, 0.0), (0.0, 0.0, 0.5), 0.14),
        ((0.0, 0.0, 0.5), (0.0, 0.0, 0.7), 0.045),
        ((0.0, 0.0, 0.76), (0.0, 0.0, 0.8), 0.07),
        ((0.14, 0.0, 0.45), (0.75, 0.0, 0.45), 0.05),
        ((-0.14, 0.0, 0.45), (-0.75, 0.0, 0.45), 0.05),
        ((0.08, 0.0, 0.0), (0.1, 0.0, -0.85), 0.07),
        ((-0.08, 0.0, 0.0), (-0.1, 0.0, -0.85), 0.07)]
ENDS = np.array([[0.0, 0.0, 0.87], [0.8, 0.0, 0.45], [-0.8, 0.0, 0.45], [0.1, 0.0, -0.92], [-0.1, 0.0, -0.92]])


def _depth_inside(points, capsules):
    """(N,) m: how far each point (N, 3) lies inside the union of capsules (negative: outside),
    the largest of each capsule's radius minus the point's distance to its axis segment."""
    starts = np.array([c[0] for c in capsules], float)
    ends = np.array([c[1] for c in capsules], float)
    radii = np.array([c[2] for c in capsules])
    along = ends - starts
    t = np.clip(np.einsum('pcj,cj->pc', points[:, None] - starts, along) / np.sum(along ** 2, axis=1), 0.0, 1.0)
    return (radii - np.linalg.norm(points[:, None] - (starts + t[..., None] * along), axis=2)).max(axis=1)


def _solid(capsules, spacing=0.02, jitter=0.0, seed=0):
    """Points (N, 3) on a grid of `spacing` m inside the union of capsules, jittered."""
    starts = np.array([c[0] for c in capsules], float)
    ends = np.array([c[1] for c in capsules], float)
    radii = np.array([c[2] for c in capsules])
    low = np.minimum(starts, ends).min(axis=0) - radii.max()
    high = np.maximum(starts, ends).max(axis=0) + radii.max()
    axes = [np.arange(lo, hi, spacing) for lo, hi in zip(low, high)]
    grid = np.stack(np.meshgrid(*axes, indexing='ij'), axis=-1).reshape(-1, 3)
    points = grid[_depth_inside(grid, capsules) >= 0.0]
    return points + np.random.default_rng(seed).normal(0.0, jitter, points.shape)


def _shell(capsules, spacing):
    """The surface of the union of capsules as points (N, 3): the grid points of `spacing` m
    within one spacing inside it, about area / spacing^2 of them (a camera sees a surface,
    and its density is what the preprocessing sets)."""
    points = _solid(capsules, spacing)
    return points[_depth_inside(points, capsules) < spacing]


def _extremities(points, scale=1.0):
    """find_extremities from the point nearest the torso's centre."""
    centre = int(np.argmin(np.linalg.norm(points - TORSO_CENTRE * scale, axis=1)))
    return find_extremities(points, centre)


def test_the_limbs_ends_are_found_from_the_centre_at_any_scale():
    """A body of capsules: the five ends (head, hands, feet) and nothing else, each tip's
    region at the end of its own limb; the same body a tenth the size (a hand's scale) gives
    the same ends, so the fractions that define an end carry no unit."""
    for scale in (1.0, 0.1):
        points = _solid([(np.multiply(a, scale), np.multiply(b, scale), r * scale) for a, b, r in BODY],
                        spacing=0.02 * scale)
        found = _extremities(points, scale)
        assert len(found) == 5, (scale, len(found))
        distance = np.linalg.norm(found.centroids[:, None] - ENDS[None] * scale, axis=2)
        assert sorted(np.argmin(distance, axis=1)) == [0, 1, 2, 3, 4]
        # the cap is the limb's last tenth of its depth: its centroid a few cm from the end
        assert distance.min(axis=1).max() < 0.08 * scale, distance.min(axis=1)


def test_a_blunt_ends_region_stays_put_under_noise():
    """The head's end is a round cap: which point is farthest changes with millimetres of
    noise, the cap's centroid (the part matched) moves by far less than the cap's size."""
    centroids, tips = [], []
    for seed in range(4):
        points = _solid(BODY, jitter=0.003, seed=seed)
        found = _extremities(points)
        head = np.argmin(np.linalg.norm(found.centroids - ENDS[0], axis=1))
        centroids.append(found.centroids[head])
        tips.append(points[found.tips[head]])

    def spread(positions):
        return np.linalg.norm(np.array(positions) - np.mean(positions, axis=0), axis=1).max()
    assert spread(centroids) < 0.02 and spread(centroids) < 0.3 * spread(tips), (spread(centroids), spread(tips))


def test_a_hand_on_the_hip_is_no_end():
    """An arm bent back until its hand touches the torso: the surface joins there, the hand is
    near the centre along it, and only the other four ends are found."""
    bent = BODY[:4] + [((-0.14, 0.0, 0.45), (-0.45, 0.0, 0.2), 0.05), ((-0.45, 0.0, 0.2), (-0.16, 0.0, 0.05), 0.05)] \
        + BODY[5:]
    found = _extremities(_solid(bent))
    assert len(found) == 4, len(found)
    assert np.linalg.norm(found.centroids - [-0.16, 0.0, 0.05], axis=1).min() > 0.2


def test_a_corner_of_a_box_like_trunk_is_no_end():
    """A box-shaped trunk with one arm (the built-in stress subject's shape): the box's
    corners are as far along the surface as the hand, but the section 20-30 % of their depth
    away is as wide as the trunk, not a limb's; only the hand is kept. Without the slenderness
    rule the corners are ends too, and which corner is farthest depends on what hides it."""
    grid = np.arange(-0.5, 0.5001, 0.02)
    cube = np.stack(np.meshgrid(grid, grid, grid, indexing='ij'), axis=-1).reshape(-1, 3)
    box = cube[(np.abs(cube[:, 0]) <= 0.15) & (np.abs(cube[:, 1]) <= 0.1) & (np.abs(cube[:, 2]) <= 0.25)]
    arm = _solid([((0.15, 0.0, 0.2), (0.45, 0.0, 0.2), 0.05)])
    points = np.vstack([box, arm])
    centre = int(np.argmin(np.linalg.norm(points, axis=1)))
    kept = find_extremities(points, centre)
    assert len(kept) == 1 and np.linalg.norm(kept.centroids[0] - [0.5, 0.0, 0.2]) < 0.06, kept.centroids
    assert len(find_extremities(points, centre, max_width=np.inf)) > 1


def _ends(centroids, depth, sizes=None):
    """Hand-made ends at centroids (K, 3) m with geodesic depths (K,) m, each a region of
    `sizes` points (default 30) all at its centroid, its limb its own region -> (Extremities,
    their points (sum(sizes), 3))."""
    centroids = np.asarray(centroids, float).reshape(-1, 3)
    sizes = [30] * len(centroids) if sizes is None else sizes
    bounds = np.concatenate([[0], np.cumsum(sizes)]).astype(int)
    regions = [np.arange(a, b) for a, b in zip(bounds[:-1], bounds[1:])]
    limbs = np.zeros((len(centroids), bounds[-1]), dtype=bool)
    for k, region in enumerate(regions):
        limbs[k, region] = True
    points = np.repeat(centroids, sizes, axis=0)
    return Extremities(np.arange(len(centroids)), np.asarray(depth, float), regions, centroids, limbs, 0.01), points


def test_matching_is_one_to_one_between_the_same_limbs_ends():
    """Model ends (where the frame starts them) against a frame's: each pairs with the
    nearest partner that is the same limb's end; a truncated limb (its end at two thirds of
    the depth: a foot behind the other leg), a partner beyond the reach, and an end the model
    saw cut short (a third of the points) pair with nothing; two model ends never share a
    partner, and an observed end that two model ends are about as near gets neither."""
    model, starts = _ends([[0.0, 0.0, 0.0], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0], [2.0, 0.0, 0.0]],
                          np.ones(5), [30, 30, 30, 30, 10])
    observed, _ = _ends([[0.05, 0.0, 0.0],          # model 0's, moved 5 cm
                      [1.0, 0.1, 0.0],           # model 1's
                      [0.0, 1.05, 0.0],          # near model 2, but a truncated limb
                      [0.0, 0.0, 1.5],           # model 3's depth, 50 cm away: beyond reach
                      [2.05, 0.0, 0.0]],         # model 4's, which the model saw cut short
                     [1.02, 0.95, 0.66, 1.0, 1.0])
    assert sorted(match_extremities(model, starts, observed, reach=0.3)) == [(0, 0), (1, 1)]
    # a still foot 20 cm from the other, swinging one: within a wide reach, not a tight one
    foot, foot_points = _ends([[0.0, 0.0, 0.0]], [1.0])
    swinging, _ = _ends([[0.2, 0.0, 0.0]], [1.0])
    assert match_extremities(foot, foot_points, swinging, reach=0.3) == [(0, 0)]
    assert match_extremities(foot, foot_points, swinging, reach=0.1) == []
    # an observed end nearest another part of the model (a forearm left behind beside the
    # trunk, a corner of the trunk that its own points explain) is not the left-behind end's,
    # however near
    hand, hand_points = _ends([[0.0, 0.0, -0.12]], [1.0])
    trunk = np.zeros((30, 3))
    beside = Extremities(hand.tips, hand.depth, hand.regions, hand.centroids,
                         np.concatenate([hand.limbs, np.zeros((1, 30), dtype=bool)], axis=1), hand.spacing)
    corner, _ = _ends([[0.0, 0.0, -0.02]], [1.0])
    assert match_extremities(beside, np.vstack([hand_points, trunk]), corner, reach=0.3) == []
    assert match_extremities(hand, hand_points, corner, reach=0.3) == [(0, 0)]
    # two model ends near one observed end: the clearly nearer takes it, a near tie gets none
    for second, expected in ((0.3, [(0, 0)]), (0.12, [])):
        crowded, crowded_points = _ends([[0.0, 0.0, 0.0], [second, 0.0, 0.0]], np.ones(2))
        assert match_extremities(crowded, crowded_points, _ends([[0.05, 0.0, 0.0]], [1.0])[0],
                                 reach=0.3) == expected, second
    assert match_extremities(model, starts, _ends(np.zeros((0, 3)), [])[0], reach=0.3) == []


def test_ends_pair_across_sampling_densities():
    """The model's ends on a body's surface sampled at 3 cm against a frame of the same body
    sampled at 1.5 cm, four times as densely (a subject nearer the camera than in its rest
    frame): each end pairs with its own, since regions are compared by surface (points x
    spacing^2), not by point count, which differs fourfold."""
    model = _extremities(_shell(BODY, 0.03))
    frame = _extremities(_shell(BODY, 0.015))
    assert len(model) == len(frame) == 5, (len(model), len(frame))
    counts = [len(r) for r in frame.regions]
    assert np.median(counts) > 3 * np.median([len(r) for r in model.regions]), counts
    model_points = _shell(BODY, 0.03)
    pairs = match_extremities(model, model_points, frame, reach=0.1)
    assert len(pairs) == 5, pairs
    assert all(np.linalg.norm(model.centroids[k] - frame.centroids[l]) < 0.05 for k, l in pairs)


def test_the_landmarks_pull_an_arm_that_slid_along_itself():
    """The body registered to itself with one arm slid 6 cm out along its own axis: along the
    arm the data cannot tell the slide, only the arm's end can. With the extremity landmarks
    (`extremity_weight`) the end is matched to the frame's and pulled onto it, and the arm
    follows; without them the arm keeps much of the slide."""
    rest = _solid(BODY)
    arm_start, arm_end, radius = BODY[3]
    slid = [(np.add(arm_start, (0.06, 0.0, 0.0)), np.add(arm_end, (0.06, 0.0, 0.0)), radius)]
    observed = _solid(BODY[:3] + slid + BODY[4:])
    hand = np.linalg.norm(rest - ENDS[1], axis=1) < 0.15
    left = {}
    for weight in (0.0, 3.0):
        registration = NonRigidRegistration(rest, RegistrationParams(extremity_weight=weight))
        result = registration.register_frame(observed)
        assert result.status == 'ok'
        assert (result.landmarks > 0) == (weight > 0), result.landmarks
        left[weight] = abs(0.06 - np.mean(result.points[hand, 0] - rest[hand, 0]))
    assert left[3.0] < 0.5 * left[0.0] and left[3.0] < 0.02, left
