"""The core's one way to use several cores: a thread pool shared by the whole process.

numpy's reductions, the k-d tree queries and scipy's sparse solves release the GIL, so
independent work (Alg. 2's E-step over frames, the rest pose's two chains of held frames,
core.registration.register_chains) runs in parallel on threads. One pool for the process,
made on first use, so a node that fits a model every few seconds does not start and stop
threads each time. A function mapped must not map on the pool itself: with as many threads
as cores, the outer calls would hold every thread the inner ones wait for.
"""
from __future__ import annotations

import os
import threading
from concurrent.futures import ThreadPoolExecutor
from typing import Callable, Iterable

_pool = None
_pool_lock = threading.Lock()


def parallel_map(function: Callable, items: Iterable) -> list:
    """[function(item) for item in items], computed on the shared pool (at most 8 threads)."""
    global _pool
    with _pool_lock:
        if _pool is None:
            _pool = ThreadPoolExecutor(max_workers=min(os.cpu_count() or 1, 8), thread_name_prefix='core')
    return list(_pool.map(function, items))
