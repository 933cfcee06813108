"""ROS 2 nodes: thin adapters around skel_extract_ros.core.

Two settings of every node process's environment, made here, before any node module loads
numpy, pykdtree or rclpy (each reads its setting once, when loaded), and only where the
environment does not set them already:

- OpenMP and OpenBLAS on one thread (OMP_NUM_THREADS, OPENBLAS_NUM_THREADS). The nodes
  share the machine's cores between processes (three nodes, the registration child, the
  camera driver); a thread pool inside one of them (pykdtree's k-d tree queries in the
  outlier removal and every E-step, numpy's matrix products) keeps its threads spinning
  between calls and takes the cores from the others. Measured through the nodes
  (bench/README.md, "One thread per node process"): on depth images of real motion in the
  room, latency median / p95 32-58 / 60-90 ms -> 24-44 / 34-67 ms, and the niced
  registration registers 1.7x the frames.
- Fast DDS's shared-memory segment of 4 MB instead of 512 kB (FASTRTPS_DEFAULT_PROFILES_FILE,
  the profile next to this file; left alone if FASTDDS_DEFAULT_PROFILES_FILE is set, and
  without effect on other RMW implementations). With the default segment about a third of
  a camera's 1.2 MB clouds at 30 Hz never reached the registration node on a 2-core machine;
  with this one on the nodes' side all of them did, from a driver left as it was
  (bench/README.md, "Large clouds over shared memory").
"""
import os
from pathlib import Path

for _variable in ('OMP_NUM_THREADS', 'OPENBLAS_NUM_THREADS'):
    os.environ.setdefault(_variable, '1')

FASTDDS_PROFILE = Path(__file__).with_name('fastdds_large_messages.xml')
if not (os.environ.get('FASTRTPS_DEFAULT_PROFILES_FILE') or os.environ.get('FASTDDS_DEFAULT_PROFILES_FILE')) \
        and FASTDDS_PROFILE.is_file():
    os.environ['FASTRTPS_DEFAULT_PROFILES_FILE'] = str(FASTDDS_PROFILE)
