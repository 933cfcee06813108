"""`skel-extract replay`: the three nodes as separate processes over real DDS, fed from a bag.

The bag's clouds are published on `points` (depth images on `depth/image`, with their
camera info on `depth/camera_info`, and the registration node set to input:=depth_image)
with their original header stamps, at the bag's pace scaled by `rate` (0 = as fast as the
registration node takes them).
- Lossless (the default): a frame is never published before the registration node has
  segmented the previous one, the registration node never skips one (lossless:=true: its
  segmentation waits for registration), the accumulator learns every window that comes due
  (lossless:=true: none replaced by a newer one) and the joint node runs Alg. 2 on every
  structure (lossless:=true) and answers registered frames (live_frames:=registered), so
  the replay loses nothing however slow the machine is and gives the joints `skel-extract
  run` gives; it ends once the accumulator has learned every
  window and the joint node has described the newest structure (a growing skeleton ends as
  run's does). The printed rate says what was sustained.
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
import sys
import time
from pathlib import Path

import numpy as np

from .node_processes import log_tail, start_nodes, stop_nodes, use_large_message_profile
from .recording import OUTPUT_TOPICS, Received, _Recorder, _ros_type
from .summary import _camera_delivery, _latencies, _write_files

__all__ = ['ReplayError', 'looped_stamp', 'replay', 'use_large_message_profile']

# Every link between the nodes must be up before the first cloud, not only ours: a volatile
# stream loses what is published before its subscriber is discovered. Readers per topic.
INTERNAL_READERS = {'rest_points': 3, 'registered_points': 3, 'filtered_points': 3, 'skeleton/structure': 2}


class ReplayError(RuntimeError):
    """Replay could not finish; the message is one line for the user."""


def _held_messages(input_path: Path, topic: str) -> list:
    """The raw messages of `topic`, in memory (for passes played backwards); ReplayError when
    they would take more than half the memory the system has available."""
    from ...codecs.bag import _raw_messages
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
    return _Replay(Path(input_path), Path(out), rate, topic, params_file, namespace, frame_timeout, progress,
                   realtime, loops, bounce).run()


class _Replay:
    """One replay: the bag checked and read (constructor), then `run`: the nodes started, the
    links waited for, the bag streamed, the window closed, the joints waited for."""

    def __init__(self, input_path: Path, out: Path, rate, topic, params_file, namespace, frame_timeout,
                 progress, realtime, loops, bounce):
        from rclpy.serialization import deserialize_message

        from ...codecs.bag import _raw_messages, camera_info_topic, cloud_topics, is_depth_topic, select_cloud_topic
        from ...codecs.messages import stamp_ns
        from ...config import default_params_file, load_params_file
        if rate < 0:
            raise ReplayError(f'--rate must be >= 0 (0 = as fast as possible), got {rate}')
        if realtime and rate == 0:
            raise ReplayError('--realtime needs a --rate above 0 (1 = the bag\'s own pace)')
        if loops < 1 or (loops > 1 and not realtime):
            raise ReplayError(f'--loop must be >= 1 and needs --realtime (a lossless replay learns one window), '
                              f'got {loops}')
        self.input_path, self.out, self.rate, self.namespace = input_path, out, rate, namespace
        self.frame_timeout, self.progress, self.realtime = frame_timeout, progress, realtime
        self.loops, self.bounce = loops, bounce
        self.topic = select_cloud_topic(input_path, topic)
        self.n_frames = cloud_topics(input_path)[self.topic]
        if self.n_frames < 2:
            raise ReplayError(f'{input_path}: {self.n_frames} cloud(s) on {self.topic}; at least 2 are needed')
        self.params_file = Path(params_file) if params_file else default_params_file()
        if self.params_file is not None:
            load_params_file(self.params_file)   # fail early, in this process, on a bad file
        if (out / 'output.mcap').exists():
            raise ReplayError(f'{out / "output.mcap"} exists already; choose a new --out or remove it')
        out.mkdir(parents=True, exist_ok=True)
        # --bounce plays passes backwards: the bag's messages are held, read before any node starts
        self.held = _held_messages(input_path, self.topic) if bounce and loops > 1 else None
        self.depth_image = is_depth_topic(input_path, self.topic)
        self.cloud_type = _ros_type('sensor_msgs/msg/Image' if self.depth_image else 'sensor_msgs/msg/PointCloud2')
        self.info_type = _ros_type('sensor_msgs/msg/CameraInfo')
        # (stamp ns, raw CDR) of every camera info, to send before its image
        self.infos = [(stamp_ns(deserialize_message(bytes(raw), self.info_type).header), bytes(raw))
                      for _t, raw in _raw_messages(input_path, camera_info_topic(self.topic))] \
            if self.depth_image else []
        self.info_stamps = np.array([stamp for stamp, _ in self.infos])
        self.received = Received()

    def run(self) -> dict:
        from rosbags.rosbag2 import CompressionFormat, CompressionMode, StoragePlugin, Writer

        from ...codecs.bag import typestore
        from ...nodes.background import BackgroundNode
        use_large_message_profile()
        helper = BackgroundNode('skel_extract_replay', self.namespace)
        self.processes = start_nodes(self.params_file, self.namespace, self.out / 'logs', self.depth_image,
                                     lossless=not self.realtime)
        # rosbags writes a bag directory DIR/.recording/ holding .recording.mcap; the file is
        # all a reader needs, so it becomes DIR/output.mcap when the recording closes
        recording = self.out / '.recording'
        shutil.rmtree(recording, ignore_errors=True)
        writer = Writer(recording, version=9, storage_plugin=StoragePlugin.MCAP)
        writer.set_compression(CompressionMode.STORAGE, CompressionFormat.ZSTD)
        writer.open()
        self.node = helper.node
        try:
            self.recorder = _Recorder(self.node, writer, typestore(), self.received, self.depth_image,
                                      lossless=not self.realtime)
            helper.start()
            self._connect()
            started = time.perf_counter()
            streamed_until = self._stream(started)
            streamed = streamed_until - started
            self._close_window()
            self._wait_for_joints()
        finally:
            exit_codes = stop_nodes(self.processes)
            helper.close()
            writer.close()
            (recording / '.recording.mcap').replace(self.out / 'output.mcap')
            shutil.rmtree(recording, ignore_errors=True)
        summary = _write_files(self.received, self.out)
        summary.update(_latencies(self.received, self.realtime))
        if self.realtime:
            summary['realtime'] = _camera_delivery(self.received, streamed)
        summary['streamed_s'] = streamed
        summary['clouds_per_s'] = self.n_frames * self.loops / streamed
        summary['exit_codes'] = exit_codes
        summary['counts'] = dict(self.received.counts)
        return summary

    def _alive(self) -> None:
        for name, (process, _) in self.processes.items():
            if process.poll() is not None:
                raise ReplayError(f'{name} exited with code {process.returncode}: '
                                  f'{log_tail(self.out / "logs" / f"{name}.log")}')

    def _wait(self, condition, timeout: float) -> bool:
        return self.recorder.wait_for(condition, timeout, self._alive)

    def _connect(self) -> None:
        """Every link up: ours to the nodes, the nodes' among themselves (INTERNAL_READERS),
        and, because the graph as this node sees it is not enough (a reader not yet matched
        to the writer loses the first frames), the registration node's own count of the
        readers its outputs have matched."""
        recorder, node, received = self.recorder, self.node, self.received

        def connected():
            return (recorder.publisher.get_subscription_count() >= 1
                    and (recorder.info_publisher is None or recorder.info_publisher.get_subscription_count() >= 1)
                    and all(node.count_publishers(t) >= 1 for t, _, _ in OUTPUT_TOPICS)
                    and all(node.count_subscribers(t) >= n for t, n in INTERNAL_READERS.items())
                    and int(received.registration.get('outputs_matched', 0)) >= 3)
        if not self._wait(connected, 120.0):
            raise ReplayError('the nodes did not come up within 120 s (see DIR/logs)')

    def _stream(self, started: float) -> float:
        """Publish the bag (restamped per pass); lossless, each cloud only once the previous
        one is segmented and the newest structure described. Returns when streaming ended
        (perf_counter s): realtime, once the nodes went quiet."""
        from rclpy.serialization import deserialize_message, serialize_message

        from ...codecs.bag import _raw_messages
        from ...codecs.messages import set_stamp_ns, stamp_ns
        received, n_frames = self.received, self.n_frames
        first_stamp, previous, pass_ns, mirror_ns = None, None, 0, 0

        def restamped(raw, msg_type, pass_index):
            """(original stamp ns, its stamp in this pass, raw CDR) of a message."""
            msg = deserialize_message(bytes(raw), msg_type)
            original = stamp_ns(msg.header)
            stamp = looped_stamp(original, pass_index, pass_ns, mirror_ns, self.bounce)
            if stamp != original:
                set_stamp_ns(msg.header, stamp)
                raw = serialize_message(msg)
            return original, stamp, bytes(raw)
        if self.held is not None:
            held = self.held
            bag_messages = (raw for k in range(self.loops) for raw in (held[::-1] if k % 2 else held))
        else:
            bag_messages = (raw for _pass in range(self.loops)
                            for _time, raw in _raw_messages(self.input_path, self.topic))
        for index, raw in enumerate(bag_messages):
            if index == n_frames:   # the bag's length and one period: a pass moves the stamps on by it
                pass_ns = (previous - first_stamp) * n_frames // (n_frames - 1)
                mirror_ns = first_stamp + previous
            pass_index = index // n_frames
            original, stamp, raw = restamped(raw, self.cloud_type, pass_index)
            first_stamp = stamp if first_stamp is None else first_stamp
            if not self.realtime and previous is not None and not self._wait(
                    lambda s=previous: s in received.filtered_at, self.frame_timeout):
                print(f'skel-extract replay: no answer to cloud {index - 1} within {self.frame_timeout:.0f} s; '
                      'going on', file=sys.stderr)
            if self.rate > 0:
                due = started + (stamp - first_stamp) * 1e-9 / self.rate
                time.sleep(max(0.0, due - time.perf_counter()))
            if not self.realtime and not self._wait(lambda: _described(received), 120.0):
                print('skel-extract replay: the newest skeleton/structure was not described within 120 s; '
                      'going on', file=sys.stderr)
            received.published_at[stamp] = time.perf_counter()
            if self.depth_image:   # the camera info at or before the image goes first
                info = self.infos[max(int(np.searchsorted(self.info_stamps, original, side='right')) - 1, 0)]
                self.recorder.info_publisher.publish(restamped(info[1], self.info_type, pass_index)[2])
            self.recorder.publisher.publish(raw)
            previous = stamp
            if self.progress:
                self.progress(index + 1, n_frames * self.loops)
        if self.realtime:
            # frames may have been skipped, the last one too: wait until the nodes go quiet,
            # and, with no rest pose yet, for one (then its held clouds are registered)
            streamed_until = time.perf_counter()
            while True:
                had_rest = received.rest is not None
                seen = len(received.registered_at) + len(received.filtered_at)
                self._wait(lambda: len(received.registered_at) + len(received.filtered_at) > seen, 3.0)
                if len(received.registered_at) + len(received.filtered_at) > seen:
                    continue
                if had_rest or not self._rest_pose_chosen():
                    return streamed_until
        self._wait(lambda: previous in received.filtered_at, self.frame_timeout)
        # the last registered frame must be in before the window is closed by hand; once a
        # rest pose exists every frame is registered unless it fails (then nothing comes),
        # and a busy machine can take seconds per frame
        if self._rest_pose_chosen():
            self._wait(lambda: previous in received.registered_at, self.frame_timeout)
        return time.perf_counter()

    def _rest_pose_chosen(self) -> bool:
        """Wait for a rest pose once the clouds stopped; False if none came. The registration
        node may hold clouds for the rest pose's choice and choose once they stop coming:
        up to frame_timeout while it reports held clouds, else 5 s (nobody in view)."""
        received = self.received
        holding = int(received.registration.get('clouds_held', 0)) > 0
        return self._wait(lambda: received.rest is not None, self.frame_timeout if holding else 5.0)

    def _close_window(self) -> None:
        """No structure yet (a bag shorter than the window): once the accumulator holds every
        registered frame, ask it to extract, as `run` learns on all frames of a short bag."""
        from std_srvs.srv import Trigger
        received = self.received
        if not received.registered:
            raise ReplayError('no cloud was registered (no rest pose: is the subject in view? '
                              f'{log_tail(self.out / "logs" / "registration_node.log")})')
        if received.structure is None:
            # the accumulator can be behind the recorder (and pairs complete in any order):
            # the window must hold every replayed frame, as `run`'s does (its 1 Hz diagnostics tell)
            def collected():
                values = received.accumulator
                return _accumulator_has_every_frame(received) and \
                    int(values['frames']) >= min(int(values['window_size']), len(received.registered))
            if not self._wait(collected, 10.0):
                print('skel-extract replay: the accumulator did not report every registered frame '
                      f'within 10 s ({received.accumulator.get("frames", "no")} frames); extracting anyway',
                      file=sys.stderr)
            client = self.node.create_client(Trigger, 'accumulator_node/extract')
            if not client.wait_for_service(timeout_sec=30.0):
                raise ReplayError('accumulator_node/extract is not available')
            future = client.call_async(Trigger.Request())
            self._wait(future.done, 30.0)
            response = future.result()
            if response is None or not response.success:
                raise ReplayError(f'accumulator_node/extract refused: {response.message if response else "no reply"}')

    def _wait_for_joints(self) -> None:
        """Lossless: every registered frame has joints; realtime: the first skeleton's frames
        (`answered`), the camera frames only as fast as the live fit goes."""
        received = self.received
        budget = 120.0 + 5.0 * len(received.registered)
        if not self._wait(lambda: received.structure is not None, budget):
            raise ReplayError('no skeleton/structure: ' + log_tail(self.out / 'logs' / 'accumulator_node.log', 1))

        if not self.realtime:
            self._wait_for_growth(budget)

        def complete():
            # markers follow each joints message: the last ones must be in before the nodes stop
            return (answered(received, self.realtime)
                    and received.counts.get('skeleton/markers', 0) >= received.counts.get('skeleton/joints', 0))
        if not self._wait(complete, budget):
            raise ReplayError('joints missing for some frames: '
                              + log_tail(self.out / 'logs' / 'joint_estimation_node.log', 1))

    def _wait_for_growth(self, budget: float) -> None:
        """Lossless: the skeleton as `run` ends it. A skeleton that grows (`sliding`) has
        windows queued at the accumulator (lossless) when the last frame is registered: wait
        until it reports, after having every registered frame, that none is left, and until
        the joint node has described the newest structure."""
        received = self.received
        if not self._wait(lambda: _accumulator_has_every_frame(received), budget):
            raise ReplayError('the accumulator did not report the last registered frame: '
                              + log_tail(self.out / 'logs' / 'accumulator_node.log', 1))
        # a report made while the last frame's window was being queued can still say idle: the next one
        reports = received.accumulator_reports
        if not self._wait(lambda: received.accumulator_reports > reports
                          and received.accumulator.get('extracting') == 'False', budget):
            raise ReplayError('the accumulator is still extracting: '
                              + log_tail(self.out / 'logs' / 'accumulator_node.log', 1))
        if not self._wait(lambda: _described(received), budget):
            raise ReplayError('the newest skeleton/structure was not described: '
                              + log_tail(self.out / 'logs' / 'joint_estimation_node.log', 1))


def _accumulator_has_every_frame(received: Received) -> bool:
    """Whether the accumulator's newest report says it has the newest registered frame."""
    values = received.accumulator
    return bool(values) and int(values['newest_stamp_ns']) >= max(received.registered)


def answered(received: Received, realtime: bool) -> bool:
    """Whether the frames the replay waits for have joints: lossless, every registered
    frame; realtime, the frames the first description was learned on. Nothing had joints
    before that one, so the joint node answers each of them. A skeleton that grows later
    (`sliding`) is learned on key frames that can be minutes old: the node answered them
    live, or skipped them like any camera frame the live fit did not reach, and does not
    answer them again (nodes/joint_stages.py)."""
    if received.description is None:
        return False
    must_have = received.descriptions[0]['window_stamps_ns'] if realtime else received.registered
    return all(stamp in received.joints for stamp in must_have)


def _described(received: Received) -> bool:
    """Whether the joint node has described the newest structure (or there is none yet).
    Lossless, a frame is published only then: a skeleton that grows (sliding windows) has
    grown before the frames after the update are answered, whatever the machine's speed
    (else how many frames get the grown skeleton depends on how long Alg. 2 takes)."""
    structure, description = received.structure, received.description
    return structure is None or (description is not None and
                                 set(description['window_stamps_ns']) == set(structure['window_stamps_ns']))


