"""Alg. 1 in the registration node's child process: the same results as in-process, a
priority that drops only when asked, and a new child after the old one died."""
import os
import signal
import threading
import time

import numpy as np
import pytest

from skel_extract_ros.core.registration import NonRigidRegistration, RegistrationParams
from skel_extract_ros.nodes.registration_process import ChildProcessDied, RegistrationProcess, RestPoseProcess

from two_bone import two_bone_sequence


@pytest.fixture
def sequence():
    rest, frames, *_ = two_bone_sequence(n_frames=6, noise=0.002)
    return rest, frames


@pytest.fixture
def child():
    process = RegistrationProcess(niceness=5)
    yield process
    process.close()


def test_the_child_registers_exactly_as_the_node_would(sequence, child):
    """The held frames' two chains (backward from the rest pose's frame, forward from it),
    registered at once on the child's threads, give what one registration after the other
    gives in the node's process, and the frames after go on from the forward chain's last."""
    rest, frames = sequence
    params = RegistrationParams()
    backward, forward = [(frames[2], None), (frames[1], None), (frames[0], None)], [(frames[3], None)]
    earlier = NonRigidRegistration(rest, params)
    here = NonRigidRegistration(rest, params)
    expected = [[earlier.register_frame(observed) for observed, _ in backward], [here.register_frame(frames[3])]]
    outcomes = child.register_chains(NonRigidRegistration(rest, params), [backward, forward])
    assert child.pid != os.getpid()
    assert [len(chain) for chain in outcomes] == [3, 1]
    for chain, expected_chain in zip(outcomes, expected):
        for (result, seconds), wanted in zip(chain, expected_chain):
            assert result.status == wanted.status and seconds > 0
            np.testing.assert_array_equal(result.points, wanted.points)
    for observed in frames[4:]:
        expected, result = here.register_frame(observed), child.register_frame(observed)
        assert result.status == expected.status
        # the child keeps its state from frame to frame: each frame starts from the last one
        np.testing.assert_array_equal(result.points, expected.points)


def test_priority_drops_once_asked_and_a_new_child_starts_at_the_node_s(child):
    base = os.getpriority(os.PRIO_PROCESS, 0)
    assert child.nice == base and not child.lowered and not child.in_idle_class
    child.make_nicer()
    child.make_nicer()                              # once, not twice
    tasks = os.listdir(f'/proc/{child.pid}/task')
    assert len(tasks) >= 1
    assert all(os.getpriority(os.PRIO_PROCESS, int(task)) == min(base + 5, 19) for task in tasks)
    assert all(os.sched_getscheduler(int(task)) == os.SCHED_OTHER for task in tasks)
    child.restart()
    assert child.nice == base and not child.lowered


def test_with_sched_idle_every_thread_of_the_child_enters_the_idle_class_and_a_new_child_does_not(sequence):
    rest, frames = sequence
    child = RegistrationProcess(niceness=5, sched_idle=True)
    try:
        child.register_chains(NonRigidRegistration(rest, RegistrationParams()), [])
        assert os.sched_getscheduler(child.pid) == os.SCHED_OTHER and not child.in_idle_class
        child.make_nicer()
        tasks = os.listdir(f'/proc/{child.pid}/task')
        assert all(os.sched_getscheduler(int(task)) == os.SCHED_IDLE for task in tasks)
        assert child.in_idle_class and child.nice == min(os.getpriority(os.PRIO_PROCESS, 0) + 5, 19)
        assert os.sched_getscheduler(0) == os.SCHED_OTHER          # the node itself is untouched
        assert child.register_frame(frames[0]).points.shape == rest.shape   # and it still works
        child.restart()
        assert not child.in_idle_class and not child.lowered
    finally:
        child.close()


def test_a_killed_child_is_reported_and_restart_gives_a_working_one(sequence, child):
    rest, frames = sequence
    child.register_chains(NonRigidRegistration(rest, RegistrationParams()), [])
    os.kill(child.pid, signal.SIGKILL)
    with pytest.raises(ChildProcessDied):
        child.register_frame(frames[0])
    child.restart()
    with pytest.raises(RuntimeError, match='no registration in the registration process'):
        child.register_frame(frames[0])
    child.register_chains(NonRigidRegistration(rest, RegistrationParams()), [])
    assert child.register_frame(frames[0]).status == 'ok'


def test_close_ends_a_child_that_gets_no_cpu_and_the_call_waiting_on_it_fails(sequence, child):
    """A child that gets no CPU (stopped here, as one in the idle class can be on a busy
    machine) is killed once close's timeout has passed, and the call waiting on it raises
    ChildProcessDied instead of waiting for ever."""
    rest, frames = sequence
    child.register_chains(NonRigidRegistration(rest, RegistrationParams()), [])
    os.kill(child.pid, signal.SIGSTOP)
    outcome = []

    def register():
        try:
            child.register_frame(frames[0])
        except ChildProcessDied as error:
            outcome.append(error)
    caller = threading.Thread(target=register)
    caller.start()
    time.sleep(0.3)
    assert caller.is_alive()                   # waiting on the stopped child
    started = time.monotonic()
    child.close(timeout=0.5)
    caller.join(timeout=5.0)
    assert time.monotonic() - started < 3.0
    assert not caller.is_alive() and len(outcome) == 1
    with pytest.raises(ChildProcessError):     # ended and reaped
        os.waitpid(child.pid, os.WNOHANG)


def test_the_child_loads_neither_rclpy_nor_open3d(sequence, child):
    rest, frames = sequence
    child.register_chains(NonRigidRegistration(rest, RegistrationParams()), [])
    child.register_frame(frames[0])                   # answered: every import is done
    maps = open(f'/proc/{child.pid}/maps').read()
    assert 'numpy' in maps or 'libopenblas' in maps or 'scipy' in maps
    assert 'open3d' not in maps and 'rclpy' not in maps and 'librcl' not in maps


def test_the_rest_pose_is_built_in_a_warm_child_that_ends_with_it(human_clean):
    from skel_extract_ros.core.preprocess import Preprocessor
    from skel_extract_ros.core.rest_pose import RestPose, RestPoseError, RestPoseParams
    params = RestPoseParams(n_points=500)
    observed = Preprocessor()(human_clean.clouds[0].reshape(-1, 3))
    builder = RestPoseProcess()
    builder.warm()
    child = builder._child
    # the child imports Open3D before it is asked (while the node waits for the subject)
    deadline = time.monotonic() + 60
    while 'open3d' not in open(f'/proc/{child.pid}/maps').read():
        assert time.monotonic() < deadline, 'the warm child never loaded Open3D'
        time.sleep(0.05)
    builder.warm()
    assert builder._child is child                              # warm is idempotent
    with pytest.raises(RestPoseError, match='usable points'):
        builder.build(observed[:50], params)
    assert builder._child is child                              # no rest pose: kept for the next frame
    here, there = RestPose.from_points(observed, params), builder.build(observed, params)
    np.testing.assert_array_equal(there.points, here.points)     # the same deterministic steps
    assert builder._child is None                               # ended with its rest pose,
    child._process.wait(timeout=30)                             # in the background: reaped, exit 0
    assert child._process.returncode == 0
    there = builder.build(observed, params)                      # a new child when asked again
    np.testing.assert_array_equal(there.points, here.points)
    builder.close()
