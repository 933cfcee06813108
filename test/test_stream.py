"""The per-frame step (core/stream.py) that `run` and the registration node share: the
subject found in each frame, the rest-pose gate, the rest pose, Alg. 1; and the order of
a camera's stamps."""
import numpy as np
import pytest

from skel_extract_ros.core.registration import STATUS_OK, RegistrationParams
from skel_extract_ros.core.rest_pose import RestPoseParams
from skel_extract_ros.core.stream import (ORDER_NEW_FRAME_ID, ORDER_REPEATED, ORDER_WENT_BACK, WAIT_FEW_POINTS,
                                          WAIT_NOBODY, FrameRegistrar, StampOrder, SubjectFinder, split_layout)
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
    """Nobody in view first (the room only): the gate says so and nothing is registered;
    the first frame with the whole subject becomes the rest pose and is registered at
    once; later frames are registered from the previous one, or from the points given."""
    finder = SubjectFinder()
    registrar = FrameRegistrar(RegistrationParams(), RestPoseParams(n_points=N_POINTS))
    steps = []
    for cloud in walk_in.clouds:
        subject = finder(*split_layout(cloud))
        steps.append(registrar(subject.observed, subject.segmentation))
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
    again = registrar(subject.observed, subject.segmentation, start_points=last)
    assert again.started_from_given and again.status == STATUS_OK
    assert np.median(np.linalg.norm(again.result.points - last, axis=1)) < 0.02


def test_too_few_points_wait_and_reset_waits_for_a_new_rest_pose(walk_in):
    finder = SubjectFinder()
    registrar = FrameRegistrar(RegistrationParams(), RestPoseParams(n_points=N_POINTS))
    subjects = [finder(*split_layout(cloud)) for cloud in walk_in.clouds]
    whole = next(s for s in subjects[6:] if s.segmentation.status == 'subject')
    step = registrar(whole.observed[:50], whole.segmentation)
    assert step.status == WAIT_FEW_POINTS and registrar.rest_pose is None
    assert registrar(whole.observed, whole.segmentation).rest_pose_built
    registrar.reset()
    assert registrar.rest_pose is None
    assert registrar(whole.observed, whole.segmentation).rest_pose_built
