"""The package builds with colcon as a ROS user would, and its executables start."""
import os
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

from ros_domains import private_environment

REPO_ROOT = Path(__file__).resolve().parents[1]
COLCON = shutil.which('colcon', path=str(Path(sys.executable).parent))
IGNORED = shutil.ignore_patterns('.git', '.venv', 'build', 'install', 'log', 'out', '__pycache__',
                                 '*.egg-info', '.pytest_cache', 'bags')


@pytest.fixture(scope='module')
def colcon_install(tmp_path_factory):
    if COLCON is None:
        pytest.fail('colcon is not installed; run scripts/setup_env.sh')
    workspace = tmp_path_factory.mktemp('ws')
    shutil.copytree(REPO_ROOT, workspace / 'src' / 'skel_extract_ros', ignore=IGNORED)
    done = subprocess.run([COLCON, 'build', '--packages-select', 'skel_extract_ros'],
                          cwd=workspace, capture_output=True, text=True, timeout=600)
    assert done.returncode == 0, done.stdout + done.stderr
    return workspace / 'install' / 'skel_extract_ros'


def test_executables_land_in_lib_and_start(colcon_install):
    lib = colcon_install / 'lib' / 'skel_extract_ros'
    executable = lib / 'skel-extract'
    assert executable.is_file() and os.access(executable, os.X_OK)
    assert (colcon_install / 'share' / 'skel_extract_ros' / 'package.xml').is_file()
    assert (colcon_install / 'share' / 'ament_index' / 'resource_index' / 'packages' / 'skel_extract_ros').is_file()
    assert (colcon_install / 'share' / 'skel_extract_ros' / 'params' / 'skel_extract.yaml').is_file()
    assert (colcon_install / 'share' / 'skel_extract_ros' / 'params' / 'fastdds_large_messages.xml').is_file()
    assert (colcon_install / 'share' / 'skel_extract_ros' / 'launch' / 'skel_extract.launch.py').is_file()
    assert (colcon_install / 'share' / 'skel_extract_ros' / 'rviz' / 'skel_extract.rviz').is_file()
    env = dict(os.environ, PYTHONPATH=os.pathsep.join(str(p) for p in
                                                      colcon_install.glob('lib/python3*/site-packages')))
    done = subprocess.run([str(executable), '--help'], capture_output=True, text=True, env=env, timeout=120)
    assert done.returncode == 0 and 'simulate' in done.stdout
    done = subprocess.run([str(executable), 'no-such-command'], capture_output=True, text=True, env=env, timeout=120)
    assert done.returncode == 2 and 'Traceback' not in done.stderr


@pytest.mark.parametrize('name', ['registration_node', 'accumulator_node', 'joint_estimation_node'])
def test_installed_nodes_come_up_and_shut_down_cleanly(colcon_install, name, tmp_path):
    executable = colcon_install / 'lib' / 'skel_extract_ros' / name
    assert executable.is_file() and os.access(executable, os.X_OK)
    env = private_environment(PYTHONPATH=os.pathsep.join(str(p) for p in
                                                         colcon_install.glob('lib/python3*/site-packages')),
                              PYTHONUNBUFFERED='1')
    log = tmp_path / 'node.log'
    with open(log, 'w') as stream:
        process = subprocess.Popen([str(executable)], stdout=stream, stderr=subprocess.STDOUT, env=env)
        deadline = time.monotonic() + 120
        while 'waiting for' not in log.read_text():      # its "ready" line
            assert process.poll() is None, log.read_text()
            assert time.monotonic() < deadline, 'the node did not come up: ' + log.read_text()
            time.sleep(0.05)
        process.send_signal(signal.SIGINT)
        assert process.wait(timeout=30) == 0, log.read_text()
    assert 'Traceback' not in log.read_text()
