"""The environment of the processes: a node process runs its thread pools on one thread (the
threads a fresh interpreter has after numpy's import and a pykdtree query) and keeps two
malloc arenas, and a replay publishes with the packaged Fast DDS profile (a shared-memory
segment for large clouds), unless the environment says otherwise."""
import os
import subprocess
import sys
import xml.etree.ElementTree as ElementTree

import pytest

from ros_domains import private_environment

PROBE = '''
import os, sys
start = len(os.listdir('/proc/self/task'))
if sys.argv[1] == 'nodes':
    import skel_extract_ros.nodes  # noqa: F401
import numpy as np
from pykdtree.kdtree import KDTree
points = np.random.default_rng(0).uniform(size=(20000, 3))
KDTree(points).query(points, k=8)
if sys.argv[1] == 'replay':
    from skel_extract_ros.app.replay import use_large_message_profile
    use_large_message_profile()
print(start, len(os.listdir('/proc/self/task')), os.environ.get('OMP_NUM_THREADS'),
      os.environ.get('OPENBLAS_NUM_THREADS'), os.environ.get('FASTRTPS_DEFAULT_PROFILES_FILE'))
'''
SETTINGS = ('OMP_NUM_THREADS', 'OPENBLAS_NUM_THREADS', 'FASTRTPS_DEFAULT_PROFILES_FILE',
            'FASTDDS_DEFAULT_PROFILES_FILE', 'MALLOC_ARENA_MAX')


def _probe(mode: str, script: str = PROBE, **env) -> list:
    """The words `script` prints in a fresh interpreter, run with `mode` as its argument, in
    this environment without SETTINGS, plus `env`."""
    environment = {k: v for k, v in os.environ.items() if k not in SETTINGS}
    environment.update(env)
    return subprocess.run([sys.executable, '-c', script, mode], capture_output=True, text=True, check=True,
                          env=environment).stdout.split()


@pytest.mark.skipif(not os.path.isdir('/proc/self/task'), reason='counts threads in /proc')
def test_node_processes_start_no_worker_threads():
    start, end, omp, openblas, _ = _probe('nodes')
    assert (omp, openblas) == ('1', '1') and end == start
    if (os.cpu_count() or 1) > 1:
        # without the limits the probe does see the pools' threads
        start, end, omp, openblas, _ = _probe('plain')
        assert (omp, openblas) == ('None', 'None') and int(end) > int(start)


def test_explicit_thread_settings_are_kept():
    assert _probe('nodes', OMP_NUM_THREADS='2', OPENBLAS_NUM_THREADS='3')[2:4] == ['2', '3']


ARENAS_PROBE = '''
import ctypes, ctypes.util, os, subprocess, sys, tempfile, threading
if sys.argv[1] == 'nodes':
    import skel_extract_ros.nodes  # noqa: F401
import numpy as np
barrier = threading.Barrier(8)
def allocate():
    # a 64 KiB buffer is under glibc's mmap threshold: it comes from the thread's arena
    held = [np.ones(8192) for _ in range(4)]
    barrier.wait()
threads = [threading.Thread(target=allocate) for _ in range(8)]
[t.start() for t in threads]
[t.join() for t in threads]
libc = ctypes.CDLL(ctypes.util.find_library('c'))
libc.fopen.restype = ctypes.c_void_p
with tempfile.NamedTemporaryFile('r', suffix='.xml') as report:
    stream = libc.fopen(report.name.encode(), b'w')
    libc.malloc_info(0, ctypes.c_void_p(stream))
    libc.fclose(ctypes.c_void_p(stream))
    heaps = report.read().count('<heap nr=')
# what a child process started now (the registration's) gets
child = subprocess.run([sys.executable, '-c', 'import os; print(os.environ.get("MALLOC_ARENA_MAX"))'],
                       capture_output=True, text=True, check=True).stdout.strip()
print(heaps, child)
'''


@pytest.mark.skipif(not sys.platform.startswith('linux'), reason="counts glibc's malloc arenas")
def test_node_processes_keep_two_malloc_arenas_and_pass_the_limit_to_their_children():
    heaps, limit = _probe('nodes', ARENAS_PROBE)
    assert int(heaps) <= 2 and limit == '2'
    # eight threads allocating at once get arenas of their own without the limit
    heaps, limit = _probe('plain', ARENAS_PROBE)
    assert int(heaps) > 2 and limit == 'None'
    # the user's own setting is kept
    assert _probe('nodes', ARENAS_PROBE, MALLOC_ARENA_MAX='4')[1] == '4'


def test_replay_publishes_with_the_large_shared_memory_profile():
    profile = _probe('replay')[4]
    root = ElementTree.parse(profile).getroot()
    namespace = {'dds': 'http://www.eprosima.com/XMLSchemas/fastRTPS_Profiles'}
    shm = [d for d in root.iterfind('dds:transport_descriptors/dds:transport_descriptor', namespace)
           if d.findtext('dds:type', namespaces=namespace) == 'SHM']
    segment = int(shm[0].findtext('dds:segment_size', namespaces=namespace)) if len(shm) == 1 else 0
    # three 320x240 clouds (1.2 MB each) fit; every process that uses it maps it, so it stays small
    assert 3 * 320 * 240 * 16 <= segment <= 8 * 2 ** 20
    assert root.find('dds:participant', namespace).get('is_default_profile') == 'true'
    # a profile of the user's own (Fast DDS 2 or 3 variable) is kept
    assert _probe('replay', FASTRTPS_DEFAULT_PROFILES_FILE='/elsewhere.xml')[4] == '/elsewhere.xml'
    assert _probe('replay', FASTDDS_DEFAULT_PROFILES_FILE='/elsewhere.xml')[4] == 'None'
    assert _probe('nodes')[4] == 'None'     # the nodes' side does not need it


class _AccumulatorProcess:
    """The accumulator node as a process of its own, alone in a DDS domain, its output in
    a log: `wait_for` a text in the log."""

    def __init__(self, tmp_path):
        self.log_path = tmp_path / 'accumulator.log'
        environment = private_environment(91, PYTHONUNBUFFERED='1')
        with open(self.log_path, 'w') as log:
            self.process = subprocess.Popen([sys.executable, '-m', 'skel_extract_ros.nodes.accumulator_node'],
                                            stdout=log, stderr=subprocess.STDOUT, env=environment)

    def wait_for(self, text: str, what: str) -> None:
        import time
        deadline = time.monotonic() + 60
        while text not in self.log_path.read_text():
            assert self.process.poll() is None, self.log_path.read_text()
            assert time.monotonic() < deadline, f'no {what}: {self.log_path.read_text()[-2000:]}'
            time.sleep(0.1)

    def __enter__(self) -> '_AccumulatorProcess':
        return self

    def __exit__(self, *_exc) -> None:
        if self.process.poll() is None:
            self.process.kill()


def test_a_node_writes_its_threads_stacks_on_sigusr1_and_goes_on(tmp_path):
    """What a node that does not end or answer is doing: SIGUSR1 puts every thread's stack
    in its log (replay sends it before killing a node that ignored Ctrl-C); the node keeps
    running and still ends cleanly on Ctrl-C."""
    import signal
    import time
    with _AccumulatorProcess(tmp_path) as node:
        node.wait_for('waiting for registered_points', 'start-up line')
        node.process.send_signal(signal.SIGUSR1)
        node.wait_for('run_node', 'stack of the main thread')       # spinning, called from run_node
        log = node.log_path.read_text()
        assert 'Current thread' in log or 'Thread 0x' in log
        time.sleep(0.5)
        assert node.process.poll() is None                             # it goes on
        node.process.send_signal(signal.SIGINT)
        assert node.process.wait(timeout=20) == 0


@pytest.mark.skipif(not os.path.isdir('/dev/shm'), reason='Fast DDS keeps its segments in /dev/shm')
def test_a_node_ended_by_ctrl_c_leaves_no_shared_memory_segment(tmp_path):
    """Fast DDS's participant keeps a shared-memory segment in /dev/shm, and only destroying
    the node removes it: a node that exited without (os._exit alone) left one in memory per
    run, until the machine restarts."""
    import re
    import signal
    with _AccumulatorProcess(tmp_path) as node:
        node.wait_for('waiting for registered_points', 'start-up line')
        # alone in its domain, the segments it maps are its own participant's
        maps = open(f'/proc/{node.process.pid}/maps').read()
        segments = set(re.findall(r'/dev/shm/fastrtps_[0-9a-f]{16}$', maps, re.MULTILINE))
        if not segments:
            pytest.skip('the node maps no Fast DDS segment (another RMW, or no shared memory)')
        assert all(os.path.exists(path) for path in segments)
        node.process.send_signal(signal.SIGINT)
        assert node.process.wait(timeout=20) == 0
    assert [path for path in segments if os.path.exists(path)] == []


def test_run_node_ends_cleanly_when_ctrl_c_races_the_executor(monkeypatch):
    """rclpy's deferred SIGINT handler shuts the context down from its own thread; an
    executor creating its wait set at that moment raises RCLError (seen once in a run of the
    test suite: the accumulator exited 1 on Ctrl-C). With the context down that is a
    Ctrl-C: exit 0. With the context up the same error is a failure and is not hidden."""
    import rclpy
    from rclpy._rclpy_pybind11 import RCLError

    from skel_extract_ros.nodes.common import spin_node

    def racing_spin(node, executor=None):
        rclpy.shutdown()          # what the signal handler does, from another thread
        raise RCLError('failed to initialize wait set: the given context is not valid')

    monkeypatch.setattr(rclpy, 'spin', racing_spin)
    assert spin_node(lambda: rclpy.create_node('shutdown_race')) == 0
    assert not rclpy.ok()

    def failing_spin(node, executor=None):
        raise RCLError('failed to take a message')

    monkeypatch.setattr(rclpy, 'spin', failing_spin)
    with pytest.raises(RCLError):
        spin_node(lambda: rclpy.create_node('real_failure'))
    assert not rclpy.ok()         # shut down on the way out all the same


def test_spin_node_stops_the_nodes_work_and_leaves_its_entities_to_run_node(monkeypatch):
    """On Ctrl-C the node's threads and child processes stop (stop_work); spin_node does not
    destroy the node: rclpy's destroy_node wakes the executor that rclpy's signal thread is
    shutting down, and a node hung there (the accumulator, twice in benchmark replays).
    run_node destroys it afterwards, on a thread it does not wait for long."""
    import rclpy

    from skel_extract_ros.nodes.common import WorkingNode, spin_node

    calls = []

    class Worked(WorkingNode):
        def stop_work(self):
            calls.append('stop_work')

        def destroy_node(self):
            calls.append('destroy_node')
            return super().destroy_node()

    def interrupted_spin(node, executor=None):
        rclpy.shutdown()
        raise KeyboardInterrupt

    monkeypatch.setattr(rclpy, 'spin', interrupted_spin)
    assert spin_node(lambda: Worked('worked')) == 0
    assert calls == ['stop_work'] and not rclpy.ok()


def test_a_destruction_that_hangs_does_not_hold_the_exit(monkeypatch):
    """run_node's release_entities destroys the node (rclpy's destroy_node, once: the
    node's work stopped already) and returns True; when the destruction hangs it returns
    False after its timeout, and the process can end all the same."""
    import threading
    import time

    import rclpy
    from rclpy.node import Node

    from skel_extract_ros.nodes.common import WorkingNode, release_entities

    rclpy.init()
    try:
        destroyed, stopped = [], []

        class Worked(WorkingNode):
            def stop_work(self):
                stopped.append(True)

        node = Worked('released')
        original = Node.destroy_node
        monkeypatch.setattr(Node, 'destroy_node', lambda self: destroyed.append(self) or original(self))
        assert release_entities(node, timeout_s=10.0)
        assert destroyed == [node] and stopped == []

        hanging = threading.Event()
        monkeypatch.setattr(Node, 'destroy_node', lambda self: hanging.wait(30.0))
        started = time.monotonic()
        assert not release_entities(Worked('hanging'), timeout_s=0.2)
        assert time.monotonic() - started < 5.0
        hanging.set()
    finally:
        rclpy.try_shutdown()


EXIT_PROBE = '''
import atexit, sys
import rclpy
from skel_extract_ros.nodes.common import ParameterError, run_node

def interrupted_spin(node, executor=None):
    rclpy.shutdown()
    raise KeyboardInterrupt

def bad_parameters():
    raise ParameterError('smoothing_radius must be > 0')

rclpy.spin = interrupted_spin
atexit.register(lambda: print('finalised'))
print('spun', flush=False)
run_node((lambda: rclpy.create_node('exiting')) if sys.argv[1] == 'ctrl-c' else bad_parameters)
print('returned')
'''


@pytest.mark.parametrize('ending, code', [('ctrl-c', 0), ('parameters', 2)])
def test_a_node_process_ends_without_the_interpreters_finalisation(ending, code):
    """After Ctrl-C (or a parameter error) the node process ends in run_node with its exit
    code: what it printed is flushed, and nothing is left to the interpreter's finalisation
    (the garbage collector finalising rclpy's entities once hung a joint node in CI)."""
    environment = private_environment(17)
    done = subprocess.run([sys.executable, '-c', EXIT_PROBE, ending], capture_output=True, text=True,
                          env=environment, timeout=60)
    assert done.returncode == code, done.stderr
    assert done.stdout.split() == ['spun']            # flushed; neither returned nor finalised
    assert ('must be > 0' in done.stderr) == (ending == 'parameters')


IMPORTS_PROBE = '''
import importlib, sys
import numpy as np
for module in sys.argv[1:]:
    if module == 'pair':
        from skel_extract_ros.core.matching import gated_assignment
        gated_assignment(np.eye(2), 1.0)
    else:
        importlib.import_module(module)
print(*sorted({m.split('.')[0] if m.startswith('rosbags') else 'scipy.optimize'
               for m in sys.modules if m.startswith(('rosbags', 'scipy.optimize'))}))
'''


def _loaded(*steps) -> list:
    """Of rosbags and scipy.optimize, those loaded in a fresh interpreter after `steps`
    (modules imported in turn; 'pair': one gated assignment)."""
    return subprocess.run([sys.executable, '-c', IMPORTS_PROBE, *steps], capture_output=True, text=True,
                          check=True).stdout.split()


def test_node_processes_leave_the_bag_codec_and_the_assignment_solver_unloaded():
    """The nodes read stamps but no bag, and the joint node and the registration node's camera
    stage pair nothing: importing the nodes loads neither rosbags nor scipy.optimize (16 MB
    of each such process); reading a bag and pairing do."""
    nodes = ['skel_extract_ros.nodes.joint_estimation_node', 'skel_extract_ros.nodes.accumulator_node',
             'skel_extract_ros.nodes.registration_node', 'skel_extract_ros.nodes.registration_process']
    assert _loaded(*nodes) == []
    assert _loaded(*nodes, 'pair') == ['scipy.optimize']
    assert _loaded('skel_extract_ros.codecs.bag') == ['rosbags']
