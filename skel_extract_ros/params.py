"""Loading parameters from params/skel_extract.yaml (ROS 2 parameter file layout).

The same file configures the nodes (`<node_name>: ros__parameters:`) and `skel-extract
run --params`. Nested mappings are the ROS dotted parameter names (`preprocess.target_points`).
Unknown names are errors, so a typo never silently falls back to a default.
"""
from __future__ import annotations

import dataclasses
from pathlib import Path

import yaml

from .core.growth import GrowthSchedule
from .core.joints import JointParams
from .core.preprocess import PreprocessParams
from .core.registration import RegistrationParams
from .core.rest_pose import RestPoseParams
from .core.segmentation import SegmentationParams
from .core.structure import StructureParams

# In a source checkout; the same file is installed to share/skel_extract_ros/params/.
# Its values equal the dataclass defaults (a test keeps them in sync), so code that gets no
# file uses the defaults directly.
DEFAULT_PARAMS_FILE = Path(__file__).resolve().parent.parent / 'params' / 'skel_extract.yaml'


def packaged_file(name: str) -> Path | None:
    """A file of the package's params/ directory: the source checkout's, else the installed
    share/ copy (colcon / ROS installs), else None."""
    source = DEFAULT_PARAMS_FILE.with_name(name)
    if source.is_file():
        return source
    try:
        from ament_index_python.packages import PackageNotFoundError, get_package_share_directory
        installed = Path(get_package_share_directory('skel_extract_ros')) / 'params' / name
        return installed if installed.is_file() else None
    except (ImportError, PackageNotFoundError, ValueError):
        return None


def default_params_file() -> Path | None:
    """The packaged parameter file, or None (the code defaults are the same values)."""
    return packaged_file(DEFAULT_PARAMS_FILE.name)


def fastdds_profile_file() -> Path | None:
    """The packaged Fast DDS profile with a 4 MB shared-memory segment, for a publisher of
    large clouds (README, "Running against a live camera")."""
    return packaged_file('fastdds_large_messages.xml')


class ParamsError(ValueError):
    """A parameter file that cannot be used; the message names the file and the key."""


def _build(cls, values: dict, where: str):
    fields = {f.name: f for f in dataclasses.fields(cls)}
    unknown = sorted(set(values) - set(fields))
    if unknown:
        raise ParamsError(f'{where}: unknown parameter(s) {", ".join(unknown)}; '
                          f'valid: {", ".join(sorted(fields))}')
    converted = {}
    for name, value in values.items():
        default = fields[name].default
        # ROS parameters cannot be None: 0 means "automatic", an empty list "unset".
        if default is None and value in (0, 0.0, [], ''):
            value = None
        elif isinstance(value, list):
            value = tuple(value)
        elif isinstance(default, float) and isinstance(value, int) and not isinstance(value, bool):
            value = float(value)
        converted[name] = value
    try:
        return cls(**converted)
    except (TypeError, ValueError) as error:
        raise ParamsError(f'{where}: {error}') from error


# Parameters of the nodes themselves (windowing, queues, display), not of the method.
# Their defaults live here (the method's live in the core dataclasses).
NODE_ONLY = {'registration_node': {'queue_size': 1, 'learning_queue_size': 60, 'lossless': False,
                                   'input_reliability': 'best_effort', 'input': 'cloud',
                                   'registration_niceness': 10, 'registration_sched_idle': True,
                                   'live_start': True},
             # the growth schedule's (core.growth.GrowthSchedule: `run` follows it too)
             'accumulator_node': {f.name: f.default for f in dataclasses.fields(GrowthSchedule)},
             'joint_estimation_node': {'buffer_size': 300, 'live_frames': 'camera', 'live_iterations': 3,
                                       'live_sweeps': 2, 'provisional_skeleton': True,
                                       'estimation_niceness': 5, 'joint_diameter': 0.04}}


def _method_values(values: dict, node: str) -> dict:
    return {k: v for k, v in values.items() if k not in NODE_ONLY[node]}


def registration_params_from_dict(values: dict, where: str = 'registration_node') -> tuple:
    """(RegistrationParams, RestPoseParams, PreprocessParams, SegmentationParams) from a
    node's parameters."""
    values = _method_values(values, 'registration_node')
    preprocess = values.pop('preprocess', {}) or {}
    rest_pose = values.pop('rest_pose', {}) or {}
    segmentation = values.pop('segmentation', {}) or {}
    return (_build(RegistrationParams, values, where),
            _build(RestPoseParams, rest_pose, f'{where}.rest_pose'),
            _build(PreprocessParams, preprocess, f'{where}.preprocess'),
            _build(SegmentationParams, segmentation, f'{where}.segmentation'))


def structure_params_from_dict(values: dict, where: str = 'accumulator_node') -> StructureParams:
    """StructureParams from the accumulator node's parameters (window keys are the node's)."""
    return _build(StructureParams, _method_values(values, 'accumulator_node'), where)


def schedule_from_dict(values: dict, where: str = 'accumulator_node') -> GrowthSchedule:
    """GrowthSchedule from the accumulator node's parameters (its window keys)."""
    return _build(GrowthSchedule, {k: v for k, v in values.items() if k in NODE_ONLY['accumulator_node']}, where)


def joint_params_from_dict(values: dict, where: str = 'joint_estimation_node') -> JointParams:
    return _build(JointParams, _method_values(values, 'joint_estimation_node'), where)


def pipeline_params(nodes: dict) -> dict:
    """Keyword arguments of SkeletonPipeline from a loaded parameter file."""
    registration, rest_pose, preprocess, segmentation = registration_params_from_dict(
        nodes.get('registration_node', {}))
    return {'registration': registration, 'rest_pose': rest_pose, 'preprocess': preprocess,
            'segmentation': segmentation,
            'structure': structure_params_from_dict(nodes.get('accumulator_node', {})),
            'schedule': schedule_from_dict(nodes.get('accumulator_node', {})),
            'joints': joint_params_from_dict(nodes.get('joint_estimation_node', {}))}


def load_params_file(path) -> dict:
    """{node name: parameter dict} from a ROS 2 parameter YAML file."""
    path = Path(path)
    if not path.is_file():
        raise ParamsError(f'parameter file {path} does not exist')
    try:
        document = yaml.safe_load(path.read_text()) or {}
    except yaml.YAMLError as error:
        raise ParamsError(f'{path} is not valid YAML: {error}') from error
    if not isinstance(document, dict):
        raise ParamsError(f'{path}: expected "<node_name>: ros__parameters: ..." mappings')
    nodes = {}
    for node, content in document.items():
        if not isinstance(content, dict) or 'ros__parameters' not in content:
            raise ParamsError(f'{path}: section {node!r} has no ros__parameters')
        nodes[str(node).lstrip('/')] = content['ros__parameters'] or {}
    return nodes
