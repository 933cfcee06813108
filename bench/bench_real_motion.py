"""Benchmark on real motion: every real clip through the simulated Kinect, `skel-extract run`
end to end, scored against the ground truth.

    python bench/bench_real_motion.py [--frames 90] [--scenes empty,room] [--only wave,cow]
                                      [--work DIR] [--score-only | --relearn] [--json FILE]
                                      [--seeds 0,1,2] [--forms cloud,depth]
                                      [--params FILE] [--baseline FILE]

Subjects: every BVH clip in $SKEL_SHARED_DATA/mocap/ (real actors, on a body of capsules), the
cow rig ($SKEL_SHARED_DATA/rigs/cow, blended between its key poses) and the samba mesh sequence
($SKEL_SHARED_DATA/samba_mesh_sequence.npz, registration only: it has no joints). Each is
rendered at 320x240 with Kinect noise, 90 frames at 30 Hz (the most active window, or the
whole clip when shorter), in an empty scene and in a room (floor, walls, a table, a lamp).
Walks keep their travel (towards the camera, which stays within 4.5 m); runs are put on a
treadmill (`simulate --treadmill`), since 5 m in two seconds leaves any depth camera's view.
`skel-extract run` is started as a user starts it (a subprocess, default parameters) and
its files are scored with skel_extract_ros.app.evaluation (the joints over the registration's
frames: every frame without joints is a miss). Absent data is skipped.

`--seeds` and `--forms` add variants of each bag (other noise seeds; the same frames as
16UC1 depth images instead of clouds) and print the range of each subject's figures over
them (the stability table). Printed: one row per subject and scene (and variant); the median of the headline figures on the tuning
half (TUNING: choices are made there) and on the check half; each anatomical joint over
the rows where it bends or travels (found, and its error split into the offset along the
camera ray, across it, and what is left once the offset is removed); the joints whose
pivot the motion fixed (skeleton.json's `pivot`) against the others, and how many of each
matched a true joint.

`--work DIR` keeps the bags and run outputs (default: a temporary directory); with
`--score-only` nothing is simulated or run again, the outputs in DIR are scored. With
`--relearn` only Steps 2 and 3 run, with `--params`, on each bag's registration kept in
DIR/registrations (registered in this process with the defaults the first time, the bag
simulated if absent): the scores of `run` with those parameters (the same files, to the
digit) in a few seconds a bag, for a Step 2-3 variant; the registration's parameters in
`--params` do not apply, and the kept registrations must be deleted after Steps 0-1 change.
`--baseline FILE` (another run's `--json` rows, e.g. the defaults before a `--params`
variant) adds the change of each half's means, per seed and input form, and on how many
rows each figure rose and fell.
$SKEL_SHARED_DATA is the real data directory (default: `shared/data` beside the checkout).
"""
from __future__ import annotations

import argparse
import itertools
import json
import math
import os
import re
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from skel_extract_ros.app.evaluation import EvaluationError, GroundTruth, evaluate_outputs  # noqa: E402

DATA = Path(os.environ.get('SKEL_SHARED_DATA', REPO.parent / 'shared' / 'data'))
CLI = shutil.which('skel-extract', path=str(Path(sys.executable).parent)) or 'skel-extract'
TIME_LINE = re.compile(r'time: segmentation ([\d.]+) s \| preprocess ([\d.]+) s \| rest pose ([\d.]+) s \| registration ([\d.]+) s '
                       r'\(median (\d+) ms/frame\) \| structure ([\d.]+) s \| joints ([\d.]+) s \| total ([\d.]+) s')


# Choices (defaults, thresholds) are made on the tuning half and reported on both: one clip
# of each pair of styles, the turning walk, on one side; the cow (another body) and the
# samba (another capture) on the check side.
TUNING = ('raise-up-both-hands_normal', 'run_active', 'walk_active', 'walk-turn-left_normal',
          'wave-both-hands_active', 'wave-left-hand_normal')


def half(name: str) -> str:
    return 'tuning' if name in TUNING else 'check'


def subjects(only: list) -> list:
    """(name, simulate arguments) for every subject whose data is present."""
    found = []
    for clip in sorted((DATA / 'mocap').glob('*.bvh')):
        name = clip.stem.replace('dataset-2_', '').replace('_001', '')
        # A run covers 5 m in two seconds, more than a depth camera sees: on a treadmill.
        found.append((name, ['--bvh', str(clip)] + (['--treadmill'] if name.startswith('run') else [])))
    if (DATA / 'rigs' / 'cow' / 'cow.obj').is_file():
        found.append(('cow', ['--rig', str(DATA / 'rigs' / 'cow')]))
    if (DATA / 'samba_mesh_sequence.npz').is_file():
        found.append(('samba', ['--mesh-sequence', str(DATA / 'samba_mesh_sequence.npz')]))
    if only:
        found = [(n, a) for n, a in found if any(o in n for o in only)]
    return found


def simulate(name: str, source_args: list, scene: str, frames: int, bag: Path) -> None:
    """Render the subject into the bag directory `bag` (`skel-extract simulate`)."""
    shutil.rmtree(bag, ignore_errors=True)
    done = subprocess.run([CLI, 'simulate', *source_args, '--frames', str(frames), '--scene', scene,
                           '--out', str(bag)], capture_output=True, text=True)
    if done.returncode != 0:
        raise RuntimeError(f'simulate {name}: {done.stderr.strip().splitlines()[-1]}')


def simulate_and_run(name: str, source_args: list, scene: str, frames: int, work: Path,
                     variant: str | None = None, params: str | None = None) -> dict:
    """Simulate the subject into a bag and `skel-extract run` it (with the parameter file
    `params`, else the defaults); `variant` (default the scene) names the bag when
    source_args hold a seed or an input form."""
    variant = variant or scene
    bag, out = work / f'{name}_{variant}', work / f'{name}_{variant}_out'
    shutil.rmtree(out, ignore_errors=True)
    simulate(name, source_args, scene, frames, bag)
    started = time.perf_counter()
    done = subprocess.run([CLI, 'run', str(bag), '--out', str(out)] + (['--params', params] if params else []),
                          capture_output=True, text=True)
    record = {'wall_s': time.perf_counter() - started, 'returncode': done.returncode,
              'stdout': done.stdout, 'error': done.stderr.strip().splitlines()[-1] if done.returncode else ''}
    (work / f'{name}_{variant}_run.json').write_text(json.dumps(record))
    return record


def relearn(name: str, source_args: list, scene: str, frames: int, work: Path, variant: str,
            params: str | None = None) -> dict:
    """Steps 2 and 3 alone (`--relearn`) with the parameter file `params`, on the bag's
    registration kept in WORK/registrations/: the first time, the bag is simulated if absent
    and registered in this process as `skel-extract run` registers it (the defaults), and
    its registered.npz written. Writes the skeleton.json `run` would and a record as
    simulate_and_run's (wall_s: Steps 2 and 3). A kept registration belongs to the code
    that made it: empty that directory after changing Steps 0-1."""
    import pickle

    from skel_extract_ros.app.cli import step_times_line
    from skel_extract_ros.app.outputs import write_registered
    from skel_extract_ros.codecs.bag import read_cloud_frames, select_cloud_topic
    from skel_extract_ros.config import load_params_file, pipeline_params
    from skel_extract_ros.core.pipeline import SkeletonPipeline
    from skel_extract_ros.core.skeleton_model import pivot_document, skeleton_document
    from skel_extract_ros.core.structure import StructureError

    bag, out = work / f'{name}_{variant}', work / f'{name}_{variant}_out'
    kept = work / 'registrations' / f'{name}_{variant}.pkl'
    if not kept.is_file():
        if not (bag / 'gt.npz').is_file():
            simulate(name, source_args, scene, frames, bag)
        pipeline = SkeletonPipeline()
        clouds = list(read_cloud_frames(bag, select_cloud_topic(bag)))
        registered = pipeline.register(f.points.reshape(f.height, f.width, 3) if f.height > 1 else f.points
                                       for f in clouds)
        kept.parent.mkdir(exist_ok=True)
        with open(kept, 'wb') as file:
            pickle.dump({'registration': pipeline.registration, 'registered': registered,
                         'stamps': np.array([f.stamp for f in clouds]),
                         'frame_id': clouds[0].frame_id if clouds else ''}, file)
    with open(kept, 'rb') as file:
        state = pickle.load(file)
    registration, registered, stamps, frame_id = (state['registration'], state['registered'], state['stamps'],
                                                  state['frame_id'])
    shutil.rmtree(out, ignore_errors=True)
    out.mkdir(parents=True)
    record = {'returncode': 1, 'error': 'no rest pose: the subject was never wholly in view', 'stdout': '',
              'wall_s': 0.0}
    if registration.rest_pose_ is None:
        (work / f'{name}_{variant}_run.json').write_text(json.dumps(record))
        return record
    write_registered(out, registered, stamps, registration.statuses_, registration.rest_pose_.points, frame_id)
    pipeline = SkeletonPipeline(**(pipeline_params(load_params_file(params)) if params else {}))
    pipeline.registration = registration      # Steps 0-1 as kept; Steps 2-3 with `params`
    started = time.perf_counter()
    record.update(returncode=0, error='')
    try:
        result = pipeline.extract(registered)
    except StructureError as error:
        record.update(returncode=1, error=str(error))
    else:
        model, seconds = result.model, result.seconds
        document = skeleton_document(model.joint_names, model.parents, model.rest_joints, stamps[result.frames],
                                     result.joint_positions, frame_id, result.joint_confidence,
                                     pivot_document(model.pivot))
        (out / 'skeleton.json').write_text(json.dumps(document))
        per_frame = 1000.0 * float(np.median(registration.times_.per_frame_registration))
        # the line `run` prints, which score() reads the steps' times from
        record['stdout'] = step_times_line(seconds, per_frame, sum(seconds.values()))
    record['wall_s'] = time.perf_counter() - started
    (work / f'{name}_{variant}_run.json').write_text(json.dumps(record))
    return record


def segmentation_scores(bag: Path, gt_path: Path) -> dict:
    """Per frame, against the simulator's per-pixel mask: the share of the measurable
    subject pixels kept and the share of kept pixels that are background; ms per frame."""
    from skel_extract_ros.codecs.bag import read_cloud_frames
    from skel_extract_ros.core.segmentation import SubjectSegmenter

    data = np.load(gt_path)
    if 'subject_measured' not in data:
        return {}
    measured, subject = data['subject_measured'], data['subject_mask']
    segmenter = SubjectSegmenter()
    kept, background, times = [], [], []
    for frame in read_cloud_frames(bag):
        started = time.perf_counter()
        result = segmenter(frame.points, frame.height, frame.width)
        times.append(time.perf_counter() - started)
        mask = result.mask.reshape(measured.shape[1:])
        truth = measured[frame.index]
        if truth.sum() and result.n_subject:   # frames where both the subject is and was found
            kept.append(mask[truth].mean())
            background.append((mask & ~subject[frame.index]).sum() / mask.sum())
    found = [f for f in range(len(measured)) if measured[f].any()]
    return {'seg_kept_min': float(np.min(kept)) if kept else float('nan'),
            'seg_kept_median': float(np.median(kept)) if kept else float('nan'),
            'seg_background_max': float(np.max(background)) if background else float('nan'),
            'seg_frames_found': len(kept), 'seg_frames_with_subject': len(found),
            'seg_ms_median': 1000 * float(np.median(times)), 'seg_ms_p95': 1000 * float(np.percentile(times, 95))}


JOINT_KEYS = ('n_predicted', 'n_matched', 'recall', 'articulated_recall', 'articulated_recall_10cm',
              'articulated_recall_5cm', 'n_articulated', 'moving_recall', 'n_moving', 'tracking_skill',
              'frame_coverage', 'precision', 'articulated_precision', 'mean_error_m', 'normalized_error_m',
              'motion_skill', 'nonfinite_fraction', 'threshold_m', 'confidence_auc', 'n_far_answers')


def _num(value) -> float:
    return float(value) if value is not None else float('nan')


def score(name: str, scene: str, work: Path) -> dict:
    bag, out = work / f'{name}_{scene}', work / f'{name}_{scene}_out'
    record = json.loads((work / f'{name}_{scene}_run.json').read_text())
    gt = GroundTruth.load(bag / 'gt.npz')
    row = {'subject': name, 'scene': scene, 'half': half(name), 'error': record['error'],
           'wall_s': record['wall_s'], 'true_joints': int(gt.joints.shape[1])}
    row.update(segmentation_scores(bag, bag / 'gt.npz'))
    timing = TIME_LINE.search(record['stdout'])
    if timing:
        keys = ('segmentation_s', 'preprocess_s', 'rest_pose_s', 'registration_s', 'registration_ms_per_frame',
                'structure_s', 'joints_s', 'total_s')
        row.update({k: float(v) for k, v in zip(keys, timing.groups())})
    registered = out / 'registered.npz'
    skeleton = out / 'skeleton.json' if gt.joints.shape[1] and (out / 'skeleton.json').is_file() else None
    scores = evaluate_outputs(gt, skeleton, registered if registered.is_file() else None)
    if 'registration' in scores:
        reg = scores['registration']
        row.update({'reg_mean_m': reg['mean_error_m'], 'reg_p95_m': reg['p95_error_m'],
                    'reg_worst_frame_m': float(np.nanmax(reg['per_frame_error_m'])),
                    'reg_worst_frame_p95_m': _num(reg.get('worst_frame_p95_m')),
                    'per_part': reg.get('per_part', {})})
    if 'joints' in scores:
        report = scores['joints']
        row.update({k: report.get(k) for k in JOINT_KEYS})
        row['missed_articulated'] = report.get('missed_articulated', [])
        row['per_joint'] = report['per_joint']
        row['pivots'] = _pivots(skeleton, report['per_joint'])
    elif gt.joints.shape[1]:
        # No skeleton is no joint found and no frame answered.
        row.update({'n_predicted': 0, 'recall': 0.0, 'articulated_recall': 0.0, 'moving_recall': 0.0,
                    'tracking_skill': 0.0, 'frame_coverage': 0.0})
    return row


def _pivots(skeleton: Path, per_joint: list) -> list:
    """Per found joint but the root: [whether its pivot was fixed by the motion (skeleton.json's
    `pivot`), whether it matched a true joint, whether that one bends]."""
    document = json.loads(skeleton.read_text())
    if not document.get('pivot'):
        return []
    matched = {e['predicted']: e for e in per_joint if e.get('predicted')}
    return [[bool(fixed), name in matched, bool(name in matched and matched[name]['articulated'])]
            for name, fixed in zip(document['joint_names'], document['pivot']['fixed']) if fixed is not None]


def pivot_table(rows: list) -> str:
    """Per half, the joints whose pivot the motion fixed against the others: how many, and
    the share of them that matched a true joint, and a bending one."""
    lines = ['| half | pivot | joints | matched a true joint | matched a bending joint |', '|' + '---|' * 5]
    for name in ('tuning', 'check'):
        entries = [p for r in rows if r['half'] == name for p in r.get('pivots') or []]
        for fixed in (True, False):
            chosen = [p for p in entries if p[0] == fixed]
            share = (lambda k: f'{np.mean([p[k] for p in chosen]):.2f}') if chosen else (lambda k: '-')
            lines.append(f'| {name} | {"fixed" if fixed else "not fixed"} | {len(chosen)} | {share(1)} | {share(2)} |')
    return '\n'.join(lines)


def _fmt(value, digits=2, scale=1.0) -> str:
    if value is None or (isinstance(value, float) and math.isnan(value)):
        return '-'
    if isinstance(value, (int, np.integer)):
        return str(int(value))
    return f'{value * scale:.{digits}f}'


def segmentation_table(rows: list) -> str:
    lines = ['| subject | scene | frames with the subject found / in view | subject kept: min / median (%) | '
             'background in the kept, worst frame (%) | ms per frame: median / p95 |', '|' + '---|' * 6]
    for r in rows:
        if 'seg_ms_median' not in r:
            continue
        lines.append(f'| {r["subject"]} | {r["scene"]} | {r["seg_frames_found"]} / {r["seg_frames_with_subject"]} | '
                     f'{_fmt(r["seg_kept_min"], 1, 100)} / {_fmt(r["seg_kept_median"], 1, 100)} | '
                     f'{_fmt(r["seg_background_max"], 2, 100)} | {_fmt(r["seg_ms_median"], 1)} / {_fmt(r["seg_ms_p95"], 1)} |')
    return '\n'.join(lines)


def table(rows: list) -> str:
    lines = ['| subject | scene | half | bending / moving / true joints | found | artic. recall 15 / 10 / 5 cm | '
             'precision: any / bending joint | moving recall | tracking skill | frame coverage | '
             'joint mean / offset removed (cm) | '
             'reg mean / p95 / worst frame (cm) | worst part: mean / worst frame (cm) | reg ms/frame | '
             'step 2 + 3 (s) | total (s) |',
             '|' + '---|' * 16]
    for r in rows:
        parts = r.get('per_part') or {}
        worst = max(parts.items(), key=lambda kv: kv[1].get('mean_error_m', 0.0), default=None)
        worst_text = (f'{worst[0]}: {_fmt(worst[1].get("mean_error_m"), 1, 100)} / '
                      f'{_fmt(worst[1].get("worst_frame_error_m"), 1, 100)}') if worst else '-'
        found = _fmt(r.get('n_predicted')) if not r.get('error') else f'fails: {r["error"][:60]}'
        steps = (r.get('structure_s') or 0.0) + (r.get('joints_s') or 0.0) if 'structure_s' in r else None
        lines.append(
            f'| {r["subject"]} | {r["scene"]} | {r["half"]} | {_fmt(r.get("n_articulated"))} / '
            f'{_fmt(r.get("n_moving"))} / {r["true_joints"]} | {found} | {_fmt(r.get("articulated_recall"))} / '
            f'{_fmt(r.get("articulated_recall_10cm"))} / {_fmt(r.get("articulated_recall_5cm"))} | '
            f'{_fmt(r.get("precision"))} / {_fmt(r.get("articulated_precision"))} | '
            f'{_fmt(r.get("moving_recall"))} | {_fmt(r.get("tracking_skill"))} | '
            f'{_fmt(r.get("frame_coverage"))} | '
            f'{_fmt(r.get("mean_error_m"), 1, 100)} / {_fmt(r.get("normalized_error_m"), 1, 100)} | '
            f'{_fmt(r.get("reg_mean_m"), 1, 100)} / {_fmt(r.get("reg_p95_m"), 1, 100)} / '
            f'{_fmt(r.get("reg_worst_frame_m"), 1, 100)} | {worst_text} | '
            f'{_fmt(r.get("registration_ms_per_frame"), 0)} | {_fmt(steps, 1)} | {_fmt(r.get("total_s"), 1)} |')
    return '\n'.join(lines)


SUMMARY_KEYS = (('articulated_recall', 'artic. recall', 1.0), ('articulated_recall_5cm', 'within 5 cm', 1.0),
                ('precision', 'precision', 1.0), ('articulated_precision', 'bending precision', 1.0),
                ('mean_error_m', 'joint mean (cm)', 100.0),
                ('normalized_error_m', 'offset removed (cm)', 100.0), ('moving_recall', 'moving recall', 1.0),
                ('tracking_skill', 'tracking skill', 1.0), ('frame_coverage', 'frame coverage', 1.0),
                ('reg_mean_m', 'reg mean (cm)', 100.0), ('confidence_auc', 'confidence rank', 1.0))


def summary_table(rows: list) -> str:
    """The median of each headline figure over the rows with joints, per half."""
    scored = [r for r in rows if r['true_joints']]
    lines = ['| half | rows | ' + ' | '.join(label for _, label, _ in SUMMARY_KEYS) + ' |',
             '|' + '---|' * (2 + len(SUMMARY_KEYS))]
    for name in ('tuning', 'check'):
        chosen = [r for r in scored if r['half'] == name]
        medians = [float(np.nanmedian([_num(r.get(key)) for r in chosen])) if chosen else float('nan')
                   for key, _, _ in SUMMARY_KEYS]
        lines.append(f'| {name} | {len(chosen)} | ' + ' | '.join(
            _fmt(value, 1 if scale == 100.0 else 2, scale) for value, (_, _, scale) in zip(medians, SUMMARY_KEYS)) + ' |')
    return '\n'.join(lines)


def _miss_kind(row: dict, entry: dict) -> str:
    """Why a true joint (a per_joint entry of `row`) was not found: 'structure' when the
    skeleton has no joint of its own there (its nearest answers another true joint, or none
    lies within twice the match threshold), 'placement' when its nearest joint is its own
    but placed beyond the threshold."""
    nearest = entry.get('nearest_m')
    if entry.get('nearest_answers') or nearest is None or nearest > 2.0 * _num(row.get('threshold_m')):
        return 'structure'
    return 'placement'


def flipping_joints(chosen: list) -> tuple:
    """Over the variants of one subject and scene: (structure, placement) counts of the
    bending joints found in some variants and not in others, a joint counting as placement
    when every variant that missed it has a joint of its own near it (`_miss_kind`)."""
    entries = {}
    for row in chosen:
        for entry in row.get('per_joint', []):
            if entry['articulated']:
                entries.setdefault(entry['ground_truth'], []).append((row, entry))
    structure = placement = 0
    for seen in entries.values():
        found = [entry['found'] for _, entry in seen]
        if all(found) or not any(found):
            continue
        kinds = {_miss_kind(row, entry) for row, entry in seen if not entry['found']}
        structure += kinds != {'placement'}
        placement += kinds == {'placement'}
    return structure, placement


def stability_table(rows: list) -> str:
    """Per subject and scene, over its seeds and input forms: the range of the headline
    figures (the skeleton should not flip with the noise or the input's form), and the
    bending joints found in only some of them, by why they were missed (`flipping_joints`)."""
    groups = {}
    for r in rows:
        if r['true_joints']:
            groups.setdefault((r['subject'], r['base_scene']), []).append(r)
    lines = ['| subject | scene | variants | artic. recall min-max | precision min-max | tracking skill min-max | '
             'bending joints found in some variants only: structure / placement |',
             '|' + '---|' * 7]
    for (subject, scene), chosen in groups.items():
        def span(key):
            values = np.array([_num(r.get(key)) for r in chosen])
            values = values[np.isfinite(values)]
            return f'{_fmt(float(values.min()))}-{_fmt(float(values.max()))}' if len(values) else '-'
        structure, placement = flipping_joints(chosen)
        lines.append(f'| {subject} | {scene} | {len(chosen)} | {span("articulated_recall")} | '
                     f'{span("precision")} | {span("tracking_skill")} | {structure} / {placement} |')
    return '\n'.join(lines)


def _variant(row: dict) -> str:
    """The seed and input form of a row ('' for seed 0 from clouds): its scene's suffix."""
    base = row.get('base_scene') or row['scene'].split('-', 1)[0]
    return row['scene'][len(base):].lstrip('-')


def comparison_table(rows: list, baseline: list) -> str:
    """Per half and variant (seed, input form), over the rows both runs scored: the mean of
    each headline figure in the baseline -> in these rows, and on how many of those rows it
    rose and fell. A real change shows on both halves and on most rows; the registration's
    chaos moves single rows both ways (bench/README.md, "Comparing two runs")."""
    before = {(r['subject'], r['scene']): r for r in baseline if r['true_joints']}
    pairs = [(before[(r['subject'], r['scene'])], r) for r in rows
             if r['true_joints'] and (r['subject'], r['scene']) in before]
    keys = [k for k in SUMMARY_KEYS if k[0] != 'frame_coverage']
    lines = ['| half | variant | rows | ' + ' | '.join(label for _, label, _ in keys) + ' |',
             '|' + '---|' * (3 + len(keys))]
    groups = {}
    for old, new in pairs:
        groups.setdefault((new['half'], _variant(new)), []).append((old, new))
    for (name, variant), chosen in sorted(groups.items(), key=lambda kv: (kv[0][0] != 'tuning', kv[0][1])):
        cells = []
        for key, _, scale in keys:
            old = np.array([_num(o.get(key)) for o, _ in chosen])
            new = np.array([_num(n.get(key)) for _, n in chosen])
            both = np.isfinite(old) & np.isfinite(new)
            digits = 1 if scale == 100.0 else 2
            old_mean = float(np.mean(old[both])) if both.any() else float('nan')
            new_mean = float(np.mean(new[both])) if both.any() else float('nan')
            cells.append(f'{_fmt(old_mean, digits, scale)} -> {_fmt(new_mean, digits, scale)} '
                         f'({int(np.sum(new[both] > old[both]))} up, {int(np.sum(new[both] < old[both]))} down)')
        lines.append(f'| {name} | {variant or "seed0"} | {len(chosen)} | ' + ' | '.join(cells) + ' |')
    return '\n'.join(lines)


def per_joint_table(rows: list) -> str:
    """Each anatomical joint over the rows where it bends or travels: how often it is
    found (at 15, 10, 5 cm), and where its error lies: the mean offset along the camera ray
    (+ = behind the true joint) and across it, along the limb (+ = towards its far end:
    past the bend for a joint that starts a bone, past the end for one that ends it), and
    the error left once the offset is removed."""
    joints = {}
    for r in rows:
        for entry in r.get('per_joint') or []:
            if entry['articulated'] or entry['moving']:
                joints.setdefault((r['subject'] == 'cow', entry['ground_truth']), []).append(entry)
    lines = ['| joint | rows it bends or moves in | found | within 10 / 5 cm | tracked (moving) | '
             'error (cm) | along the ray (cm) | across (cm) | along the limb (cm) | offset removed (cm) |',
             '|' + '---|' * 10]
    for (_, name), entries in sorted(joints.items()):
        found = [e for e in entries if e['found']]
        moving = [e for e in entries if e['moving']]

        def mean(key, chosen=found):
            values = [e[key] for e in chosen if e.get(key) is not None]
            return float(np.mean(values)) if values else float('nan')
        lines.append(
            f'| {name} | {len(entries)} | {len(found)} | {sum(e["found_10cm"] for e in entries)} / '
            f'{sum(e["found_5cm"] for e in entries)} | {sum(e["tracks"] for e in moving)} of {len(moving)} | '
            f'{_fmt(mean("error_m"), 1, 100)} | {_fmt(mean("offset_along_ray_m"), 1, 100)} | '
            f'{_fmt(mean("offset_across_ray_m"), 1, 100)} | {_fmt(mean("offset_along_limb_m"), 1, 100)} | '
            f'{_fmt(mean("normalized_error_m"), 1, 100)} |')
    return '\n'.join(lines)


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument('--frames', type=int, default=90)
    parser.add_argument('--scenes', default='empty,room')
    parser.add_argument('--only', default='', help='comma-separated name fragments (e.g. wave,cow)')
    parser.add_argument('--work', default=None, help='keep bags and outputs here')
    parser.add_argument('--score-only', action='store_true', help='score the outputs already in --work')
    parser.add_argument('--relearn', action='store_true',
                        help='Steps 2 and 3 alone with --params, on each bag\'s registration kept in '
                             'WORK/registrations (made with the defaults the first time): a Step 2-3 variant in '
                             'minutes; empty that directory after changing Steps 0-1')
    parser.add_argument('--json', default=None, help='write the rows as JSON')
    parser.add_argument('--seeds', default='0', help='comma-separated simulation noise seeds (stability)')
    parser.add_argument('--forms', default='cloud', help='input forms: cloud, depth (16UC1 depth images)')
    parser.add_argument('--params', default=None, help='a parameter file for skel-extract run (a variant to '
                                                       'compare with the defaults)')
    parser.add_argument('--baseline', default=None, help="another run's --json rows: print the change of each "
                                                         'half\'s means from them (and on how many rows)')
    args = parser.parse_args()
    chosen = subjects([o for o in args.only.split(',') if o])
    if not chosen:
        print(f'no real-motion data under {DATA}; nothing to benchmark')
        return 0
    work = Path(args.work) if args.work else Path(tempfile.mkdtemp(prefix='bench_real_'))
    work.mkdir(parents=True, exist_ok=True)
    rows = []
    for name, source_args in chosen:
        for scene in args.scenes.split(','):
            for seed, form in itertools.product(args.seeds.split(','), args.forms.split(',')):
                # the default variant keeps the scene's name (and its bag) as before
                variant = scene + ('' if seed == '0' else f'-seed{seed}') + ('' if form == 'cloud' else '-depth')
                extra = (['--seed', seed] if seed != '0' else []) + (['--depth-image'] if form == 'depth' else [])
                if not args.score_only:
                    started = time.perf_counter()
                    run = relearn if args.relearn else simulate_and_run
                    record = run(name, source_args + extra, scene, args.frames, work, variant, args.params)
                    print(f'{name} {variant}: run exit {record["returncode"]} in '
                          f'{time.perf_counter() - started:.0f} s {record["error"]}', file=sys.stderr, flush=True)
                try:
                    rows.append(dict(score(name, variant, work), base_scene=scene))
                except (EvaluationError, FileNotFoundError) as error:
                    print(f'{name} {variant}: cannot score: {error}', file=sys.stderr)
    print(table(rows))
    print()
    print(summary_table(rows))
    print()
    print(per_joint_table(rows))
    print()
    print(pivot_table(rows))
    print()
    if len(rows) > len({(r['subject'], r['base_scene']) for r in rows}):
        print(stability_table(rows))
        print()
    print(segmentation_table(rows))
    if args.baseline:
        print()
        print(comparison_table(rows, json.loads(Path(args.baseline).read_text())))
    if args.json:
        Path(args.json).write_text(json.dumps(rows, indent=1, default=float))
    return 0


if __name__ == '__main__':
    sys.exit(main())
