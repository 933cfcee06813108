"""Alg. 1 in a child process of the registration node, at a lower CPU priority once the
skeleton is tracked.

Why a process: registration is up to seconds of numpy calls on small arrays a frame, and
in the node's own process it holds the GIL most of the time, so the camera stage
(segmentation -> filtered_points, what the live path fits) waits for the GIL inside every
numpy call. In its own process it no longer shares a GIL, and its priority can be set
apart from the live path's: while the skeleton is learned, registration is all that
matters and runs at the node's priority; once the skeleton is tracked, `lower_priority`
makes the scheduler give a short CPU to learning, not to the live path (measured at 30 Hz
on 2 cores, bench/README.md "Registration in its own process").

No rclpy in this module; the child is spawned, not forked (forking a process that runs
DDS threads is not safe), and spawn imports the node's main module again in it, so rclpy
comes along (about 20 MB of the child's 112). The
NonRigidRegistration object is built in the node and sent over once per rest pose;
afterwards only the frame's observed points (N, 3) and its FrameResult cross.

The rest pose (Open3D's Poisson reconstruction) is built in a process of its own that ends
with it (`build_rest_pose`): Open3D costs a process 170 MB resident for as long as it
lives, and the node needs it once per rest pose.
"""
from __future__ import annotations

import multiprocessing
import os
import signal
from concurrent.futures import ProcessPoolExecutor
from concurrent.futures.process import BrokenProcessPool

import numpy as np

from ..core.registration import FrameResult, NonRigidRegistration
from ..core.rest_pose import RestPose, RestPoseParams

__all__ = ['BrokenProcessPool', 'RegistrationProcess', 'build_rest_pose']

# in the child: the registration of the current rest pose (its state moves frame to frame)
_registration: NonRigidRegistration | None = None


def _start_child() -> None:
    # Ctrl-C reaches the whole process group: the node, not the child, decides when it ends
    signal.signal(signal.SIGINT, signal.SIG_IGN)


def _install(registration: NonRigidRegistration) -> None:
    global _registration
    _registration = registration


def _register_frame(observed: np.ndarray) -> FrameResult:
    if _registration is None:
        raise RuntimeError('no registration installed in the registration process')
    return _registration.register_frame(observed)


class RegistrationProcess:
    """A NonRigidRegistration run in one spawned child process.

    niceness: what `lower_priority` adds to the child's nice value (0 = none; 19 = only
    idle CPU). The child starts at once (about a second of imports), not on the first frame,
    at the node's priority. Calls block the calling thread (not the GIL) until the child
    answers; a child that died (out of memory, killed) raises BrokenProcessPool from every
    later call, and `restart` gives a new one.
    """

    def __init__(self, niceness: int = 0):
        self.niceness = int(niceness)
        self._start()

    def _start(self) -> None:
        self._pool = ProcessPoolExecutor(max_workers=1, mp_context=multiprocessing.get_context('spawn'),
                                         initializer=_start_child)
        self.pid = self._pool.submit(os.getpid).result()
        self.lowered = False

    def lower_priority(self) -> None:
        """Add `niceness` to the child's nice value (once; a new child starts at the node's)."""
        if self.lowered or self.niceness == 0:
            return
        value = min(os.getpriority(os.PRIO_PROCESS, 0) + self.niceness, 19)
        # Linux keeps a nice value per thread: set it on every thread of the child (numpy's
        # BLAS threads were started before any call could); raising it needs no privilege
        try:
            for task in os.listdir(f'/proc/{self.pid}/task'):
                os.setpriority(os.PRIO_PROCESS, int(task), value)
        except (FileNotFoundError, ProcessLookupError):
            return       # the child is gone: the next call says so
        self.lowered = True

    @property
    def nice(self) -> int | None:
        """The child's nice value now (None if it is gone)."""
        try:
            return os.getpriority(os.PRIO_PROCESS, self.pid)
        except OSError:
            return None

    def install(self, registration: NonRigidRegistration) -> None:
        """Register the next frames with `registration` (a new rest pose)."""
        self._pool.submit(_install, registration).result()

    def register_frame(self, observed: np.ndarray) -> FrameResult:
        """observed: (N, 3) subject points, metres -> the FrameResult of Alg. 1 on it."""
        return self._pool.submit(_register_frame, np.ascontiguousarray(observed, dtype=np.float64)).result()

    def restart(self) -> None:
        """A new child at the node's priority (after BrokenProcessPool, or to learn a new
        skeleton first); it needs `install` again."""
        self._pool.shutdown(wait=False, cancel_futures=True)
        self._start()

    def close(self) -> None:
        self._pool.shutdown(wait=True, cancel_futures=True)


def build_rest_pose(observed: np.ndarray, params: RestPoseParams) -> RestPose:
    """RestPose.from_points(observed (N, 3) m, params) in a short-lived child process (a few
    seconds more than in-process: a Python start and the Open3D import). Raises what
    from_points raises (RestPoseError), or BrokenProcessPool if the child died."""
    with ProcessPoolExecutor(max_workers=1, mp_context=multiprocessing.get_context('spawn'),
                             initializer=_start_child) as pool:
        return pool.submit(RestPose.from_points, np.ascontiguousarray(observed, dtype=np.float64),
                           params).result()
