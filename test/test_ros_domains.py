"""The tests' private ROS domains (test/ros_domains.py): a domain another test process holds
is never shared, even when the two processes' ids point both at it."""
import subprocess
import sys
from pathlib import Path

from ros_domains import DOMAINS, private_domain

TEST_DIRECTORY = str(Path(__file__).resolve().parent)
# a process that takes the domain its id (or the id given) points at for offset 0, prints it
# and holds it until its standard input closes
TAKE = '''
import os, sys
sys.path.insert(0, sys.argv[1])
import ros_domains
if len(sys.argv) > 2:
    os.getpid = lambda: int(sys.argv[2])
print(ros_domains.private_domain(0), flush=True)
sys.stdin.read()
'''


def _take(pid=None):
    process = subprocess.Popen([sys.executable, '-c', TAKE, TEST_DIRECTORY] + ([str(pid)] if pid else []),
                               stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True)
    return process, int(process.stdout.readline())


def _release(process):
    process.stdin.close()
    assert process.wait(timeout=30) == 0


def test_a_domain_another_process_holds_is_not_taken_and_is_free_once_it_ends():
    holder, held = _take()
    # a second process whose id points at the same domain (two pids equal modulo 100)
    other, second = _take(pid=holder.pid)
    assert second != held
    _release(other)
    _release(holder)
    again, third = _take(pid=holder.pid)
    assert third == held
    _release(again)


def test_one_process_keeps_its_domain_per_offset_and_never_takes_one_twice():
    first = private_domain(0)
    assert private_domain(0) == first
    # offsets DOMAINS apart point at the same domain: the second is given another one
    assert private_domain(DOMAINS) != first
