"""The per-frame step (core/stream.py) that `run` and the registration node share: the
subject found in each frame, the rest-pose gate, the rest pose, Alg. 1; and the order of
a camera's stamps."""
import numpy as np
import pytest

from skel_extract_ros.core.registration import STATUS_OK, RegistrationParams
from skel_extract_ros.core.rest_pose import RestPoseError, RestPoseParams, spread
from skel_extract_ros.core.sequence import SequenceRegistration
from skel_extract_ros.core.stream import (ORDER_NEW_FRAME_ID, ORDER_REPEATED, ORDER_WENT_BACK, WAIT_FEW_POINTS,
                                          WAIT_NOBODY, WAIT_REST_POSE_FAILED, FrameRegistrar, StampOrder,
                                          SubjectFinder, split_layout)
from skel_extract_ros.sim import generate_sequence

N_POINTS = 400


@pytest.fixture(scope='module')
def walk_in():
    """The upper body in a room, walking into the view over the first 6 frames."""
    return generate_sequence('upper_body', 12, scene='room', seed=6, enter_frames=6, progress=False)


def test_stamps_in_order_repeated_back_and_a_new_frame_id():
    order = StampOrder()
    assert order(100, 'cam') is None                       # the first frame
    assert order(133, 'cam') is None
    assert order(133, 'cam') == ORDER_REPEATED             # not counted as seen
    assert order(166, 'cam') is None
    assert order(50, 'cam') == ORDER_WENT_BACK             # a bag looped
    assert order(83, 'cam') is None                        # in order again after it
    assert order(116, 'other') == ORDER_NEW_FRAME_ID


def test_the_step_waits_for_somebody_then_builds_the_rest_pose_and_registers(walk_in):
    """choice_frames 1 (the paper): nobody in view first (the room only): the gate says
    so and nothing is registered; the first frame with the whole subject becomes the rest
    pose and is registered at once; later frames are registered from the previous one, or
    from the points given."""
    finder = SubjectFinder()
    registrar = FrameRegistrar(RegistrationParams(), RestPoseParams(n_points=N_POINTS, choice_frames=1))
    steps = []
    for index, cloud in enumerate(walk_in.clouds):
        subject = finder(*split_layout(cloud))
        answered = registrar(subject.observed, subject.segmentation, frame=index)
        assert [step.frame for step in answered] == [index]      # every frame answered at once
        steps += answered
    statuses = [step.status for step in steps]
    assert statuses[0] == WAIT_NOBODY and steps[0].result is None
    built = [i for i, step in enumerate(steps) if step.rest_pose_built]
    assert len(built) == 1 and all(step.result is None for step in steps[:built[0]])
    assert all(step.status == STATUS_OK for step in steps[built[0]:])
    assert registrar.rest_pose is not None and len(registrar.rest_pose.points) == N_POINTS
    assert steps[built[0]].seconds_rest_pose > 0 and not steps[-1].started_from_given
    # registered from given points: the step says so, and the result is a registration
    last = steps[-1].result.points
    subject = finder(*split_layout(walk_in.clouds[-1]))
    again, = registrar(subject.observed, subject.segmentation, start_points=last)
    assert again.started_from_given and again.status == STATUS_OK
    assert np.median(np.linalg.norm(again.result.points - last, axis=1)) < 0.02


@pytest.fixture(scope='module')
def opening_clouds():
    """The whole body, in view from the second frame, opening up over the first frames
    (the feet touch the image border from the sixth)."""
    return generate_sequence('human', 10, seed=3, progress=False).clouds


@pytest.fixture(scope='module')
def opening(opening_clouds):
    finder = SubjectFinder()
    return [finder(*split_layout(cloud)) for cloud in opening_clouds]


def _distance_to(points, cloud):
    from scipy.spatial import cKDTree
    return cKDTree(cloud).query(points)[0]


def test_the_rest_pose_is_the_most_spread_out_held_frame_and_the_held_frames_are_registered_both_ways(
        opening, opening_clouds):
    """The body opens up over the first frames: the frames from the first one in view are
    held, the rest pose is built from the most spread-out of those wholly in view (not the
    first), and every
    held frame is registered, the earlier ones backward from it: each registered frame lies
    on its own subject."""
    subjects = opening
    registrar = FrameRegistrar(RegistrationParams(), RestPoseParams(n_points=N_POINTS, choice_frames=8))
    answered = [registrar(s.observed, s.segmentation, frame=i) for i, s in enumerate(subjects)]
    first = next(i for i, steps in enumerate(answered) if not steps)
    held = range(first, first + 8)
    assert all(answered[i] == [] for i in held[:-1])                   # held: no answer yet
    steps = answered[held[-1]]
    assert [step.frame for step in steps] == list(held)                 # then all, in order
    whole = [i for i in held if not subjects[i].segmentation.touches_border]     # what the gate lets through
    chosen = [step.frame for step in steps if step.rest_pose_built]
    assert chosen == [max(whole, key=lambda i: spread(subjects[i].observed))] and chosen[0] != first
    assert all(step.status == STATUS_OK for step in steps)
    for step in steps:
        on_subject = _distance_to(step.result.points, subjects[step.frame].observed)
        assert np.median(on_subject) < 0.01, (step.frame, np.median(on_subject))
    # after the held frames: one frame, one answer, from the last held frame
    later, = answered[held[-1] + 1]
    assert later.frame == held[-1] + 1 and later.status == STATUS_OK
    # `run`'s registration makes the same choice and says which frame it was
    sequence = SequenceRegistration(RegistrationParams(), RestPoseParams(n_points=N_POINTS, choice_frames=8))
    sequence.register(opening_clouds)
    assert sequence.rest_frame_ == chosen[0] and (sequence.statuses_[held] == STATUS_OK).all()


def test_flush_chooses_from_the_frames_held_so_far_and_a_failed_choice_starts_over(opening):
    """A stream that ends before choice_frames: flush gives every held frame's step. When
    no held frame gives a rest pose, each says why, and the next frame starts a new choice."""
    subjects = opening
    whole = [i for i, s in enumerate(subjects) if s.segmentation.status == 'subject']
    registrar = FrameRegistrar(RegistrationParams(), RestPoseParams(n_points=N_POINTS, choice_frames=60))
    for i in whole[:4]:
        assert registrar(subjects[i].observed, subjects[i].segmentation, frame=i) == []
    steps = registrar.flush()
    assert [step.frame for step in steps] == whole[:4] and sum(step.rest_pose_built for step in steps) == 1
    assert all(step.status == STATUS_OK for step in steps) and registrar.flush() == []

    def failing(points, params):
        raise RestPoseError('degenerate surface')
    registrar = FrameRegistrar(RegistrationParams(), RestPoseParams(n_points=N_POINTS, choice_frames=2),
                               build_rest_pose=failing)
    assert registrar(subjects[whole[0]].observed, subjects[whole[0]].segmentation, frame=0) == []
    steps = registrar(subjects[whole[1]].observed, subjects[whole[1]].segmentation, frame=1)
    assert [(step.frame, step.status, step.error) for step in steps] == \
        [(0, WAIT_REST_POSE_FAILED, 'degenerate surface'), (1, WAIT_REST_POSE_FAILED, 'degenerate surface')]
    assert registrar.rest_pose is None and registrar.held == []
    assert registrar(subjects[whole[2]].observed, subjects[whole[2]].segmentation, frame=2) == []


def test_too_few_points_wait_and_reset_waits_for_a_new_rest_pose(walk_in):
    finder = SubjectFinder()
    registrar = FrameRegistrar(RegistrationParams(), RestPoseParams(n_points=N_POINTS, choice_frames=1))
    subjects = [finder(*split_layout(cloud)) for cloud in walk_in.clouds]
    whole = next(s for s in subjects[6:] if s.segmentation.status == 'subject')
    step, = registrar(whole.observed[:50], whole.segmentation)
    assert step.status == WAIT_FEW_POINTS and registrar.rest_pose is None
    assert registrar(whole.observed, whole.segmentation)[0].rest_pose_built
    registrar.reset()
    assert registrar.rest_pose is None
    assert registrar(whole.observed, whole.segmentation)[0].rest_pose_built
