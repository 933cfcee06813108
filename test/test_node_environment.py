"""The node processes run their thread pools on one thread (skel_extract_ros/nodes/__init__.py):
the threads a fresh interpreter has after numpy's import and a pykdtree query."""
import os
import subprocess
import sys

import pytest

PROBE = '''
import os, sys
start = len(os.listdir('/proc/self/task'))
if sys.argv[1] == 'nodes':
    import skel_extract_ros.nodes  # noqa: F401
import numpy as np
from pykdtree.kdtree import KDTree
points = np.random.default_rng(0).uniform(size=(20000, 3))
KDTree(points).query(points, k=8)
print(start, len(os.listdir('/proc/self/task')), os.environ.get('OMP_NUM_THREADS'),
      os.environ.get('OPENBLAS_NUM_THREADS'))
'''
LIMITS = ('OMP_NUM_THREADS', 'OPENBLAS_NUM_THREADS')


def _probe(mode: str, **env) -> list:
    environment = {k: v for k, v in os.environ.items() if k not in LIMITS}
    environment.update(env)
    return subprocess.run([sys.executable, '-c', PROBE, mode], capture_output=True, text=True, check=True,
                          env=environment).stdout.split()


@pytest.mark.skipif(not os.path.isdir('/proc/self/task'), reason='counts threads in /proc')
def test_node_processes_start_no_worker_threads():
    start, end, omp, openblas = _probe('nodes')
    assert (omp, openblas) == ('1', '1') and end == start
    if (os.cpu_count() or 1) > 1:
        # without the limits the probe does see the pools' threads
        start, end, omp, openblas = _probe('plain')
        assert (omp, openblas) == ('None', 'None') and int(end) > int(start)


def test_explicit_limits_are_kept():
    assert _probe('nodes', OMP_NUM_THREADS='2', OPENBLAS_NUM_THREADS='3')[2:] == ['2', '3']
