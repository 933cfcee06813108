"""After a replay: the files `run` writes, from what was received, and what a camera user
got (frames with joints, rates, latencies)."""
from __future__ import annotations

from pathlib import Path

import numpy as np

from .recording import Received


def _write_files(received: Received, out: Path) -> dict:
    from ..outputs import write_registered, write_skeleton

    stamps_ns = sorted(received.registered)
    write_registered(out, np.stack([received.registered[s] for s in stamps_ns]),
                     np.array(stamps_ns, dtype=np.int64) * 1e-9, np.array(['ok'] * len(stamps_ns)),
                     received.rest, received.frame_id)
    # the newest skeleton that answered frames (one described after the last frame answered
    # none), and every frame it answered (a live camera frame has no registered points); a
    # frame answered by another skeleton (before it grew) has other joints, named on
    # skeleton/confidence, and is left out
    def answered_by(description):
        names = description['joint_names']
        return sorted(s for s, p in received.joints.items()
                      if len(p) == len(names) and received.joint_names.get(s, names) == names)
    description = next((d for d in reversed(received.descriptions) if answered_by(d)), received.description)
    answered = answered_by(description)
    structure = next((d for d in received.structures
                      if set(d['window_stamps_ns']) == set(description['window_stamps_ns'])), received.structure)
    write_skeleton(out, description['joint_names'], description['parents'], description['rest_positions'],
                   description['frame_id'], np.array(answered) * 1e-9,
                   np.stack([received.joints[s] for s in answered]), [received.confidence.get(s) for s in answered],
                   received.rest, np.asarray(structure['labels']),
                   registered={row: received.registered[s] for row, s in enumerate(answered) if s in received.registered},
                   observed={row: received.filtered[s] for row, s in enumerate(answered) if s in received.filtered},
                   pivot=description.get('pivot'), interpolated=[s in received.interpolated for s in answered])
    return {'n_frames': len(stamps_ns), 'n_joints': len(description['joint_names']),
            'n_frames_with_joints': len(answered)}


def _camera_delivery(received: Received, streamed_s: float) -> dict:
    """What a camera user got: frames published, frames with joints (and their rate over the
    streaming time), frames without, the seconds from the first camera frame to the first
    skeleton/description (NaN without one), and the latency cloud published -> joints received,
    median / p95 in ms, over the live frames: those published once the skeleton existed (the
    first skeleton/description received). The frames before it that got joints (the
    structure's window and the learning window's other registered frames, which Alg. 2 and
    the registered pose answer seconds later) are counted, not timed."""
    published = received.published_at
    with_joints = [s for s in published if s in received.joints_at]
    tracking_from = received.description_at
    live = ([s for s in with_joints if published[s] >= tracking_from] if tracking_from is not None else [])
    latency = [1000 * (received.joints_at[s] - published[s]) for s in live]
    first_skeleton_s = (tracking_from - min(published.values())
                        if tracking_from is not None and published else float('nan'))
    return {'published': len(published), 'with_joints': len(with_joints), 'first_skeleton_s': first_skeleton_s,
            'without_joints': len(published) - len(with_joints),
            'joints_hz': len(with_joints) / streamed_s if streamed_s > 0 else float('nan'),
            'live_frames': len(live),
            'latency_ms_median': float(np.median(latency)) if latency else float('nan'),
            'latency_ms_p95': float(np.percentile(latency, 95)) if latency else float('nan'),
            'tracking': _tracking_delivery(received, tracking_from) if live else None}


def _tracking_delivery(received: Received, tracking_from: float) -> dict:
    """From the first camera frame published once the skeleton existed (perf_counter s of
    the first skeleton/description) to the last one published: frames published, passed on
    by the camera stage (filtered_points), with joints, and the joints rate over that time
    (Hz), the rate a user gets once the skeleton is tracked."""
    published = {s: t for s, t in received.published_at.items() if t >= tracking_from}
    span_s = max(published.values()) - min(published.values())
    with_joints = sum(s in received.joints_at for s in published)
    return {'published': len(published), 'filtered': sum(s in received.filtered_at for s in published),
            'with_joints': with_joints, 'seconds': span_s,
            'camera_hz': (len(published) - 1) / span_s if span_s > 0 else float('nan'),
            'joints_hz': with_joints / span_s if span_s > 0 else float('nan')}


def _latencies(received: Received, realtime: bool) -> dict:
    """Per-node latency (ms): registration = cloud published -> registered_points received;
    lossless only, joints (live frames) = registered_points received -> skeleton/joints
    received, over the frames registered once the first skeleton/description had come.
    The frames registered before it (the first window, which Alg. 2 answers, and those
    registered while it learned) wait for the skeleton, not for the joint node; a grown
    skeleton's window (`sliding`) holds frames answered live long before it, so no
    structure's window marks them. Realtime joints answer the camera frame, not its
    registration (often before it): their latency is the camera delivery's
    (_camera_delivery)."""
    registration = [1000 * (received.registered_at[s] - received.published_at[s])
                    for s in received.registered_at if s in received.published_at]
    tracking_from = received.description_at
    live = [] if realtime or tracking_from is None else [
        1000 * (received.joints_at[s] - received.registered_at[s])
        for s in received.joints_at if received.registered_at.get(s, -np.inf) >= tracking_from]
    result = {}
    for name, values in (('registration_ms', registration), ('live_joints_ms', live)):
        if values:
            result[name] = {'median': float(np.median(values)), 'worst': float(np.max(values)), 'n': len(values)}
    return result
