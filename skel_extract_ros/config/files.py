"""The package's files (params/skel_extract.yaml, the Fast DDS profile) and reading a ROS 2
parameter file.

The same file configures the nodes (`<node_name>: ros__parameters:`) and `skel-extract
run --params`. Nested mappings are the ROS dotted parameter names (`preprocess.target_points`).
Unknown names are errors (config.values), so a typo never silently falls back to a default.
"""
from __future__ import annotations

from pathlib import Path

import yaml

# In a source checkout; the same file is installed to share/skel_extract_ros/params/.
# Its values equal the dataclass defaults (a test keeps them in sync), so code that gets no
# file uses the defaults directly.
DEFAULT_PARAMS_FILE = Path(__file__).resolve().parents[2] / 'params' / 'skel_extract.yaml'


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
