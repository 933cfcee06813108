"""ROS 2 nodes: thin adapters around skel_extract_ros.core.

Every node process runs OpenMP and OpenBLAS on one thread, unless OMP_NUM_THREADS /
OPENBLAS_NUM_THREADS say otherwise. The nodes share the machine's cores between processes
(three nodes, the registration child, the camera driver); a thread pool inside one of them
(pykdtree's k-d tree queries in the outlier removal and every E-step, numpy's matrix
products) keeps its threads spinning between calls and takes the cores from the others
(bench/HISTORY.md, "One thread per node process"). Set here, before any node module
imports numpy or pykdtree: both libraries read these once, when they are loaded.
"""
import os

for _variable in ('OMP_NUM_THREADS', 'OPENBLAS_NUM_THREADS'):
    os.environ.setdefault(_variable, '1')
