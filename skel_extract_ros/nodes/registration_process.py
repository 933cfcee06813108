"""Alg. 1 in a child process of the registration node, at a lower CPU priority once the
skeleton is tracked; the rest pose in a child process that ends with it.

Why a process: registration is up to seconds of numpy calls on small arrays a frame, and
in the node's own process it holds the GIL most of the time, so the camera stage
(segmentation -> filtered_points, what the live path fits) waits for the GIL inside every
numpy call. In its own process it no longer shares a GIL, and its priority can be set
apart from the live path's: while the skeleton is learned, registration is all that
matters and runs at the node's priority; once the skeleton is tracked, `make_nicer`
makes the scheduler give a short CPU to learning, not to the live path (nicer, and in the
idle scheduling class).

Why not multiprocessing: its spawn start imports the node's main module again in the child
(rclpy and the message packages, about 20 MB), adds a resource-tracker process (13 MB) and
its fork start is unsafe in a process running DDS threads. The child here is `python -m
skel_extract_ros.nodes.registration_process`: it imports numpy, scipy and the core modules
only (and nodes/worker.py, which imports only the standard library), reads (call,
arguments) pickles on stdin and answers (ok, value) pickles on stdout, and ends when its
stdin closes (the node ended or died). The NonRigidRegistration object
is built in the node and sent once per rest pose, with the frames held for its choice
(`register_chains`: their two chains on two threads of the child); afterwards only the
frame's observed points (N, 3) and its FrameResult (~50 kB) cross.

The rest pose (Open3D's Poisson reconstruction) is built in a child of its own that ends
with it (`RestPoseProcess`): Open3D costs a process 170 MB resident for as long as it
lives, and the node needs it once per rest pose. That child starts when a rest pose is
wanted (node start, start over), not when the subject's first whole frame comes: its Python
start and Open3D import (seconds) then happen while the segmentation still waits for motion, not on the way to the
first skeleton.
"""
from __future__ import annotations

import importlib
import os
import pickle
import signal
import subprocess
import sys
import threading
import time

import numpy as np

from ..core.registration import FrameResult, NonRigidRegistration, register_chains
from ..core.rest_pose import RestPose, RestPoseParams
from .worker import Worker, lower_priority

# The rest pose child (290 MB resident, Open3D loaded) waits warm this long with nobody in
# view, then is ended until a region moves: an idle robot does not carry it for hours, and a
# subject who comes at once does not wait for its start
REST_POSE_IDLE_RELEASE_S = 10.0

__all__ = ['ChildProcessDied', 'RegistrationProcess', 'RestPoseProcess']


class ChildProcessDied(RuntimeError):
    """The child process ended (killed, out of memory) before it answered."""


class _Child:
    """One `python -m` child running _serve(); call() is one request and its answer."""

    def __init__(self, preload: tuple = ()):
        """preload: modules the child imports before it reads its first call."""
        # stderr stays the node's: a traceback of the child shows in the node's log
        self._process = subprocess.Popen([sys.executable, '-m', __name__, *preload], stdin=subprocess.PIPE,
                                         stdout=subprocess.PIPE, close_fds=True)
        self.pid = self._process.pid
        self._lock = threading.Lock()

    def call(self, name: str, *args):
        with self._lock:
            try:
                pickle.dump((name, args), self._process.stdin, protocol=pickle.HIGHEST_PROTOCOL)
                self._process.stdin.flush()
                ok, value = pickle.load(self._process.stdout)
            except (EOFError, OSError, ValueError, pickle.UnpicklingError) as error:
                # ValueError: its stdin was closed (`close`) while this call waited for the lock
                raise ChildProcessDied(f'the child process {self.pid} ended (exit code '
                                       f'{self._process.poll()})') from error
        if not ok:
            raise value
        return value

    def close(self, timeout: float = 10.0, background: bool = False) -> None:
        """Close its stdin once the call in progress is answered (it then ends) and reap it,
        killing it after `timeout` s of either wait: here, or with `background` in a daemon
        thread, for a caller that need not wait for the child's interpreter to end."""
        # a call in progress may be blocked writing to, or reading from, a child that gets no
        # CPU; closing stdin then would wait on that call: the child is killed instead, which
        # ends the call (ChildProcessDied)
        if self._lock.acquire(timeout=max(timeout, 0.0)):
            try:
                self._process.stdin.close()
            except OSError:
                pass
            finally:
                self._lock.release()
        else:
            self._process.kill()
        if background:
            _reaper().submit((self, timeout))
        else:
            self._reap(timeout)

    def _reap(self, timeout: float) -> None:
        try:
            self._process.wait(timeout)
        except subprocess.TimeoutExpired:
            self._process.kill()
            self._process.wait()


_REAPER = None


def _reaper() -> Worker:
    """The Worker that waits for children closed in the background (one for the process)."""
    global _REAPER
    if _REAPER is None:
        _REAPER = Worker(lambda item: item[0]._reap(item[1]), 'reaper', capacity=64, keep='oldest')
    return _REAPER


class RegistrationProcess:
    """A NonRigidRegistration run in one child process.

    niceness: what `make_nicer` adds to the child's nice value (0 = the priority is
    never lowered).
    sched_idle: `make_nicer` also puts the child in Linux's idle scheduling class
    (SCHED_IDLE): it runs when no other task wants the core. A nice value only shares the
    cores in proportion; a live-path thread that wakes while the nicer child runs still
    waits for the scheduler to preempt it.
    The child starts at once, at the node's priority. Calls block the calling
    thread (not the GIL) until the child answers; a child that died (out of memory, killed)
    raises ChildProcessDied, and `restart` gives a new one.
    """

    def __init__(self, niceness: int = 0, sched_idle: bool = False):
        self.niceness = int(niceness)
        self.sched_idle = bool(sched_idle)
        self._start()

    def _start(self) -> None:
        self._child = _Child()
        self.pid = self._child.pid
        self.lowered = False

    def make_nicer(self) -> None:
        """Add `niceness` to the child's nice value and, with `sched_idle`, put it in the
        idle scheduling class (once; a new child starts at the node's priority)."""
        if self.lowered or self.niceness == 0:     # 0: never lowered, nor put in the idle class
            return
        # on every thread of the child: Linux keeps a nice value and a policy per thread
        try:
            for task in os.listdir(f'/proc/{self.pid}/task'):
                lower_priority(int(task), self.niceness, self.sched_idle)
        except (FileNotFoundError, ProcessLookupError):
            return       # the child is gone: the next call says so
        self.lowered = True

    @property
    def in_idle_class(self) -> bool:
        """The child runs in the idle scheduling class (False if it is gone)."""
        try:
            return os.sched_getscheduler(self.pid) == os.SCHED_IDLE
        except (AttributeError, OSError):
            return False

    @property
    def nice(self) -> int | None:
        """The child's nice value now (None if it is gone)."""
        try:
            return os.getpriority(os.PRIO_PROCESS, self.pid)
        except OSError:
            return None

    def register_frame(self, observed: np.ndarray, start_points: np.ndarray | None = None,
                       stamp: float | None = None) -> FrameResult:
        """observed: (N, 3) subject points, metres -> the FrameResult of Alg. 1 on it;
        start_points (M, 3) and stamp (s): see NonRigidRegistration.register_frame."""
        return self._child.call('register_frame', np.ascontiguousarray(observed, dtype=np.float64),
                                None if start_points is None else np.asarray(start_points, dtype=np.float64),
                                stamp)

    def register_chains(self, registration: NonRigidRegistration, chains: list) -> list:
        """core.registration.register_chains in the child, on its threads: [[(FrameResult,
        seconds), ...] per chain]; the frames after go on from the last chain (no chains:
        `registration` is only installed)."""
        chains = [[(np.ascontiguousarray(observed, dtype=np.float64), stamp) for observed, stamp in chain]
                  for chain in chains]
        return self._child.call('register_chains', registration, chains)

    def restart(self) -> None:
        """A new child at the node's priority (after ChildProcessDied, or to learn a new
        skeleton first); it needs `register_chains` again."""
        self._child.close(timeout=0.0)
        self._start()

    def close(self, timeout: float = 10.0) -> None:
        """End the child: after the call in progress, or killed once `timeout` s have passed
        (a call waiting on it then raises ChildProcessDied)."""
        self._child.close(timeout)


class RestPoseProcess:
    """RestPose.from_points in a child process that has imported Open3D before it is asked.

    `warm` starts the child (idempotent); `build` builds one rest pose in it and ends it on
    success, handing its memory back. A frame that gives no rest pose (RestPoseError) keeps
    the child for the next frame.
    """

    def __init__(self):
        self._child: _Child | None = None
        self.starts = 0                   # children started so far
        self._somebody_at = time.monotonic()

    def while_waiting(self, somebody: bool) -> bool:
        """Before the rest pose: warm while a subject may come (somebody in view), ended after
        REST_POSE_IDLE_RELEASE_S s of nobody. True when it was ended now."""
        now = time.monotonic()
        if somebody:
            self._somebody_at = now
            self.warm()
        elif self.is_warm and now - self._somebody_at > REST_POSE_IDLE_RELEASE_S:
            self.close()
            return True
        return False

    @property
    def is_warm(self) -> bool:
        return self._child is not None

    def warm(self) -> None:
        """Start the child now, if there is none, so that `build` does not wait for it."""
        if self._child is None:
            self._child = _Child(preload=('open3d',))
            self.starts += 1

    def build(self, observed: np.ndarray, params: RestPoseParams) -> RestPose:
        """observed (N, 3) m -> RestPose.from_points(observed, params). Raises what
        from_points raises (RestPoseError), or ChildProcessDied (the next call starts a new
        child)."""
        self.warm()
        try:
            rest_pose = self._child.call('rest_pose', np.ascontiguousarray(observed, dtype=np.float64), params)
        except ChildProcessDied:
            self.close()
            raise
        # The child ends in the background: its ending (the interpreter and Open3D's memory
        # torn down) takes 0.16-0.27 s, and the rest pose is on the way to the first skeleton
        self._child.close(background=True)
        self._child = None
        return rest_pose

    def close(self, timeout: float = 10.0) -> None:
        """End the child, if there is one, as RegistrationProcess.close."""
        if self._child is not None:
            self._child.close(timeout)
            self._child = None


def _serve() -> None:
    """The child: answer calls until stdin closes."""
    # Ctrl-C reaches the whole process group: the node, not the child, decides when it ends
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    for module in sys.argv[1:]:
        importlib.import_module(module)
    requests, answers = sys.stdin.buffer, sys.stdout.buffer
    sys.stdout = sys.stderr            # a stray print must not corrupt the answers
    registration = None
    while True:
        try:
            name, args = pickle.load(requests)
        except EOFError:
            return
        try:
            if name == 'register_frame':
                if registration is None:
                    raise RuntimeError('no registration in the registration process: register_chains first')
                value = registration.register_frame(*args)
            elif name == 'register_chains':
                value, registration = register_chains(*args)
            elif name == 'rest_pose':
                value = RestPose.from_points(*args)
            else:
                raise ValueError(f'unknown call {name!r}')
            answer = (True, value)
        except Exception as error:  # sent back and raised in the node; the child goes on
            answer = (False, error)
        try:
            data = pickle.dumps(answer, protocol=pickle.HIGHEST_PROTOCOL)
        except Exception as error:  # an exception that does not pickle: its text does
            data = pickle.dumps((False, RuntimeError(f'{type(answer[1]).__name__}: {answer[1]} '
                                                     f'(unpicklable: {error})')))
        answers.write(data)
        answers.flush()


if __name__ == '__main__':
    _serve()
