"""params/skel_extract.yaml is loadable, strict, and equal to the code defaults."""
import dataclasses

import pytest

from skel_extract_ros.core.joints import JointParams
from skel_extract_ros.core.preprocess import PreprocessParams
from skel_extract_ros.core.registration import RegistrationParams
from skel_extract_ros.core.rest_pose import RestPoseParams
from skel_extract_ros.core.structure import StructureParams
from skel_extract_ros.params import (DEFAULT_PARAMS_FILE, ParamsError, load_params_file,
                                     pipeline_params, registration_params_from_dict)


def test_yaml_defaults_equal_dataclass_defaults():
    nodes = load_params_file(DEFAULT_PARAMS_FILE)
    registration, rest, preprocess = registration_params_from_dict(nodes['registration_node'])
    assert registration == RegistrationParams()
    assert rest == RestPoseParams()
    assert preprocess == PreprocessParams()
    # every dataclass field is documented in the file
    settings = pipeline_params(nodes)
    assert settings['structure'] == StructureParams() and settings['joints'] == JointParams()
    for cls, section in ((StructureParams, nodes['accumulator_node']),
                         (JointParams, nodes['joint_estimation_node']),
                         (RegistrationParams, nodes['registration_node']),
                         (RestPoseParams, nodes['registration_node']['rest_pose']),
                         (PreprocessParams, nodes['registration_node']['preprocess'])):
        assert {f.name for f in dataclasses.fields(cls)} <= set(section)


def test_unknown_or_invalid_parameters_are_rejected(tmp_path):
    with pytest.raises(ParamsError, match='unknown parameter.*betta_smooth'):
        registration_params_from_dict({'betta_smooth': 1.0})
    with pytest.raises(ParamsError, match='omega'):
        registration_params_from_dict({'omega': 2.0})
    bad = tmp_path / 'bad.yaml'
    bad.write_text('registration_node: {omega: 0.1}\n')
    with pytest.raises(ParamsError, match='ros__parameters'):
        load_params_file(bad)
    with pytest.raises(ParamsError, match='does not exist'):
        load_params_file(tmp_path / 'missing.yaml')
