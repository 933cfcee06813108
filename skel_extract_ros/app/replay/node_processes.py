"""The three nodes as child processes, as a user starts them, and the DDS profile they
publish with: `skel-extract replay` and the benches (bench_soak) start and stop them here."""
from __future__ import annotations

import os
import signal
import subprocess
import sys
import time
from pathlib import Path

from .recording import NODES


def use_large_message_profile() -> None:
    """Publish like a camera driver configured as README says: Fast DDS's shared-memory
    segment is 512 kB by default, and a third of 1.2 MB clouds at 30 Hz (600 kB 640x480
    depth images too) never reached the node on a loaded 2-core machine; the publisher's
    segment is what counts (bench/README.md, "Large clouds over shared memory"). Sets
    FASTRTPS_DEFAULT_PROFILES_FILE to the packaged 4 MB profile unless it or
    FASTDDS_DEFAULT_PROFILES_FILE is set; call before rclpy.init (Fast DDS reads it once),
    the nodes started after inherit it."""
    from ...config import fastdds_profile_file
    profile = fastdds_profile_file()
    if profile is not None and not (os.environ.get('FASTRTPS_DEFAULT_PROFILES_FILE')
                                    or os.environ.get('FASTDDS_DEFAULT_PROFILES_FILE')):
        os.environ['FASTRTPS_DEFAULT_PROFILES_FILE'] = str(profile)


def start_nodes(params_file: Path | None, namespace: str | None, logs: Path, depth_image: bool = False,
                 lossless: bool = True) -> dict:
    """Start the three nodes (`python -m skel_extract_ros.nodes.<name>`), their output in
    logs/<name>.log; lossless: as a lossless replay needs them (reliable input, nothing
    skipped, joints for every registered frame). Returns {name: (Popen, log file)}."""
    logs.mkdir(parents=True, exist_ok=True)
    env = dict(os.environ, PYTHONUNBUFFERED='1')
    processes = {}
    for name in NODES:
        command = [sys.executable, '-m', f'skel_extract_ros.nodes.{name}', '--ros-args']
        if params_file is not None:
            command += ['--params-file', str(params_file)]
        if name == 'registration_node':
            if lossless:   # a lossless replay must not lose clouds (see the node)
                command += ['-p', 'input_reliability:=reliable', '-p', 'lossless:=true']
            if depth_image:
                command += ['-p', 'input:=depth_image']
        if name == 'accumulator_node' and lossless:   # the windows `run` learns: none replaced
            command += ['-p', 'lossless:=true']
        if name == 'joint_estimation_node' and lossless:   # the joints `run` gives: every registered frame
            command += ['-p', 'live_frames:=registered', '-p', 'lossless:=true']
        if namespace:
            command += ['-r', f'__ns:={namespace}']
        log = open(logs / f'{name}.log', 'w')
        processes[name] = (subprocess.Popen(command, stdout=log, stderr=subprocess.STDOUT, env=env), log)
    return processes


def stop_nodes(processes: dict) -> dict:
    """SIGINT (Ctrl-C) every node, as a user would; returns {name: exit code}. A node still
    running 20 s later is asked for its threads' stacks (SIGUSR1: into its log, see
    nodes.common.run_node), then killed (exit code -9)."""
    for process, _ in processes.values():
        if process.poll() is None:
            process.send_signal(signal.SIGINT)
    codes = {}
    for name, (process, log) in processes.items():
        try:
            codes[name] = process.wait(timeout=20)
        except subprocess.TimeoutExpired:
            process.send_signal(signal.SIGUSR1)
            time.sleep(1.0)
            process.kill()
            codes[name] = process.wait()
        log.close()
    return codes


def log_tail(path: Path, lines: int = 3) -> str:
    try:
        return ' | '.join(path.read_text().strip().splitlines()[-lines:])
    except OSError:
        return ''
