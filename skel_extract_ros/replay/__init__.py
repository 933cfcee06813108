"""`skel-extract replay`: the three nodes as separate processes over real DDS, fed from a bag.

The bag's clouds are published on `points` (depth images on `depth/image`, with their
camera info on `depth/camera_info`, and the registration node set to input:=depth_image)
with their original header stamps, at the bag's pace scaled by `rate` (0 = as fast as the
registration node takes them).
- Lossless (the default): a frame is never published before the registration node has
  segmented the previous one, the registration node never skips one (lossless:=true: its
  segmentation waits for registration) and the joint node answers registered frames
  (live_frames:=registered), so the replay loses nothing however slow the machine is and
  gives the joints `skel-extract run` gives; the printed rate says what was sustained.
- `realtime`: like a camera, at the bag's pace (times `rate`), best effort, never waiting
  for the nodes, every node on its defaults (camera frames get live joints); the summary
  then says how many camera frames got joints, at what rate, and with what latency (cloud
  published -> joints received).
Every output topic and /diagnostics is recorded (raw CDR, receive time) into
DIR/output.mcap, one self-contained MCAP file (schemas and summary inside) that Foxglove
opens and `ros2 bag play DIR/output.mcap` plays (rosbags writes a bag directory; its one
file is moved into place when the recording closes). skeleton.json / skeleton.bvh /
registered.npz / skeleton.png are written from the received messages: the same files as
`skel-extract run`. skeleton.json has a frame for every input frame that got joints (with
the final skeleton's joint count): lossless, the registered frames; realtime, every camera
frame answered, live ones included. skeleton.bvh and skeleton.png need the registered
points of a frame: the registered frames with joints.
"""
from __future__ import annotations

import os
import shutil
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path

import numpy as np

from .recording import NODES, OUTPUT_TOPICS, Received, _Recorder, _ros_type
from .summary import _camera_delivery, _latencies, _write_files

class ReplayError(RuntimeError):
    """Replay could not finish; the message is one line for the user."""


def use_large_message_profile() -> None:
    """Publish like a camera driver configured as README says: Fast DDS's shared-memory
    segment is 512 kB by default, and a third of 1.2 MB clouds at 30 Hz (600 kB 640x480
    depth images too) never reached the node on a loaded 2-core machine; the publisher's
    segment is what counts (bench/README.md, "Large clouds over shared memory"). Sets
    FASTRTPS_DEFAULT_PROFILES_FILE to the packaged 4 MB profile unless it or
    FASTDDS_DEFAULT_PROFILES_FILE is set; call before rclpy.init (Fast DDS reads it once),
    the nodes started after inherit it."""
    from ..config import fastdds_profile_file
    profile = fastdds_profile_file()
    if profile is not None and not (os.environ.get('FASTRTPS_DEFAULT_PROFILES_FILE')
                                    or os.environ.get('FASTDDS_DEFAULT_PROFILES_FILE')):
        os.environ['FASTRTPS_DEFAULT_PROFILES_FILE'] = str(profile)


def _start_nodes(params_file: Path | None, namespace: str | None, logs: Path, depth_image: bool = False,
                 lossless: bool = True) -> dict:
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
        if name == 'joint_estimation_node' and lossless:   # the joints `run` gives: every registered frame
            command += ['-p', 'live_frames:=registered']
        if namespace:
            command += ['-r', f'__ns:={namespace}']
        log = open(logs / f'{name}.log', 'w')
        processes[name] = (subprocess.Popen(command, stdout=log, stderr=subprocess.STDOUT, env=env), log)
    return processes


def _stop_nodes(processes: dict) -> dict:
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


def _log_tail(path: Path, lines: int = 3) -> str:
    try:
        return ' | '.join(path.read_text().strip().splitlines()[-lines:])
    except OSError:
        return ''


def _held_messages(input_path: Path, topic: str) -> list:
    """The raw messages of `topic`, in memory (for passes played backwards); ReplayError when
    they would take more than half the memory the system has available."""
    from ..bag import _raw_messages
    budget = _available_memory_bytes() // 2
    held, size = [], 0
    for _time, raw in _raw_messages(input_path, topic):
        held.append(raw)
        size += len(raw)
        if size > budget:
            raise ReplayError(f'--bounce holds the bag in memory, and {input_path} is larger than half the '
                              f'memory available ({budget * 2e-9:.1f} GB): play it without --bounce')
    return held


def _available_memory_bytes() -> int:
    """MemAvailable of /proc/meminfo (bytes), or the free physical pages where there is none."""
    try:
        with open('/proc/meminfo') as meminfo:
            for line in meminfo:
                if line.startswith('MemAvailable:'):
                    return int(line.split()[1]) * 1024
    except OSError:
        pass
    return os.sysconf('SC_AVPHYS_PAGES') * os.sysconf('SC_PAGE_SIZE')


def looped_stamp(original: int, pass_index: int, pass_ns: int, mirror_ns: int, bounce: bool) -> int:
    """The stamp (ns) a bag message stamped `original` gets in pass `pass_index` of a looped
    replay: moved on by a pass (the bag's length and one period, `pass_ns`) each pass; with
    `bounce` every odd pass plays the bag backwards, its stamps mirrored about the middle of
    the bag (`mirror_ns` = first + last stamp), so the last frame of a pass and the first of
    the next are one period apart either way and the motion stays continuous."""
    return (mirror_ns - original if bounce and pass_index % 2 else original) + pass_index * pass_ns


def replay(input_path, out, rate: float = 1.0, topic: str | None = None, params_file=None,
           namespace: str | None = None, frame_timeout: float = 20.0, progress=None,
           realtime: bool = False, loops: int = 1, bounce: bool = False) -> dict:
    """Run the node graph on a bag; writes DIR/output.mcap, skeleton.json, skeleton.bvh,
    registered.npz, skeleton.png and DIR/logs/<node>.log. Returns a summary dict (counts,
    latencies; with `realtime`, 'realtime': the camera-like delivery). `loops` (realtime
    only): play the bag that many times, the stamps of each pass moved on by the bag's
    length so time never goes back (each pass starts with a jump to the first pose; with
    `bounce` every other pass plays the bag backwards instead, see `looped_stamp`: the
    bag's messages are then held in memory).
    Raises ReplayError / BagError on failure."""
    import rclpy
    from rclpy.executors import SingleThreadedExecutor
    from rclpy.serialization import deserialize_message, serialize_message
    from rosbags.rosbag2 import CompressionFormat, CompressionMode, StoragePlugin, Writer
    from std_srvs.srv import Trigger

    from ..nodes.conversions import stamp_ns

    from ..bag import _raw_messages, camera_info_topic, cloud_topics, is_depth_topic, select_cloud_topic, typestore
    from ..config import default_params_file, load_params_file

    input_path, out = Path(input_path), Path(out)
    if rate < 0:
        raise ReplayError(f'--rate must be >= 0 (0 = as fast as possible), got {rate}')
    if realtime and rate == 0:
        raise ReplayError('--realtime needs a --rate above 0 (1 = the bag\'s own pace)')
    if loops < 1 or (loops > 1 and not realtime):
        raise ReplayError(f'--loop must be >= 1 and needs --realtime (a lossless replay learns one window), '
                          f'got {loops}')
    topic = select_cloud_topic(input_path, topic)
    n_frames = cloud_topics(input_path)[topic]
    if n_frames < 2:
        raise ReplayError(f'{input_path}: {n_frames} cloud(s) on {topic}; at least 2 are needed')
    params_file = Path(params_file) if params_file else default_params_file()
    if params_file is not None:
        load_params_file(params_file)   # fail early, in this process, on a bad file
    if (out / 'output.mcap').exists():
        raise ReplayError(f'{out / "output.mcap"} exists already; choose a new --out or remove it')
    out.mkdir(parents=True, exist_ok=True)

    # --bounce plays passes backwards: the bag's messages are held, read before any node starts
    held = _held_messages(input_path, topic) if bounce and loops > 1 else None
    store = typestore()
    depth_image = is_depth_topic(input_path, topic)
    cloud_type = _ros_type('sensor_msgs/msg/Image' if depth_image else 'sensor_msgs/msg/PointCloud2')
    infos = []
    if depth_image:   # (stamp ns, raw CDR) of every camera info, to send before its image
        info_type = _ros_type('sensor_msgs/msg/CameraInfo')
        infos = [(stamp_ns(deserialize_message(bytes(raw), info_type).header), bytes(raw))
                 for _t, raw in _raw_messages(input_path, camera_info_topic(topic))]
        info_stamps = np.array([stamp for stamp, _ in infos])
    received = Received()
    use_large_message_profile()
    context = rclpy.Context()
    rclpy.init(context=context)
    processes = _start_nodes(params_file, namespace, out / 'logs', depth_image, lossless=not realtime)
    # rosbags writes a bag directory DIR/.recording/ holding .recording.mcap; the file is
    # all a reader needs, so it becomes DIR/output.mcap when the recording closes
    recording = out / '.recording'
    shutil.rmtree(recording, ignore_errors=True)
    writer = Writer(recording, version=9, storage_plugin=StoragePlugin.MCAP)
    writer.set_compression(CompressionMode.STORAGE, CompressionFormat.ZSTD)
    writer.open()
    node = rclpy.create_node('skel_extract_replay', namespace=namespace or '', context=context)
    executor = SingleThreadedExecutor(context=context)
    executor.add_node(node)
    spinner = threading.Thread(target=executor.spin, daemon=True)
    exit_codes = {}
    try:
        recorder = _Recorder(node, writer, store, received, depth_image, lossless=not realtime)
        spinner.start()

        def alive():
            for name, (process, _) in processes.items():
                if process.poll() is not None:
                    raise ReplayError(f'{name} exited with code {process.returncode}: '
                                      f'{_log_tail(out / "logs" / f"{name}.log")}')

        # Every link between the nodes must be up too, not only ours: a volatile stream
        # loses what is published before its subscriber is discovered (the joint node
        # once missed the first five registered frames that way).
        internal = {'rest_points': 3, 'registered_points': 3, 'filtered_points': 3, 'skeleton/structure': 2}

        # ... and the graph as this node sees it is not enough: the accumulator once missed
        # the first 3 registered frames, its reader not yet matched to the registration node's
        # writer. The registration node says how many readers its outputs have matched.
        def connected():
            return (recorder.publisher.get_subscription_count() >= 1
                    and (recorder.info_publisher is None or recorder.info_publisher.get_subscription_count() >= 1)
                    and all(node.count_publishers(t) >= 1 for t, _, _ in OUTPUT_TOPICS)
                    and all(node.count_subscribers(t) >= n for t, n in internal.items())
                    and int(received.registration.get('outputs_matched', 0)) >= 3)
        if not recorder.wait_for(connected, 120.0, alive):
            raise ReplayError('the nodes did not come up within 120 s (see DIR/logs)')

        started = time.perf_counter()
        first_stamp, previous, pass_ns, mirror_ns = None, None, 0, 0

        def restamped(raw, msg_type, pass_index):
            """(original stamp ns, its stamp in this pass, raw CDR) of a message."""
            msg = deserialize_message(bytes(raw), msg_type)
            original = stamp_ns(msg.header)
            stamp = looped_stamp(original, pass_index, pass_ns, mirror_ns, bounce)
            if stamp != original:
                msg.header.stamp.sec, msg.header.stamp.nanosec = divmod(stamp, 10**9)
                raw = serialize_message(msg)
            return original, stamp, bytes(raw)
        if held is not None:
            bag_messages = (raw for pass_index in range(loops) for raw in (held[::-1] if pass_index % 2 else held))
        else:
            bag_messages = (raw for _pass in range(loops) for _time, raw in _raw_messages(input_path, topic))
        for index, raw in enumerate(bag_messages):
            if index == n_frames:   # the bag's length and one period: a pass moves the stamps on by it
                pass_ns = (previous - first_stamp) * n_frames // (n_frames - 1)
                mirror_ns = first_stamp + previous
            pass_index = index // n_frames
            original, stamp, raw = restamped(raw, cloud_type, pass_index)
            first_stamp = stamp if first_stamp is None else first_stamp
            if not realtime and previous is not None and not recorder.wait_for(
                    lambda s=previous: s in received.filtered_at, frame_timeout, alive):
                print(f'skel-extract replay: no answer to cloud {index - 1} within {frame_timeout:.0f} s; '
                      'going on', file=sys.stderr)
            if rate > 0:
                due = started + (stamp - first_stamp) * 1e-9 / rate
                time.sleep(max(0.0, due - time.perf_counter()))
            if not realtime and not recorder.wait_for(lambda: _described(received), 120.0, alive):
                print('skel-extract replay: the newest skeleton/structure was not described within 120 s; '
                      'going on', file=sys.stderr)
            received.published_at[stamp] = time.perf_counter()
            if depth_image:   # the camera info at or before the image goes first
                info = infos[max(int(np.searchsorted(info_stamps, original, side='right')) - 1, 0)]
                recorder.info_publisher.publish(restamped(info[1], info_type, pass_index)[2])
            recorder.publisher.publish(raw)
            previous = stamp
            if progress:
                progress(index + 1, n_frames * loops)
        if realtime:
            # frames may have been skipped, the last one too: wait until the nodes go quiet
            streamed_until = time.perf_counter()
            while True:
                seen = len(received.registered_at) + len(received.filtered_at)
                recorder.wait_for(lambda: len(received.registered_at) + len(received.filtered_at) > seen,
                                  3.0, alive)
                if len(received.registered_at) + len(received.filtered_at) == seen:
                    break
        else:
            recorder.wait_for(lambda: previous in received.filtered_at, frame_timeout, alive)
            # the last registered frame must be in before the window is closed by hand; once a
            # rest pose exists every frame is registered unless it fails (then nothing comes),
            # and a busy machine can take seconds per frame
            recorder.wait_for(lambda: previous in received.registered_at,
                              frame_timeout if received.rest is not None else 5.0, alive)
        streamed = (streamed_until if realtime else time.perf_counter()) - started
        if not received.registered:
            raise ReplayError('no cloud was registered (no rest pose: is the subject in view? '
                              f'{_log_tail(out / "logs" / "registration_node.log")})')
        if received.structure is None:
            # the accumulator can be behind the recorder (and pairs complete in any order):
            # the window must hold every replayed frame, as `run`'s does (its 1 Hz diagnostics tell)
            def collected():
                values = received.accumulator
                return bool(values) and int(values['frames']) >= min(int(values['window_size']),
                                                                    len(received.registered)) \
                    and int(values['newest_stamp_ns']) >= max(received.registered)
            if not recorder.wait_for(collected, 10.0, alive):
                print('skel-extract replay: the accumulator did not report every registered frame '
                      f'within 10 s ({received.accumulator.get("frames", "no")} frames); extracting anyway',
                      file=sys.stderr)
            client = node.create_client(Trigger, 'accumulator_node/extract')
            if not client.wait_for_service(timeout_sec=30.0):
                raise ReplayError('accumulator_node/extract is not available')
            future = client.call_async(Trigger.Request())
            recorder.wait_for(future.done, 30.0, alive)
            response = future.result()
            if response is None or not response.success:
                raise ReplayError(f'accumulator_node/extract refused: {response.message if response else "no reply"}')
        budget = 120.0 + 5.0 * len(received.registered)
        if not recorder.wait_for(lambda: received.structure is not None, budget, alive):
            raise ReplayError('no skeleton/structure: ' + _log_tail(out / 'logs' / 'accumulator_node.log', 1))

        # lossless: every registered frame gets joints; realtime: the window's frames (Alg. 2
        # answers them), the camera frames only as fast as the live fit goes
        must_have = (received.structure['window_stamps_ns'] if realtime else received.registered)

        def complete():
            # markers follow each joints message: the last ones must be in before the nodes stop
            # (the sample bag's test once recorded 58 markers for 59 joints)
            return (received.description is not None and all(s in received.joints for s in must_have)
                    and received.counts.get('skeleton/markers', 0) >= received.counts.get('skeleton/joints', 0))
        if not recorder.wait_for(complete, budget, alive):
            raise ReplayError('joints missing for some frames: '
                              + _log_tail(out / 'logs' / 'joint_estimation_node.log', 1))
    finally:
        exit_codes = _stop_nodes(processes)
        executor.shutdown()
        node.destroy_node()
        rclpy.shutdown(context=context)
        writer.close()
        (recording / '.recording.mcap').replace(out / 'output.mcap')
        shutil.rmtree(recording, ignore_errors=True)

    summary = _write_files(received, out)
    summary.update(_latencies(received, realtime))
    if realtime:
        summary['realtime'] = _camera_delivery(received, streamed)
    summary['streamed_s'] = streamed
    summary['clouds_per_s'] = n_frames * loops / streamed
    summary['exit_codes'] = exit_codes
    summary['counts'] = dict(received.counts)
    return summary


def _described(received: Received) -> bool:
    """Whether the joint node has described the newest structure (or there is none yet).
    Lossless, a frame is published only then: a skeleton that grows (sliding windows) has
    grown before the frames after the update are answered, whatever the machine's speed
    (else how many frames get the grown skeleton depends on how long Alg. 2 takes)."""
    structure, description = received.structure, received.description
    return structure is None or (description is not None and
                                 set(description['window_stamps_ns']) == set(structure['window_stamps_ns']))


