"""Soak: the three nodes driven like a camera for a long time; memory and rates over time.

    python bench/bench_soak.py [--minutes 30] [--rate 1] [--bag DIR] [--params FILE]
                               [--sample-s 30] [--work DIR]

A bag's clouds (default: the built-in human in a room, 300 frames, simulated into --work)
are published over and over at the bag's pace times --rate, best effort as a driver does,
their stamps moving on by the bag's length each pass so time never goes back (each pass
starts with a jump from the last pose to the first). Every --sample-s seconds one line:
the resident memory (VmRSS, MB) of each node with its child processes and their sum, and
over the interval the rates of filtered_points, registered_points and skeleton/joints
received (Hz). At the end, each node's memory growth from its first sample after the
skeleton exists to its last.
"""
from __future__ import annotations

import argparse
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from skel_extract_ros.app.replay.node_processes import start_nodes, stop_nodes, use_large_message_profile  # noqa: E402

OUTPUTS = ('filtered_points', 'registered_points', 'skeleton/joints')


def rss_mb(pid: int) -> float:
    """Resident memory of a node with its child processes (the registration node runs
    Alg. 1 in one), MB."""
    total = 0.0
    try:
        for line in Path(f'/proc/{pid}/status').read_text().splitlines():
            if line.startswith('VmRSS:'):
                total += int(line.split()[1]) / 1024.0
        children = [int(c) for task in Path(f'/proc/{pid}/task').iterdir()
                    for c in (task / 'children').read_text().split()]
    except OSError:
        return total if total else float('nan')
    return total + sum(rss_mb(child) for child in children)


def default_bag(work: Path) -> Path:
    bag = work / 'soak_human_room'
    if not (bag / 'metadata.yaml').is_file():
        subprocess.run([sys.executable, '-m', 'skel_extract_ros.app.cli', 'simulate', '--subject', 'human',
                        '--frames', '300', '--scene', 'room', '--out', str(bag)], check=True,
                       capture_output=True)
    return bag


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument('--minutes', type=float, default=30.0)
    parser.add_argument('--rate', type=float, default=1.0, help='times the bag pace (1 = 30 Hz)')
    parser.add_argument('--bag', default=None)
    parser.add_argument('--params', default=None)
    parser.add_argument('--sample-s', type=float, default=30.0)
    parser.add_argument('--work', default=None)
    args = parser.parse_args()

    from geometry_msgs.msg import PoseArray
    from rclpy.serialization import deserialize_message
    from sensor_msgs.msg import PointCloud2

    from skel_extract_ros.codecs.bag import _raw_messages, select_cloud_topic
    from skel_extract_ros.nodes.background import BackgroundNode
    from skel_extract_ros.nodes.common import SENSOR_QOS, STREAM_QOS
    from skel_extract_ros.codecs.messages import stamp_ns

    work = Path(args.work) if args.work else Path(tempfile.mkdtemp(prefix='bench_soak_'))
    work.mkdir(parents=True, exist_ok=True)
    bag = Path(args.bag) if args.bag else default_bag(work)
    topic = select_cloud_topic(bag, None)
    clouds = [deserialize_message(bytes(raw), PointCloud2) for _t, raw in _raw_messages(bag, topic)]
    stamps = [stamp_ns(c.header) for c in clouds]
    period_ns = (stamps[-1] - stamps[0]) // (len(stamps) - 1)
    pass_ns = stamps[-1] - stamps[0] + period_ns

    use_large_message_profile()        # publish as a configured camera driver, as replay does
    # Ctrl-C ends the soak through the finally below (the nodes stopped as a user would)
    helper = BackgroundNode('skel_extract_soak', signal_handlers=False)
    node = helper.node
    processes = start_nodes(Path(args.params) if args.params else None, None, work / 'logs', lossless=False)
    counts = {t: 0 for t in OUTPUTS}
    lock = threading.Lock()

    def counter(name):
        def on_message(_msg):
            with lock:
                counts[name] += 1
        return on_message
    node.create_subscription(PointCloud2, 'filtered_points', counter('filtered_points'), STREAM_QOS)
    node.create_subscription(PointCloud2, 'registered_points', counter('registered_points'), STREAM_QOS)
    node.create_subscription(PoseArray, 'skeleton/joints', counter('skeleton/joints'), STREAM_QOS)
    publisher = node.create_publisher(PointCloud2, 'points', SENSOR_QOS)
    helper.start()
    while publisher.get_subscription_count() < 1:
        time.sleep(0.1)

    pids = {name: process.pid for name, (process, _) in processes.items()}
    print('| minute | ' + ' | '.join(f'{n} MB' for n in pids) + ' | sum MB | filtered Hz | registered Hz | '
          'joints Hz |', flush=True)
    print('|' + '---|' * (len(pids) + 5), flush=True)
    started = time.perf_counter()
    next_sample, last_counts, last_time = started, dict(counts), started
    samples = []   # (minute, {name: MB}, joints Hz)
    published = 0
    try:
        while time.perf_counter() - started < 60.0 * args.minutes:
            index = published % len(clouds)
            cloud = clouds[index]
            stamp = stamps[index] + (published // len(clouds)) * pass_ns
            cloud.header.stamp.sec, cloud.header.stamp.nanosec = divmod(stamp, 10**9)
            due = started + published * period_ns * 1e-9 / args.rate
            time.sleep(max(0.0, due - time.perf_counter()))
            publisher.publish(cloud)
            published += 1
            now = time.perf_counter()
            if now >= next_sample:
                with lock:
                    current = dict(counts)
                span = max(now - last_time, 1e-9)
                rates = {t: (current[t] - last_counts[t]) / span for t in OUTPUTS}
                memory = {name: rss_mb(pid) for name, pid in pids.items()}
                minute = (now - started) / 60.0
                samples.append((minute, memory, rates['skeleton/joints']))
                print(f'| {minute:.1f} | ' + ' | '.join(f'{m:.0f}' for m in memory.values())
                      + f' | {sum(memory.values()):.0f} | {rates["filtered_points"]:.1f} | '
                      f'{rates["registered_points"]:.1f} | {rates["skeleton/joints"]:.1f} |', flush=True)
                last_counts, last_time = current, now
                next_sample = now + args.sample_s
    finally:
        codes = stop_nodes(processes)
        helper.close()
    tracking = [s for s in samples if s[2] > 0]
    if len(tracking) >= 2:
        first, last = tracking[0], tracking[-1]
        growth = {n: last[1][n] - first[1][n] for n in pids}
        print(f'\nmemory growth from minute {first[0]:.1f} (joints flowing) to {last[0]:.1f}: '
              + ', '.join(f'{n} {g:+.0f} MB' for n, g in growth.items())
              + f'; sum {sum(last[1].values()):.0f} MB at the end')
    print(f'{published} clouds published; node exit codes {codes}; logs in {work / "logs"}')
    return 0


if __name__ == '__main__':
    sys.exit(main())
