"""A DDS domain of its own for each test process that starts ROS nodes: two test runs on one
machine (a developer's beside CI, two pytest processes) must never see each other's
latched topics. Each domain this process takes is held by an exclusive lock on a file for
as long as the process lives; a domain another process holds is skipped."""
import fcntl
import os
import tempfile
from pathlib import Path

# the domains the tests use: above the ones people usually set, below Fast DDS's limit for
# its default ports (232)
FIRST_DOMAIN, DOMAINS = 100, 100
LOCK_DIRECTORY = Path(tempfile.gettempdir())

_held = {}      # offset -> (domain, the open lock file that holds it)


def private_domain(offset: int = 0) -> int:
    """The ROS domain id this process uses for `offset` (offsets keep several node sets of
    one process apart, e.g. a node left from one test and the next test's). The same offset
    gives the same domain for the process's life; raises RuntimeError when every domain of
    the range is held."""
    if offset in _held:
        return _held[offset][0]
    start = (os.getpid() + offset) % DOMAINS
    for step in range(DOMAINS):
        domain = FIRST_DOMAIN + (start + step) % DOMAINS
        lock = open(LOCK_DIRECTORY / f'skel_extract_ros_test_domain_{domain}.lock', 'w')
        try:
            # flock locks an open file, not the process: this process's own other domains
            # are refused too
            fcntl.flock(lock, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except OSError:
            lock.close()
            continue
        _held[offset] = (domain, lock)
        return domain
    raise RuntimeError(f'every test ROS domain {FIRST_DOMAIN}-{FIRST_DOMAIN + DOMAINS - 1} is held by '
                       f'another process')


def private_environment(offset: int = 0, **extra: str) -> dict:
    """os.environ for a child process that starts ROS nodes: on this process's domain for
    `offset`, discovery kept to this machine, plus `extra` (name=value)."""
    return dict(os.environ, ROS_DOMAIN_ID=str(private_domain(offset)), ROS_AUTOMATIC_DISCOVERY_RANGE='LOCALHOST',
                **extra)
