"""The scores of `evaluate_outputs` as text, for `skel-extract evaluate`, `run` and `replay`."""
from __future__ import annotations

import numpy as np


def _cm(value) -> str:
    return '-' if value is None or not np.isfinite(value) else f'{100 * value:.1f}'


def _ratio(value) -> str:
    return '-' if value is None or not np.isfinite(value) else f'{value:.2f}'


def score_lines(result: dict, per_joint: bool) -> list:
    """The scores of `evaluate_outputs` as text lines, the headline figures first."""
    lines = []
    if 'joints' in result:
        j = result['joints']
        lines.append(f'joints: {j["n_predicted"]} predicted, {j["n_matched"]} of {j["n_ground_truth"]} true matched '
                     f'(recall {j["recall"]:.2f}, precision {j["precision"]:.2f}, '
                     f'threshold {_cm(j["threshold_m"])} cm); '
                     f'frames {j["n_frames"]} scored from frame {j["n_frames_before_start"]}, coverage '
                     f'{100 * j["frame_coverage"]:.0f} %' + (f', {j["n_repeated_frames"]} repeated stamps'
                                                             if j['n_repeated_frames'] else ''))
        lines.append(f'  bending joints ({j["n_articulated"]}, >= 25 deg): recall {_ratio(j["articulated_recall"])} '
                     f'(within 10 cm {_ratio(j["articulated_recall_10cm"])}, '
                     f'5 cm {_ratio(j["articulated_recall_5cm"])}), '
                     f'precision {_ratio(j.get("articulated_precision"))}; '
                     f'moving joints ({j["n_moving"]}, >= 10 cm): recall {_ratio(j["moving_recall"])}, '
                     f'tracking skill {_ratio(j["tracking_skill"])} (0 = holding each still)')
        lines.append(f'  error {_cm(j["mean_error_m"])} cm, offset removed {_cm(j["normalized_error_m"])} cm; '
                     f'motion skill {_ratio(j["motion_skill"])}; non-finite {100 * j["nonfinite_fraction"]:.1f} %')
        if j.get('n_confident_answers', 0) or j.get('n_far_answers', 0):
            lines.append(f'  confidence: ranks the answers within the threshold above the '
                         f'{j["n_far_answers"]} beyond it with probability {_ratio(j["confidence_auc"])} '
                         f'(0.5 = no information)')
        if j['missed_articulated']:
            lines.append(f'  bending joints not found: {", ".join(j["missed_articulated"])}')
        if j['missed_moving']:
            lines.append(f'  moving joints not tracked: {", ".join(j["missed_moving"])}')
        if per_joint:
            lines.append('  true joint      <- predicted   error / offset removed / along ray / across / '
                         'along limb (cm)')
            for row in j['per_joint']:
                kind = ' bends' if row['articulated'] else ''
                kind += f' moves {_cm(row["travel_m"])} cm' if row['moving'] else ''
                if not row['found']:
                    nearest = ''
                    if row.get('nearest_predicted') is not None:
                        nearest = (f' (nearest {row["nearest_predicted"]} at {_cm(row["nearest_m"])} cm'
                                   + (f', matched to {row["nearest_answers"]}' if row['nearest_answers'] else '')
                                   + ')')
                    lines.append(f'  {row["ground_truth"]:>14s} <- not found{nearest}{kind}')
                    continue
                lines.append(f'  {row["ground_truth"]:>14s} <- {row["predicted"]:<10s} {_cm(row["error_m"])} / '
                             f'{_cm(row["normalized_error_m"])} / {_cm(row["offset_along_ray_m"])} / '
                             f'{_cm(row["offset_across_ray_m"])} / {_cm(row["offset_along_limb_m"])}{kind}')
    if 'registration' in result:
        r = result['registration']
        drift = '  '.join(f'@{k} {v:.4f}' for k, v in r['drift_m'].items())
        lines.append(f'registration: mean_error_m {r["mean_error_m"]:.4f}  p95_error_m {r["p95_error_m"]:.4f}  '
                     f'worst frame {r["worst_frame_error_m"]:.4f} (p95 {r["worst_frame_p95_m"]:.4f})  '
                     f'drift {drift or "-"}  coverage {r["coverage"]:.2f}  non-finite '
                     f'{100 * r["nonfinite_fraction"]:.1f} %  ({r["n_points"]} points, {r["n_frames"]} frames'
                     + (f', scored from frame {r["n_frames_before_start"]}' if r['n_frames_before_start'] else '')
                     + (f', tied to the surface at frame {r["tied_at_frame"]}'
                        if r.get('tied_at_frame', r['n_frames_before_start']) != r['n_frames_before_start'] else '')
                     + ')')
        parts = sorted(r['per_part'].items(), key=lambda kv: -kv[1]['mean_error_m'])
        if parts:
            lines.append('  worst parts: ' + ', '.join(f'{name} {v["mean_error_m"]:.3f} (worst frame '
                                                       f'{v["worst_frame_error_m"]:.3f})' for name, v in parts[:4]))
    return lines
