"""One worker idiom for the nodes: a background thread that processes submitted items in
order, holding at most `capacity` waiting ones; when full, the oldest waiting item is
dropped and counted (keep='newest'), or the new one is (keep='oldest': a run of
consecutive items, e.g. the frames of a learning window). capacity 1 is "latest frame
only" (live fits) and "single flight, newest wins" (a long job such as Alg. 2: while it
runs, a newer request replaces the waiting one). No rclpy: the callbacks stay cheap
(submit never blocks) and the executor never waits for the work.

    >>> worker = Worker(fit_and_publish, name='live', capacity=1)
    >>> worker.submit(frame)        # from a subscription callback
    >>> worker.stats()              # submitted, processed, dropped, failed, latency ms
    >>> worker.stop()               # in the node's stop_work
"""
from __future__ import annotations

import collections
import os
import threading
import time
import traceback
from typing import Callable

# A lossless node's long jobs (the accumulator's windows, the joint node's structures) wait
# in a queue of at most this many, not one: each holds its window's frames, a few MB. Jobs
# come due seconds apart at the registration's pace and take seconds, so the queue stays
# short; past this the oldest is dropped (counted, and the node says so).
LOSSLESS_CAPACITY = 100


def lower_priority(task_id: int, niceness: int, idle_class: bool = False) -> None:
    """Add `niceness` to the nice value of thread or process `task_id` (Linux keeps one per
    thread; threads it starts later inherit it) and, with `idle_class`, put it in the idle
    scheduling class (SCHED_IDLE: it runs only when no other task wants the core). Lowering
    either needs no privilege. Raises OSError (ProcessLookupError: the task is gone) and
    AttributeError (not Linux) from the nice value; a refused class leaves the nice value."""
    os.setpriority(os.PRIO_PROCESS, task_id, min(os.getpriority(os.PRIO_PROCESS, task_id) + niceness, 19))
    if idle_class:
        try:
            os.sched_setscheduler(task_id, os.SCHED_IDLE, os.sched_param(0))
        except (AttributeError, PermissionError):
            pass


class RateMeter:
    """Events per second over the last `window_s` seconds (thread-safe)."""

    def __init__(self, window_s: float = 5.0):
        self.window_s = window_s
        self._times = collections.deque()
        self._lock = threading.Lock()

    def tick(self) -> None:
        now = time.monotonic()
        with self._lock:
            self._times.append(now)
            self._trim(now)

    def rate(self) -> float:
        with self._lock:
            self._trim(time.monotonic())
            return len(self._times) / self.window_s

    def _trim(self, now: float) -> None:
        while self._times and self._times[0] < now - self.window_s:
            self._times.popleft()


class Worker:
    """process(item) on a thread named `name`; on_error(item, exception) is called (on the
    worker thread) when process raises, and the worker goes on with the next item.
    niceness: added to the thread's nice value when it starts (Linux keeps one per thread;
    threads it starts inherit it): background learning below the live path of the same
    process. Raising it needs no privilege; where it fails, the thread runs as it is."""

    def __init__(self, process: Callable, name: str, capacity: int = 1,
                 on_error: Callable | None = None, history: int = 1000, keep: str = 'newest',
                 niceness: int = 0):
        self._process, self._on_error = process, on_error
        self.niceness = int(niceness)
        self._waiting = collections.deque()
        self._wake = threading.Condition()
        self._stopping = False
        self._busy = False
        self.submitted = self.processed = self.dropped = self.failed = 0
        self.configure(capacity, keep)
        self._latency_s = collections.deque(maxlen=history)   # submit -> processed, seconds
        self.rate_in, self.rate_out = RateMeter(), RateMeter()
        self._thread = threading.Thread(target=self._run, name=name, daemon=True)
        self._thread.start()

    def configure(self, capacity: int, keep: str = 'newest') -> int:
        """Change the capacity and what a full queue keeps ('newest': the oldest waiting
        item is dropped; 'oldest': the new one is); returns how many waiting items the new
        capacity dropped (counted)."""
        if capacity < 1:
            raise ValueError(f'capacity must be >= 1, got {capacity}')
        if keep not in ('newest', 'oldest'):
            raise ValueError(f"keep must be 'newest' or 'oldest', got {keep!r}")
        with self._wake:
            self.capacity, self.keep = int(capacity), keep
            return self._trim()

    def _trim(self) -> int:
        """Drop what exceeds the capacity, by the keep policy (the caller holds the lock)."""
        dropped = 0
        while len(self._waiting) > self.capacity:
            if self.keep == 'newest':
                self._waiting.popleft()
            else:
                self._waiting.pop()
            dropped += 1
        self.dropped += dropped
        return dropped

    def submit(self, item, block: bool = False) -> int:
        """Queue `item`; returns how many items this dropped (0 or more; with keep='oldest'
        and a full queue, 1: the item itself). block: wait for room instead of dropping
        (back-pressure, for lossless processing; never from an executor callback)."""
        with self._wake:
            while block and len(self._waiting) >= self.capacity and not self._stopping:
                self._wake.wait()
            self._waiting.append((time.monotonic(), item))
            self.submitted += 1
            self.rate_in.tick()
            dropped = self._trim()
            self._wake.notify_all()
        return dropped

    @property
    def full(self) -> bool:
        """No room: a submit now would drop an item. A producer whose item costs work to
        make (decode, segment) asks first, and skips the work (see `refuse`)."""
        with self._wake:
            return len(self._waiting) >= self.capacity

    def refuse(self) -> None:
        """Count an item the producer did not make because the queue was `full` (it would
        have been dropped on submit): counted as dropped, like those."""
        with self._wake:
            self.submitted += 1
            self.dropped += 1
            self.rate_in.tick()

    def clear(self) -> int:
        """Forget the waiting items (not counted as dropped: the caller chose to); returns how many."""
        with self._wake:
            n = len(self._waiting)
            self._waiting.clear()
        return n

    @property
    def idle(self) -> bool:
        with self._wake:
            return not self._waiting and not self._busy

    def wait_idle(self, timeout: float) -> bool:
        """Block until nothing waits and nothing runs (tests, shutdown); False on timeout."""
        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline:
            if self.idle:
                return True
            time.sleep(0.005)
        return self.idle

    def stats(self) -> dict:
        """Counts, the latency (submit -> done) median / p95 in ms over the last items, and
        the rates (Hz) of submitted and processed items over the last seconds."""
        with self._wake:
            latency = sorted(self._latency_s)
            counts = {'submitted': self.submitted, 'processed': self.processed, 'dropped': self.dropped,
                      'failed': self.failed, 'waiting': len(self._waiting), 'busy': self._busy}
        percentile = (lambda q: 1000.0 * latency[min(len(latency) - 1, int(q * len(latency)))]) if latency \
            else (lambda q: float('nan'))
        return {**counts, 'latency_ms_median': percentile(0.5), 'latency_ms_p95': percentile(0.95),
                'rate_in_hz': self.rate_in.rate(), 'rate_hz': self.rate_out.rate()}

    def stop(self, timeout: float = 10.0) -> None:
        """Finish the item in progress, drop the waiting ones, end the thread."""
        with self._wake:
            self._stopping = True
            self._waiting.clear()
            self._wake.notify_all()
        if self._thread is not threading.current_thread():
            self._thread.join(timeout=timeout)

    def _run(self) -> None:
        if self.niceness > 0:
            try:
                lower_priority(threading.get_native_id(), self.niceness)
            except (OSError, AttributeError):   # not Linux, or not allowed: at the process's priority
                pass
        while True:
            with self._wake:
                while not self._waiting and not self._stopping:
                    self._wake.wait()
                if self._stopping:
                    return
                submitted_at, item = self._waiting.popleft()
                self._busy = True
                self._wake.notify_all()          # room for a blocked submit
            try:
                self._process(item)
                ok = True
            except Exception as error:  # one bad item never ends the worker
                ok = False
                if self._on_error is not None:
                    try:
                        self._on_error(item, error)
                    except Exception:  # nor a bad error handler: its traceback, then on
                        traceback.print_exc()
            with self._wake:
                self._busy = False
                now = time.monotonic()
                if ok:
                    self.processed += 1
                    self._latency_s.append(now - submitted_at)
                    self.rate_out.tick()
                else:
                    self.failed += 1
