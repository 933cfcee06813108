"""accumulator_node: Step 2 on windows of registered frames, grown into one skeleton.

Subscribes  registered_points, filtered_points (PointCloud2, reliable), paired by stamp
            rest_points (PointCloud2, transient local): a new rest pose starts a new skeleton
Publishes   skeleton/structure (std_msgs/String JSON, transient local): bones, bone tree,
            per-point labels, stable joint ids, what changed, and the stamps of the key
            frames it was learned on (see codecs.messages.structure_document)
Service     ~/extract (std_srvs/Trigger): extract now from the frames collected so far

Every window (and with `sliding`, every `stride` frames after it) goes into one growing
skeleton (core.growth): the structure is learned on the most different poses seen so far,
so a joint appears once its part has moved and stays; it is published again only when it
changed. Extraction runs on a Worker (nodes/worker.py) so the subscriptions keep collecting
meanwhile; a window that comes due during an extraction waits for it (a newer one
replaces it; with `lossless`, as in a bag replay, every window waits its turn, so the
skeleton grows through the windows `skel-extract run` learns).
"""
from __future__ import annotations

import collections
import json
import threading
import time
from typing import NoReturn

import numpy as np
from sensor_msgs.msg import PointCloud2
from std_msgs.msg import String
from std_srvs.srv import Trigger

from ..core.growth import SkeletonGrowth
from ..core.structure import StructureError
from .common import (LATCHED_QOS, STREAM_QOS, StampPairer, ThrottledLog, WorkingNode, declare_params,
                     decode_registered_or_warn, decode_rest_or_warn, on_live_parameters, release_freed_memory,
                     run_node)
from ..codecs.messages import stamp_ns, structure_document
from .diagnostics import OK, WARN, NodeDiagnostics
from .worker import LOSSLESS_CAPACITY, RateMeter, Worker

SECTION = 'accumulator_node'


class AccumulatorNode(WorkingNode):
    def __init__(self, **kwargs):
        super().__init__('accumulator_node', **kwargs)
        params = declare_params(self, SECTION)
        self.params, self.schedule, self.settings = params['structure'], params['schedule'], params['node']
        self.log = ThrottledLog(self.get_logger())
        on_live_parameters(self, SECTION, self._apply_parameters)
        self.structure_pub = self.create_publisher(String, 'skeleton/structure', LATCHED_QOS)
        self._lock = threading.Lock()
        self.rest = None                 # (M, 3) float64
        self.rest_stamp = None
        self.growth = None               # the skeleton of the current rest pose
        self.frame_id = ''
        self.frames = collections.OrderedDict()      # stamp ns -> (M, 3) float32, paired only
        self.pairer = StampPairer()      # registered points with their filtered cloud, by stamp
        self._since_extraction = 0
        self._extracted_once = False
        # lossless: every due window waits its turn; live, only the newest waits
        self.extractor = Worker(lambda job: self._extract(*job), 'structure',
                                capacity=LOSSLESS_CAPACITY if self.settings.lossless else 1,
                                on_error=self._extraction_failed)
        self.registered_rate = RateMeter()
        self.last_bones = 0
        self.extractions = 0
        self.published = 0
        self.create_subscription(PointCloud2, 'rest_points', self._on_rest, LATCHED_QOS)
        self.create_subscription(PointCloud2, 'registered_points', self._on_registered, STREAM_QOS)
        self.create_subscription(PointCloud2, 'filtered_points', self._on_filtered, STREAM_QOS)
        self.create_service(Trigger, '~/extract', self._on_extract)
        self.diagnostics = NodeDiagnostics(self, self._diagnostics)
        mode = f'sliding, every {self.schedule.stride} frames' if self.schedule.sliding else 'once'
        self.get_logger().info(f'waiting for registered_points: windows of {self.schedule.window_size} frames ({mode})')

    def _apply_parameters(self, params: dict, _changed: set) -> None:
        """`ros2 param set` of the window (its live parameters): from the next registered frame."""
        with self._lock:
            self.schedule = params['schedule']

    # -- inputs ----------------------------------------------------------------------------
    def _on_rest(self, msg: PointCloud2) -> None:
        if (decoded := decode_rest_or_warn(msg, self.log)) is None:
            return
        rest, rest_stamp = decoded
        with self._lock:
            # frames of the new rest pose may have come in before it (two topics, no order)
            old = [s for s in self.frames if s < rest_stamp or len(self.frames[s]) != len(rest)]
            for stamp in old:
                del self.frames[stamp]
            self.rest, self.rest_stamp, self.frame_id = rest, rest_stamp, msg.header.frame_id
            # the new skeleton's joint ids follow the old one's: a name is one joint for good
            self.growth = SkeletonGrowth(rest, self.params, first_id=0 if self.growth is None else self.growth.next_id)
            self._since_extraction = len(self.frames)
            self._extracted_once = False
        self.get_logger().info(f'new rest pose ({len(rest)} points); window and skeleton restarted'
                               + (f', {len(old)} frames of the previous rest pose dropped' if old else ''))

    def _on_filtered(self, msg: PointCloud2) -> None:
        pair = self.pairer.add(1, stamp_ns(msg.header), True)
        if pair is not None:
            self._add(stamp_ns(msg.header), pair[0])

    def _on_registered(self, msg: PointCloud2) -> None:
        self.registered_rate.tick()
        stamp = stamp_ns(msg.header)
        points = decode_registered_or_warn(msg, self.log, self.rest)
        if points is None:
            return
        pair = self.pairer.add(0, stamp, points)
        if pair is not None:
            self._add(stamp, pair[0])

    def _add(self, stamp: int, points: np.ndarray) -> None:
        with self._lock:
            if self.rest_stamp is not None and stamp < self.rest_stamp:
                return   # a late frame of the previous rest pose
            if stamp in self.frames:
                self.log.warn('duplicate', f'a second registered frame at {stamp * 1e-9:.3f} s: ignored')
                return
            if len(self.frames) >= self.schedule.window_size and stamp < next(iter(self.frames)):
                return   # older than the whole (full) window
            newest = next(reversed(self.frames), None)
            self.frames[stamp] = points
            if newest is not None and stamp < newest:
                # a pair completes when its later half arrives, and a fragmented cloud can be
                # resent seconds late (reliable DDS): the window stays in stamp order, nothing lost
                self.frames = collections.OrderedDict(sorted(self.frames.items()))
            while len(self.frames) > self.schedule.window_size:
                self.frames.popitem(last=False)
            self._since_extraction += 1
            due = self.schedule.due(self._since_extraction, self._extracted_once)
        if due:
            self._start_extraction('window full')

    # -- extraction ------------------------------------------------------------------------
    def _on_extract(self, _request, response):
        with self._lock:
            n, newest = len(self.frames), next(reversed(self.frames), 0)
        if not self.extractor.idle:   # the running extraction answers the request
            response.success, response.message = True, 'an extraction is running; its result will be published'
        elif n < 2 or self.rest is None:
            response.success = False
            response.message = (f'only {n} registered frame(s) collected; need 2' if self.rest is not None
                                else 'no rest_points received yet')
        else:
            response.success = self._start_extraction('requested')
            response.message = f'extracting from {n} frames up to stamp {newest} ns'
        return response

    def _start_extraction(self, reason: str) -> bool:
        with self._lock:
            if self.rest is None:
                self.log.warn('no_rest', f'{len(self.frames)} registered frames but no rest_points yet '
                                         '(is the registration_node running in the same namespace?)')
                return False
            stamps = list(self.frames)
            window = np.stack([self.frames[s] for s in stamps])
            growth, rest_stamp, frame_id = self.growth, self.rest_stamp, self.frame_id
            self._since_extraction = 0
            self._extracted_once = True
        if not self.extractor.idle:
            self.get_logger().info(f'extraction running: the window of {len(stamps)} frames ({reason}) waits '
                                   + ('its turn' if self.settings.lossless else '(a newer one replaces it)'))
        if self.extractor.submit((growth, rest_stamp, frame_id, stamps, window, reason)) and self.settings.lossless:
            self.log.warn('windows_dropped', f'{LOSSLESS_CAPACITY} windows wait for an extraction: the oldest is '
                                             'dropped (the extraction is much slower than the registration)')
        return True

    def _diagnostics(self) -> tuple:
        """(level, state, values) for /diagnostics."""
        with self._lock:
            n_frames, has_rest = len(self.frames), self.rest is not None
            newest = next(reversed(self.frames), 0)
        running = not self.extractor.idle
        if not has_rest:
            level, state = WARN, 'waiting for rest_points'
        elif running:
            level, state = OK, f'extracting the structure from {n_frames} frames'
        elif self.published == 0:
            level, state = OK, f'collecting: {n_frames} of {self.schedule.window_size} frames'
        else:
            level, state = OK, f'skeleton of {self.last_bones} bones published'
        return level, state, {'rate_in_hz': self.registered_rate.rate(), 'frames': n_frames,
                              'newest_stamp_ns': newest,
                              'window_size': self.schedule.window_size, 'extracting': running,
                              'extractions': self.extractions, 'published': self.published,
                              'failed': self.extractor.failed}

    def _extraction_failed(self, _job, error) -> None:
        self.get_logger().error(f'structure extraction failed: {type(error).__name__}: {error}')

    def _extract(self, growth, rest_stamp, frame_id, stamps, window, reason) -> None:
        started = time.perf_counter()
        try:
            update = growth.update(np.array(stamps, dtype=np.int64), window)
        except StructureError as error:
            retry = '' if self.schedule.sliding else f'; trying again on the next {self.schedule.window_size} frames'
            self.get_logger().warning(f'no skeleton from {len(stamps)} frames: {error}{retry}')
            with self._lock:
                self._extracted_once = self.schedule.sliding and self._extracted_once
            return
        structure = update.structure
        self.extractions += 1
        release_freed_memory()
        seconds = time.perf_counter() - started
        if not update.changed:
            self.get_logger().info(f'skeletal structure ({reason}): unchanged, {structure.n_bones} bones '
                                   f'from {len(update.key_stamps)} key frames in {seconds:.1f} s')
            return
        document = structure_document(structure, rest_stamp, update.key_stamps, frame_id, update.joint_ids,
                                      update.changes)
        self.structure_pub.publish(String(data=json.dumps(document)))
        self.published += 1
        self.last_bones = structure.n_bones
        changes = '; '.join(f'{kind} {", ".join(names)}' for kind, names in update.changes.items() if names)
        self.get_logger().info(f'skeletal structure ({reason}): {structure.n_bones} bones from '
                               f'{len(update.key_stamps)} key frames in {seconds:.1f} s'
                               + (f'; {changes}' if changes else ''))

    def stop_work(self) -> None:
        """Stop the extraction thread (not the ROS entities: destroy_node)."""
        self.extractor.stop()


def main(args=None) -> NoReturn:
    run_node(AccumulatorNode, args)


if __name__ == '__main__':
    main()
