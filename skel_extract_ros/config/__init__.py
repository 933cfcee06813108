"""Configuration: the nodes' parameters from the parameter dataclasses (core.parameters),
the package's parameter file and how values go between ROS, YAML and the dataclasses.

- files: DEFAULT_PARAMS_FILE, load_params_file, ParamsError, packaged files;
- nodes: each node's sections (NODES) and the node-only dataclasses;
- values: declarations(node), node_params(node, values), pipeline_params(file);
- docs: the README tables and params/skel_extract.yaml generated from the same metadata.
"""
from .files import (DEFAULT_PARAMS_FILE, ParamsError, default_params_file, fastdds_profile_file,  # noqa: F401
                    load_params_file, packaged_file)
from .nodes import NODE_KEY, NODES, JointNodeParams, RegistrationNodeParams, Section  # noqa: F401
from .values import Declaration, declarations, node_params, parameter_defaults, pipeline_params  # noqa: F401
