"""params/skel_extract.yaml is loadable, strict, and equal to the code defaults."""
import dataclasses

import pytest

from skel_extract_ros.core.joints import JointParams
from skel_extract_ros.core.preprocess import PreprocessParams
from skel_extract_ros.core.registration import RegistrationParams
from skel_extract_ros.core.rest_pose import RestPoseParams
from skel_extract_ros.core.segmentation import SegmentationParams
from skel_extract_ros.core.structure import StructureParams
from skel_extract_ros.params import (DEFAULT_PARAMS_FILE, ParamsError, load_params_file,
                                     pipeline_params, registration_params_from_dict)


def test_yaml_defaults_equal_dataclass_defaults():
    nodes = load_params_file(DEFAULT_PARAMS_FILE)
    registration, rest, preprocess, segmentation = registration_params_from_dict(nodes['registration_node'])
    assert registration == RegistrationParams()
    assert rest == RestPoseParams()
    assert preprocess == PreprocessParams()
    assert segmentation == SegmentationParams()
    # every dataclass field is documented in the file
    settings = pipeline_params(nodes)
    assert settings['structure'] == StructureParams() and settings['joints'] == JointParams()
    for cls, section in ((StructureParams, nodes['accumulator_node']),
                         (JointParams, nodes['joint_estimation_node']),
                         (RegistrationParams, nodes['registration_node']),
                         (RestPoseParams, nodes['registration_node']['rest_pose']),
                         (PreprocessParams, nodes['registration_node']['preprocess']),
                         (SegmentationParams, nodes['registration_node']['segmentation'])):
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


def _flat(values, prefix=''):
    for key, value in values.items():
        if isinstance(value, dict):
            yield from _flat(value, prefix + key + '.')
        else:
            yield prefix + key


def test_every_node_parameter_is_documented_in_the_file_the_code_and_the_readme():
    from skel_extract_ros.parameter_docs import PARAMETER_DOCS
    from skel_extract_ros.params import NODE_ONLY
    nodes = load_params_file(DEFAULT_PARAMS_FILE)
    readme = (DEFAULT_PARAMS_FILE.parent.parent / 'README.md').read_text()
    declared = {
        'registration_node': [f.name for f in dataclasses.fields(RegistrationParams)]
        + ['rest_pose.' + f.name for f in dataclasses.fields(RestPoseParams)]
        + ['preprocess.' + f.name for f in dataclasses.fields(PreprocessParams)]
        + ['segmentation.' + f.name for f in dataclasses.fields(SegmentationParams)],
        'accumulator_node': [f.name for f in dataclasses.fields(StructureParams)],
        'joint_estimation_node': [f.name for f in dataclasses.fields(JointParams)],
    }
    for node, names in declared.items():
        names = set(names) | set(NODE_ONLY[node])
        assert set(PARAMETER_DOCS[node]) == names, node
        assert set(_flat(nodes[node])) == names, node
        for name in names:
            assert f'| `{name}` |' in readme, f'{node}.{name} missing from the README'
        for name, value in NODE_ONLY[node].items():
            section = nodes[node]
            assert section[name] == value, f'{node}.{name}: YAML {section[name]} != code {value}'


def test_readme_parameter_tables_are_generated_from_the_one_source():
    """The README's ROS API tables are exactly what parameter_docs generates from the
    descriptions and the dataclass / node defaults (regenerate with
    `python -m skel_extract_ros.parameter_docs README.md`)."""
    from skel_extract_ros.parameter_docs import markdown_table, readme_with_tables
    readme = (DEFAULT_PARAMS_FILE.parent.parent / 'README.md').read_text()
    assert readme_with_tables(readme) == readme, 'README parameter tables out of date'
    # and a table that lost a parameter or a default would be caught
    table = markdown_table('joint_estimation_node')
    assert '| `max_iterations` | `10` |' in table and '| `buffer_size` | `300` |' in table
    with pytest.raises(ValueError, match='no block'):
        readme_with_tables(readme.replace('<!-- /parameters:accumulator_node -->', ''))
