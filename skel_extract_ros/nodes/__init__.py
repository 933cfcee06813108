"""ROS 2 nodes: thin adapters around skel_extract_ros.core.

Every node process runs OpenMP and OpenBLAS on one thread, unless OMP_NUM_THREADS /
OPENBLAS_NUM_THREADS say otherwise. The nodes share the machine's cores between processes
(three nodes, the registration child, the camera driver); a thread pool inside one of them
(pykdtree's k-d tree queries in the outlier removal and every E-step, numpy's matrix
products) keeps its threads spinning between calls and takes the cores from the others
(bench/HISTORY.md, "One thread per node process"). Set here, before any node module
imports numpy or pykdtree: both libraries read these once, when they are loaded.

For the same processes, glibc's malloc keeps at most two arenas, unless MALLOC_ARENA_MAX
says otherwise. glibc gives each new thread an arena of its own (up to 8 per core), and an
arena keeps the pages its thread freed. A node's threads (DDS, the executor, its workers)
mostly take turns under the GIL: two arenas hold less memory, at no speed the nodes'
benches can tell (bench/HISTORY.md, "Two malloc arenas a node process"). Set here, before
rclpy starts the DDS threads, and in the environment for the child processes a node starts
later (glibc reads it when a process starts).
"""
import ctypes
import ctypes.util
import functools
import os


@functools.lru_cache(maxsize=1)
def libc() -> ctypes.CDLL | None:
    """The process's C library (for glibc's mallopt and malloc_trim), or None where it
    cannot be loaded."""
    try:
        return ctypes.CDLL(ctypes.util.find_library('c') or 'libc.so.6')
    except OSError:
        return None


for _variable in ('OMP_NUM_THREADS', 'OPENBLAS_NUM_THREADS'):
    os.environ.setdefault(_variable, '1')

# mallopt's parameter number for the arena limit (glibc malloc.h: M_ARENA_MAX)
_M_ARENA_MAX = -8
if 'MALLOC_ARENA_MAX' not in os.environ:
    os.environ['MALLOC_ARENA_MAX'] = '2'
    # not glibc (musl, macOS): no mallopt, and their allocators have no such arenas
    getattr(libc(), 'mallopt', lambda *_args: None)(_M_ARENA_MAX, 2)
