"""One description (with unit) and valid range for every node parameter.

The nodes put these in their ParameterDescriptors (`ros2 param describe`), and a test
checks that params/skel_extract.yaml and the README's ROS API section list exactly these
names, so the three never drift apart. Ranges are (low, high) or (None, None).
"""
from __future__ import annotations

INF = 1e300
_ANY = (None, None)

_REGISTRATION = {
    'omega': ('weight of the uniform outlier component of the GMM (Eq. 1, 3), in [0, 1)', (0.0, 0.999)),
    'smoothness': ('deformation graph smoothness: robust (default; weight relative to sigma2, Geman-McClure '
                   'loss per edge, so a limb can leave the body it touched in the first frame) or paper '
                   '(Eq. 4 as written, fixed beta_smooth)', _ANY),
    'beta_smooth': ('weight of E_smooth with smoothness: paper (Eq. 4, Table 1), 1/m^2', (0.0, INF)),
    'beta_smooth_relative': ('with smoothness: robust, E_smooth is weighted this / sigma2 (the units of '
                             'the data term)', (0.0, INF)),
    'edge_strain_scale': ('with smoothness: robust, an edge residual this fraction of the edge length '
                          '(about the relative rotation of its nodes, rad) weighs a quarter', (1e-6, 100.0)),
    'visibility': ('model points hidden behind the observed surface take no observations in that frame '
                   '(measured: mixed on real motion, off by default)', _ANY),
    'recapture': ('after EM, move a part left without data rigidly onto the observations nothing explains '
                  'and re-run EM (fast limbs)', _ANY),
    'beta_small': ('weight of E_small, the small-motion term between frames (Eq. 4)', (0.0, INF)),
    'initial_sigma2': ('GMM variance at the start of every frame, m^2 (Sec. 7)', (1e-12, INF)),
    'max_iterations': ('EM iterations per frame at most (Alg. 1)', (1, 1000)),
    'tolerance': ('stop EM when the relative energy change is below this', (0.0, 1.0)),
    'm_step': ('M-step scheme: translations_rotations (default, converges with stiff beta_smooth) '
               'or per_node (the paper node-by-node scheme)', _ANY),
    'node_spacing': ('deformation graph node spacing, m; 0 = automatic', (0.0, INF)),
    'node_spacing_factor': ('automatic node spacing = this x the median rest point spacing', (1.0, 100.0)),
    'n_influence': ('deformation graph nodes blending each point (Eq. 2)', (1, 16)),
    'e_step_neighbours': ('truncated E-step: nearest centroids per observed point', (1, 64)),
    'truncation_sigmas': ('truncated E-step: neighbour radius in GMM standard deviations', (1.0, 100.0)),
    'min_sigma2': ('lower bound of the GMM variance, m^2', (0.0, INF)),
    'max_sigma2': ('a frame whose variance ends above this counts as diverged, m^2', (0.0, INF)),
    'min_matched_fraction': ('a frame explaining less than this share of its points diverged', (0.0, 1.0)),
    'min_points': ('a preprocessed frame with fewer points is skipped as empty', (1, 10_000_000)),
    'rest_pose.n_points': ('M, rest points = registered points per frame', (100, 1_000_000)),
    'rest_pose.poisson_depth': ('octree depth of the Poisson reconstruction of the rest pose', (4, 12)),
    'rest_pose.density_quantile': ('Poisson vertices below this density quantile are trimmed', (0.0, 1.0)),
    'rest_pose.max_distance_factor': ('surface farther than this x point spacing from the data is trimmed',
                                      (0.0, INF)),
    'rest_pose.normal_neighbours': ('neighbours for normal estimation', (3, 200)),
    'rest_pose.camera_location': ('[x, y, z] m, normals are oriented towards it (the cloud frame origin)', _ANY),
    'rest_pose.poisson_threads': ('threads of the Poisson solver; 1 = repeatable, -1 = all cores', (-1, 256)),
    'preprocess.crop_min': ('[x, y, z] m lower corner of a crop box in the cloud frame; [] = no crop', _ANY),
    'preprocess.crop_max': ('[x, y, z] m upper corner of the crop box; [] = no crop', _ANY),
    'preprocess.target_points': ('voxel downsampling aims at this many points per frame', (100, 10_000_000)),
    'preprocess.initial_voxel_size': ('first voxel size tried, m (adapted per frame)', (1e-4, 1.0)),
    'preprocess.max_input_points': ('larger clouds are randomly thinned to this many points first',
                                    (1000, 100_000_000)),
    'preprocess.remove_plane': ('remove the dominant plane (floor, table)', _ANY),
    'preprocess.plane_distance': ('plane inlier distance, m', (1e-4, 1.0)),
    'preprocess.plane_min_fraction': ('only a plane holding this share of the points is removed', (0.0, 1.0)),
    'preprocess.keep_largest_cluster': ('keep only the largest Euclidean cluster (the subject)', _ANY),
    'preprocess.cluster_eps': ('cluster neighbour distance, m', (1e-4, 10.0)),
    'preprocess.cluster_min_points': ('smallest cluster, points', (1, 1_000_000)),
    'preprocess.outlier_neighbours': ('statistical outlier removal neighbours; 0 = off', (0, 200)),
    'preprocess.outlier_std_ratio': ('statistical outlier removal threshold, standard deviations', (0.1, 100.0)),
    'preprocess.seed': ('seed of the random thinning', (0, 2**31 - 1)),
    'segmentation.enabled': ('find the subject (the connected region that moves) and drop the room; '
                             'false = every valid point is the subject', _ANY),
    'segmentation.noise_sigmas': ('a depth change or a distance to a plane counts beyond this many measured '
                                  'noise deviations', (0.5, 100.0)),
    'segmentation.min_noise_c': ('floor of the measured depth noise coefficient c in sigma = c r^2, 1/m',
                                 (1e-6, 1.0)),
    'segmentation.motion_lag': ('frames between the depth images compared for motion', (1, 1000)),
    'segmentation.motion_memory': ('frames over which motion evidence fades', (1, 100_000)),
    'segmentation.max_planes': ('planes (floor, walls, table tops) removed at most', (0, 20)),
    'segmentation.min_plane_extent': ('m; smaller planes are kept (they may be the subject)', (0.01, 100.0)),
    'segmentation.plane_refresh': ('frames between plane fits', (1, 100_000)),
    'segmentation.attach_distance': ('m; a region this close to the subject in 3-D is part of it', (0.0, 10.0)),
    'segmentation.min_subject_points': ('a smaller subject is nobody, pixels of the working grid', (1, 10_000_000)),
    'segmentation.max_pixels': ('the working grid: motion, planes and regions are found on every k-th row '
                                'and column of larger images (640x480 at 320x240), the subject kept at full '
                                'resolution; lower it on a slow machine (fewer frames find a small subject)',
                                (1000, 100_000_000)),
    'segmentation.seed': ('RANSAC seed (repeatable plane fits)', (0, 2**31 - 1)),
    'input': ('what the camera driver publishes: cloud (PointCloud2 on points) or depth_image '
              '(Image on depth/image, 16UC1 mm or 32FC1 m, with CameraInfo on depth/camera_info)', _ANY),
    'input_reliability': ('QoS of the points subscription: best_effort (sensor data, matches every driver) '
                          'or reliable (lossless bag replay; needs a reliable publisher)', _ANY),
    'queue_size': ('subject clouds waiting for the registration at most once the first window is '
                   'learned; older ones are skipped (and counted) when registration falls behind the camera '
                   '(filtered_points still comes for every cloud)', (1, 100_000)),
    'learning_queue_size': ('subject clouds waiting for the registration at most while the first window '
                            'is learned (from the rest pose to the first skeleton/structure), registered in '
                            'order: the window is then consecutive camera frames, as skel-extract run\'s, '
                            'and close frames register 2-3 times faster than frames a second apart; when '
                            'full, new clouds are skipped (counted), before their segmentation until the '
                            'first skeleton is described. Set it to at least the accumulator\'s '
                            'window_size', (1, 100_000)),
    'registration_niceness': ('added to the nice value of the child process that runs Alg. 1 once the '
                              'first window is learned (skeleton/structure): when the cores are short, the '
                              'joint node\'s Alg. 2 and then the live path (segmentation, filtered_points, the '
                              'joint fit) go first and growing the skeleton waits; while learning the first '
                              'window it runs at the node\'s priority; 0 = never lowered (nor with lossless)',
                              (0, 19)),
    'registration_sched_idle': ('when the priority of the child running Alg. 1 is lowered '
                                '(registration_niceness), it also enters Linux\'s idle scheduling class '
                                '(SCHED_IDLE): it gets a core only when no other task wants it, so the live '
                                'path never waits for the scheduler to preempt it (at 30 Hz on 2 cores: '
                                'latency p95 68-73 -> 47-56 ms on the cow) and growing the skeleton uses the '
                                'idle CPU; false = the nice value only', _ANY),
    'lossless': ('never skip a cloud: when registration falls behind, segmentation waits for it and '
                 'so does the input (bag replay with input_reliability reliable; replay sets it)', _ANY),
    'live_start': ('once a skeleton is tracked, register each frame starting from the joint node\'s '
                   'newest posed model (skeleton/posed_points: the live fit of a frame since the last '
                   'registered one) instead of from that last registered frame, up to seconds old; '
                   'false = always from the last registered frame (Alg. 1 as in skel-extract run). Not '
                   'with lossless', _ANY),
}

_ACCUMULATOR = {
    'window_size': ('frames collected before the skeletal structure is extracted', (2, 100_000)),
    'sliding': ('keep growing the skeleton: every `stride` frames the last window_size frames compete for the key '
                'frames and the structure is learned again', _ANY),
    'stride': ('frames between extractions when sliding', (1, 100_000)),
    'n_clusters': ('initial K-means clusters (deliberately more than the bones)', (2, 10_000)),
    'cluster_on': ('K-means features: trajectories (whole registered paths) or rest (positions)', _ANY),
    'n_rounds': ('rounds of rigid fit / relabel / local continuity (paper: 10)', (0, 1000)),
    'neighbour_radius': ('ball radius for local continuity and bone adjacency, m; 0 = automatic', (0.0, INF)),
    'neighbour_radius_factor': ('automatic radius = this x the median rest point spacing', (0.1, 100.0)),
    'min_bone_fraction': ('bones with fewer than this share of the points are dropped', (0.0, 1.0)),
    'motion_noise_factor': ('evidence a joint needs: its relative rotation over the window over the rotation the '
                            'registration noise alone makes (swap displacement / rigid-fit noise); below it the '
                            'bone is merged into its parent', (0.0, INF)),
    'leaf_min_fraction': ('paper rule 1: leaf bones at branching joints below this share of points are dropped',
                          (0.0, 1.0)),
    'joint_merge_fraction': ('paper rule 3: joints closer than this x the subject size are merged', (0.0, 1.0)),
    'eta': ('weight of the joint data term, Step 2 joint solve (Table 1)', (0.0, INF)),
    'max_key_frames': ('the growing skeleton is learned from at most this many frames, the most different poses '
                       'seen so far', (2, 100_000)),
    'joint_match_fraction': ('joints of two updates closer than this x the subject size are the same joint '
                             '(keep id and name)', (0.0, 1.0)),
    'anchor_depth': ('joint anchors c~: medial (moved back along the camera ray to the bone\'s '
                     'cross-section centre) or surface (the paper\'s boundary centroid)', _ANY),
    'camera_location': ('[x, y, z] m, the sensor origin in the cloud frame (camera rays for medial anchors)',
                        _ANY),
    'seed': ('K-means seed', (0, 2**31 - 1)),
}

_JOINTS = {
    'omega': ("outlier weight omega' of the GMM (Eq. 11)", (0.0, 0.999)),
    'eta': ('weight of the joint data term in E_Joint (Table 1)', (0.0, INF)),
    'zeta': ('weight of E_Register, the pull to the registered points (Table 1)', (0.0, INF)),
    'gamma': ('weight of E_small (Table 1)', (0.0, INF)),
    'alpha_growth': ('alpha = zeta * M * alpha_growth^iteration (E_Joint weight)', (1.0, 100.0)),
    'initial_tau': ('initial per-frame GMM variance tau, m^2', (1e-12, INF)),
    'max_iterations': ('Alg. 2 EM iterations at most (10: as good as 20 on the real-motion benchmark, at half the time)', (1, 1000)),
    'tolerance': ('stop Alg. 2 when the relative energy change is below this', (0.0, 1.0)),
    'max_influences': ('bones per point in the LBS weights (Eq. 12b)', (1, 4)),
    'e_step_neighbours': ('truncated E-step: nearest centroids per observed point', (1, 64)),
    'truncation_sigmas': ('truncated E-step: neighbour radius in standard deviations', (1.0, 100.0)),
    'min_tau': ('lower bound of tau, m^2', (0.0, INF)),
    'buffer_size': ('registered + filtered frames kept to find a structure window in', (2, 100_000)),
    'live_frames': ('which frames get live joints: camera (every filtered_points frame, the learned skeleton '
                    'fitted to its subject points, started from the newest registered frame; never waits for '
                    'registration) or registered (registered frames only, as skel-extract run; lossless replay)',
                    _ANY),
    'live_iterations': ('EM iterations of the live fit to a camera frame (each: the whole-body move, then the '
                        'bone-by-bone update with the joint weight growing to Alg. 2\'s at the last)', (1, 100)),
    'live_sweeps': ('live per-frame fit: bone-by-bone passes after the rigid initialisation', (0, 100)),
    'provisional_skeleton': ('with live_frames camera: track Step 2\'s skeleton (each point on its bone) as soon '
                             'as a structure arrives, described with provisional true, while Alg. 2 runs; Alg. 2\'s '
                             'model then replaces it under the same joint names. false: the first joints wait '
                             'for Alg. 2 (seconds)', _ANY),
    'estimation_niceness': ('added to the nice value of the thread running Alg. 2 (and of its pool): the live '
                            'fit of every camera frame, in the same process, comes first, and Alg. 2 before the '
                            'registration (registration_niceness, larger); 0 = same priority', (0, 19)),
    'joint_diameter': ('diameter of the joint spheres in skeleton/markers, m', (1e-4, 10.0)),
}

PARAMETER_DOCS = {'registration_node': _REGISTRATION, 'accumulator_node': _ACCUMULATOR,
                  'joint_estimation_node': _JOINTS}

# The parameters a running node takes from `ros2 param set` (its parameter callback applies
# them; LIVE_FROM says from when). Every other parameter is declared read-only, so a set
# fails with that reason: the registration runs Alg. 1 in a child process started with its
# parameters and subscribes to its input once; the accumulator's growing skeleton keeps the
# structure parameters it started with; the joint node's live_frames chooses its
# subscriptions' use and estimation_niceness its thread's priority at start.
LIVE = {'registration_node': frozenset(),
        'accumulator_node': frozenset({'window_size', 'sliding', 'stride'}),
        'joint_estimation_node': frozenset(set(_JOINTS) - {'live_frames', 'estimation_niceness'})}
LIVE_FROM = {'registration_node': '',
             'accumulator_node': 'the next registered frame',
             'joint_estimation_node': 'the next frame (joint_diameter, live_iterations, live_sweeps, buffer_size) '
                                      'or the next skeleton/structure (the method\'s parameters, '
                                      'provisional_skeleton)'}
READ_ONLY_NOTE = ' [read-only: set at start, in the params file or with --ros-args -p]'


def is_live(node: str, name: str) -> bool:
    """Whether a running node applies a new value of the parameter (else it is read-only)."""
    return name in LIVE[node]


def describe(node: str, name: str) -> tuple:
    """(description, low, high) of a node parameter; KeyError for an undocumented one."""
    description, (low, high) = PARAMETER_DOCS[node][name]
    return description, low, high


# -- the README's parameter tables are generated from here ---------------------------------
README_BEGIN = '<!-- parameters:{node} (generated: python -m skel_extract_ros.parameter_docs README.md) -->'
README_END = '<!-- /parameters:{node} -->'


def unset_value(hint):
    """What a node declares for a method parameter whose default is None (unset): 0.0 for
    an optional number ('automatic'), [] for an optional list ('unset'). hint: the field's
    type hint."""
    import typing
    return 0.0 if float in typing.get_args(hint) else []


def parameter_defaults(node: str) -> dict:
    """{name: default as the node declares it} of every parameter of a node, in declaration
    order: the method's dataclass fields (nested sections as `section.name`; an unset
    optional is 0.0 for a number, [] for a list, as in the YAML), then the node's own."""
    import dataclasses
    import typing

    from .core.joints import JointParams
    from .core.preprocess import PreprocessParams
    from .core.registration import RegistrationParams
    from .core.rest_pose import RestPoseParams
    from .core.segmentation import SegmentationParams
    from .core.structure import StructureParams
    from .params import NODE_ONLY
    sections = {'registration_node': [('', RegistrationParams), ('rest_pose.', RestPoseParams),
                                      ('preprocess.', PreprocessParams), ('segmentation.', SegmentationParams)],
                'accumulator_node': [('', StructureParams)],
                'joint_estimation_node': [('', JointParams)]}[node]
    defaults = {}
    for prefix, cls in sections:
        hints = typing.get_type_hints(cls)
        for field in dataclasses.fields(cls):
            default = field.default
            defaults[prefix + field.name] = unset_value(hints[field.name]) if default is None else default
    return {**defaults, **NODE_ONLY[node]}


def _format_default(value) -> str:
    if isinstance(value, bool):
        return str(value).lower()
    if isinstance(value, tuple):
        value = [float(v) for v in value]
    return str(value)


def markdown_table(node: str) -> str:
    """The README table of a node's parameters: name, default, meaning (with unit)."""
    lines = ['| parameter | default | live | meaning (unit) |', '|---|---|---|---|']
    for name, default in parameter_defaults(node).items():
        live = 'yes' if is_live(node, name) else ''
        lines.append(f'| `{name}` | `{_format_default(default)}` | {live} | {PARAMETER_DOCS[node][name][0]} |')
    if LIVE_FROM[node]:
        lines.append(f'\n`live`: `ros2 param set` applies it from {LIVE_FROM[node]}; the others are '
                     'read-only (a set fails with the reason).')
    else:
        lines.append('\nEvery parameter of this node is read-only once it runs (a set fails with the reason).')
    return '\n'.join(lines)


def readme_with_tables(text: str) -> str:
    """`text` with every node's generated block replaced by the current table (ValueError
    if a block's markers are missing)."""
    for node in PARAMETER_DOCS:
        begin, end = README_BEGIN.format(node=node), README_END.format(node=node)
        if begin not in text or end not in text:
            raise ValueError(f'the README has no block {begin} ... {end}')
        head, rest = text.split(begin, 1)
        _, tail = rest.split(end, 1)
        text = f'{head}{begin}\n{markdown_table(node)}\n{end}{tail}'
    return text


def main(argv=None) -> int:
    """python -m skel_extract_ros.parameter_docs README.md: rewrite the tables in place."""
    import sys
    from pathlib import Path
    paths = (argv if argv is not None else sys.argv[1:]) or ['README.md']
    for path in map(Path, paths):
        path.write_text(readme_with_tables(path.read_text()))
    return 0


if __name__ == '__main__':
    raise SystemExit(main())
