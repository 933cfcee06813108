"""The nodes' one worker idiom: bounded waiting, counted drops, errors that do not end it."""
import os
import sys
import threading
from concurrent.futures import ThreadPoolExecutor

import pytest

from skel_extract_ros.nodes.worker import Worker


def test_latest_frame_only_drops_the_older_waiting_items_and_counts_them():
    release, started, seen = threading.Event(), threading.Event(), []

    def process(item):
        seen.append(item)
        started.set()
        release.wait(5.0)

    worker = Worker(process, 'test', capacity=1)
    try:
        worker.submit(0)
        assert started.wait(5.0)              # 0 is running: 1..4 wait, each replacing the last
        assert [worker.submit(i) for i in range(1, 5)] == [0, 1, 1, 1]
        release.set()
        assert worker.wait_idle(5.0)
        stats = worker.stats()
        assert seen == [0, 4]
        assert (stats['submitted'], stats['processed'], stats['dropped'], stats['waiting']) == (5, 2, 3, 0)
        assert stats['latency_ms_median'] >= 0.0 and stats['rate_hz'] > 0.0
    finally:
        worker.stop()


def test_a_deeper_queue_keeps_order_and_drops_the_oldest():
    release, seen = threading.Event(), []
    worker = Worker(lambda item: (release.wait(5.0), seen.append(item)), 'test', capacity=3)
    try:
        for i in range(6):
            worker.submit(i)
        release.set()
        assert worker.wait_idle(5.0)
        # 0 was taken at once (or still waiting when 3 arrived): the survivors are in order
        assert seen == sorted(seen) and seen[-3:] == [3, 4, 5]
        assert worker.dropped == 6 - len(seen)
    finally:
        worker.stop()


def test_keeping_the_oldest_gives_a_consecutive_run_and_reconfiguring_trims_the_queue():
    release, started, seen = threading.Event(), threading.Event(), []

    def process(item):
        started.set()
        release.wait(5.0)
        seen.append(item)

    worker = Worker(process, 'test', capacity=3, keep='oldest')
    try:
        worker.submit(0)
        assert started.wait(5.0)              # 0 is running: 1, 2, 3 wait, 4 and 5 are refused
        assert [worker.submit(i) for i in range(1, 6)] == [0, 0, 0, 1, 1]
        assert worker.stats()['waiting'] == 3 and worker.dropped == 2
        # a producer that asks first skips making the item; the skip counts as a drop
        assert worker.full
        worker.refuse()
        assert worker.stats()['submitted'] == 7 and worker.dropped == 3 and worker.stats()['waiting'] == 3
        # learning done: the newest only from now on; the waiting run shrinks to its newest
        assert worker.configure(1, keep='newest') == 2
        assert worker.submit(6) == 1          # replaces 3
        release.set()
        assert worker.wait_idle(5.0)
        assert seen == [0, 6] and worker.dropped == 6 and not worker.full
        with pytest.raises(ValueError):
            worker.configure(2, keep='middle')
        with pytest.raises(ValueError):
            worker.configure(0)
    finally:
        worker.stop()


def test_a_blocking_submit_waits_for_room_and_loses_nothing():
    """Back-pressure (the registration node's lossless mode): a producer faster than the
    worker is slowed down to it, nothing is dropped and the order is kept."""
    seen = []
    gate = threading.Semaphore(0)
    worker = Worker(lambda item: (gate.acquire(timeout=5.0), seen.append(item)), 'test', capacity=1)
    producer_done = threading.Event()

    def produce():
        for i in range(5):
            worker.submit(i, block=True)
        producer_done.set()

    try:
        threading.Thread(target=produce, daemon=True).start()
        # the worker holds item 0, item 1 waits: the producer cannot get further
        assert not producer_done.wait(0.3)
        assert worker.stats()['waiting'] == 1
        for _ in range(5):
            gate.release()
        assert producer_done.wait(5.0) and worker.wait_idle(5.0)
        assert seen == [0, 1, 2, 3, 4] and worker.dropped == 0
    finally:
        worker.stop()


def test_an_item_that_raises_is_reported_and_the_worker_goes_on():
    errors, seen = [], []

    def process(item):
        if item == 'bad':
            raise RuntimeError('broken cloud')
        seen.append(item)

    worker = Worker(process, 'test', capacity=10, on_error=lambda item, error: errors.append((item, str(error))))
    try:
        for item in ('a', 'bad', 'b'):
            worker.submit(item)
        assert worker.wait_idle(5.0)
        assert seen == ['a', 'b'] and errors == [('bad', 'broken cloud')]
        assert (worker.processed, worker.failed) == (2, 1)
    finally:
        worker.stop()


@pytest.mark.skipif(not sys.platform.startswith('linux'), reason='a nice value per thread is Linux')
def test_a_nicer_worker_lowers_its_own_thread_and_the_threads_it_starts_not_the_caller():
    """Alg. 2 runs on a worker with niceness, its pool started from that thread; the live
    fit's thread in the same process keeps its priority."""
    def nice_of_this_thread():
        return os.getpriority(os.PRIO_PROCESS, threading.get_native_id())

    caller = nice_of_this_thread()
    seen = {}

    def process(_item):
        seen['worker'] = nice_of_this_thread()
        with ThreadPoolExecutor(max_workers=1) as pool:      # as core.joints' E-step pool
            seen['pool'] = pool.submit(nice_of_this_thread).result()

    worker = Worker(process, 'nicer', niceness=5)
    plain = Worker(lambda _item: seen.setdefault('plain', nice_of_this_thread()), 'plain')
    try:
        worker.submit('job')
        plain.submit('job')
        assert worker.wait_idle(5.0) and plain.wait_idle(5.0)
        expected = min(caller + 5, 19)
        assert seen == {'worker': expected, 'pool': expected, 'plain': caller}
        assert nice_of_this_thread() == caller
    finally:
        worker.stop()
        plain.stop()


def test_an_error_handler_that_raises_does_not_end_the_worker(capsys):
    # as the joint node's did once, at shutdown, reading a field the item did not have
    def process(item):
        if item == 'bad':
            raise RuntimeError('publish failed')
    seen = []
    worker = Worker(lambda item: (process(item), seen.append(item)), 'test', capacity=10,
                    on_error=lambda item, error: item.header)
    try:
        for item in ('bad', 'a'):
            worker.submit(item)
        assert worker.wait_idle(5.0)
        assert seen == ['a'] and (worker.processed, worker.failed) == (1, 1)
        assert "has no attribute 'header'" in capsys.readouterr().err
    finally:
        worker.stop()


def test_stop_ends_the_thread_and_clear_forgets_without_counting():
    release = threading.Event()
    worker = Worker(lambda item: release.wait(5.0), 'test', capacity=5)
    worker.submit(1)
    worker.submit(2)
    worker.submit(3)
    assert worker.clear() >= 1 and worker.dropped == 0
    release.set()
    worker.stop()
    assert not worker._thread.is_alive()
    with pytest.raises(ValueError, match='capacity'):
        Worker(lambda item: None, 'test', capacity=0)


def test_the_pairer_forgets_frames_the_registration_has_passed():
    from skel_extract_ros.nodes.common import StampPairer
    pairer = StampPairer(capacity=100)
    for stamp in range(10):                       # filtered frames of every camera frame
        assert pairer.add(1, stamp, f'filtered {stamp}') is None
    assert pairer.add(0, 3, 'registered 3') == ('registered 3', 'filtered 3')
    # registration goes in stamp order: 0-2 will never be registered and are gone
    assert list(pairer._sides[1]) == [4, 5, 6, 7, 8, 9]
    assert pairer.add(0, 7, 'registered 7') == ('registered 7', 'filtered 7')
    assert pairer.add(1, 12, 'filtered 12') is None and pairer.add(0, 12, 'r') == ('r', 'filtered 12')
    assert list(pairer._sides[1]) == []           # 4-6, 8-11 dropped when 7 and 12 came
    # either side may come first (DDS does not order topics): a registered frame waits
    assert pairer.add(0, 13, 'r13') is None and pairer.add(1, 13, 'f13') == ('r13', 'f13')
