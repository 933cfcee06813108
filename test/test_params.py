"""One parameter source: every parameter is a dataclass field carrying its default, range or
choices and description (core.parameters); validation, the nodes' declarations, the YAML
file and the README tables all come from it."""
import dataclasses

import pytest
import yaml

from skel_extract_ros.config import (DEFAULT_PARAMS_FILE, NODES, ParamsError, declarations, load_params_file,
                                     node_params, parameter_defaults, pipeline_params)
from skel_extract_ros.config.docs import markdown_table, params_yaml, readme_with_tables, ros_description
from skel_extract_ros.config.nodes import LIVE_FROM
from skel_extract_ros.config.values import from_ros
from skel_extract_ros.core.parameters import INF, spec

README = DEFAULT_PARAMS_FILE.parent.parent / 'README.md'
SECTIONS = [section for sections in NODES.values() for section in sections]
FIELDS = [(section.cls, field) for section in SECTIONS for field in dataclasses.fields(section.cls)]


def _id(item):
    return f'{item[0].__name__}.{item[1].name}'


@pytest.mark.parametrize('item', FIELDS, ids=_id)
def test_every_field_is_a_parameter_with_description_and_valid_values(item):
    """No field without a description, and none that validation cannot check: a number has
    a range, a string its choices, an [x, y, z] its size (only a switch has none)."""
    cls, field = item
    field_spec = spec(field)
    assert field_spec is not None, f'{_id(item)} is not declared with parameter(...)'
    assert len(field_spec.description) > 10, _id(item)
    assert 'measured' not in field_spec.description, f'{_id(item)}: no measured history in a description'
    default = field.default
    if isinstance(default, bool):
        return
    if isinstance(default, str):
        assert field_spec.choices and default in field_spec.choices, _id(item)
    elif isinstance(default, tuple) or (default is None and not field_spec.ranged):
        assert field_spec.size == 3, _id(item)
    else:
        assert field_spec.ranged, f'{_id(item)} has no range'


def _out_of_range(field_spec, default):
    """Values just outside a field's range (a strict bound itself), from its metadata."""
    low, high = field_spec.bounds()
    values = [low if field_spec.strict_low else low - abs(low) - 1]
    if high < INF:
        values.append(high if field_spec.strict_high else high + abs(high) + 1)
    return [type(default)(v) if isinstance(default, int) else float(v) for v in values]


def _invalid_values(field):
    field_spec = spec(field)
    if field_spec.choices:
        return ['no_such_choice']
    if field_spec.size:
        return [(0.0, 0.0), (0.0, 0.0, 0.0, 0.0)]
    if field_spec.ranged:
        return _out_of_range(field_spec, field.default if field.default is not None else 0.0)
    return []


@pytest.mark.parametrize('item', FIELDS, ids=_id)
def test_validation_refuses_every_value_outside_the_metadata_and_names_the_field(item):
    cls, field = item
    invalid = _invalid_values(field)
    assert invalid or isinstance(field.default, bool), _id(item)
    for value in invalid:
        with pytest.raises(ValueError, match=rf'\b{field.name}\b'):
            cls(**{field.name: value})
    field_spec = spec(field)
    if field_spec.ranged:          # the bounds themselves are valid unless strict
        low, high = field_spec.bounds()
        for bound, strict in ((low, field_spec.strict_low), (high, field_spec.strict_high)):
            if not strict and bound < INF:
                cls(**{field.name: type(field.default)(bound) if field.default is not None else float(bound)})


@pytest.mark.parametrize('node', list(NODES))
def test_a_node_and_a_parameter_file_refuse_out_of_range_values_by_name(node):
    """The same validation through the parameter file / node path: the error names the
    node, the section and the parameter."""
    for d in declarations(node):
        field = next(f for f in dataclasses.fields(d.section.cls) if f.name == d.name.rpartition('.')[2])
        for value in _invalid_values(field)[:1]:
            value = list(value) if isinstance(value, tuple) else value
            with pytest.raises(ParamsError, match=rf'^{node}\b.*\b{field.name} must be'):
                node_params(node, {d.name: value})


def test_node_only_choices_are_validated_like_the_method_parameters():
    with pytest.raises(ParamsError, match="input must be 'cloud' or 'depth_image', got 'rgb'"):
        node_params('registration_node', {'input': 'rgb'})
    with pytest.raises(ParamsError, match='input_reliability'):
        node_params('registration_node', {'input_reliability': 'sometimes'})
    with pytest.raises(ParamsError, match='live_frames'):
        node_params('joint_estimation_node', {'live_frames': 'all'})


def test_yaml_file_is_generated_from_the_dataclasses_and_equals_their_defaults():
    assert DEFAULT_PARAMS_FILE.read_text() == params_yaml(), \
        'params/skel_extract.yaml out of date: python -m skel_extract_ros.config.docs'
    nodes = load_params_file(DEFAULT_PARAMS_FILE)
    assert set(nodes) == set(NODES)
    for node in NODES:
        flat = dict(_flat(nodes[node]))
        assert flat == parameter_defaults(node), node
        for key, value in flat.items():      # same types as the node declares (1.0e-06 is a float)
            assert type(value) is type(parameter_defaults(node)[key]), f'{node}.{key}'
        built = node_params(node, nodes[node])
        assert all(instance == section.cls() for section in NODES[node]
                   for key, instance in built.items() if key == section.key), node
    settings = pipeline_params(nodes)
    assert {key: type(value) for key, value in settings.items()} == {
        s.key: s.cls for s in SECTIONS if s.key != 'node'}


def test_ros_values_round_trip_to_the_dataclass_defaults():
    """None <-> 0.0 / [] and tuple <-> list, in both directions, for every field."""
    for node in NODES:
        for d in declarations(node):
            field = next(f for f in dataclasses.fields(d.section.cls) if f.name == d.name.rpartition('.')[2])
            assert from_ros(field, d.default) == field.default, d.name
            assert field.default is not None or d.default in (0.0, []), d.name


def test_unknown_or_invalid_parameters_are_rejected(tmp_path):
    with pytest.raises(ParamsError, match='unknown parameter.*betta_smooth'):
        node_params('registration_node', {'betta_smooth': 1.0})
    with pytest.raises(ParamsError, match=r'registration_node\.rest_pose: n_points'):
        node_params('registration_node', {'rest_pose': {'n_points': 5}})
    with pytest.raises(ParamsError, match='omega'):
        pipeline_params({'registration_node': {'omega': 2.0}})
    bad = tmp_path / 'bad.yaml'
    bad.write_text('registration_node: {omega: 0.1}\n')
    with pytest.raises(ParamsError, match='ros__parameters'):
        load_params_file(bad)
    with pytest.raises(ParamsError, match='does not exist'):
        load_params_file(tmp_path / 'missing.yaml')
    # a file changes what it names, in the dataclass it belongs to
    assert pipeline_params({'accumulator_node': {'window_size': 12, 'n_clusters': 9}})['schedule'].window_size == 12
    assert pipeline_params({'registration_node': {'preprocess': {'crop_min': [0, 0, 0]}}})['preprocess'].crop_min \
        == (0, 0, 0)


def _flat(values, prefix=''):
    for key, value in values.items():
        if isinstance(value, dict):
            yield from _flat(value, prefix + key + '.')
        else:
            yield prefix + key, value


def test_each_parameter_is_declared_once_per_node():
    for node in NODES:
        names = [d.name for d in declarations(node)]
        assert len(names) == len(set(names)), node


def test_readme_tables_are_generated_from_the_same_metadata():
    """The README's ROS API tables are exactly what config.docs generates (regenerate with
    `python -m skel_extract_ros.config.docs`); each row is a field's default, live flag and
    description."""
    readme = README.read_text()
    assert readme_with_tables(readme) == readme, 'README parameter tables out of date'
    for node in NODES:
        table = markdown_table(node)
        for d in declarations(node):
            live = 'yes' if d.spec.live else ''
            default = str(d.default).lower() if isinstance(d.default, bool) else str(d.default)
            assert f'| `{d.name}` | `{default}` | {live} | {d.spec.description} |' in table
    assert '| `max_iterations` | `10` | yes |' in markdown_table('joint_estimation_node')
    # a node with live parameters says from when they apply; one without says all are read-only
    assert set(LIVE_FROM) == {node for node in NODES if any(d.spec.live for d in declarations(node))}
    assert 'Every parameter of this node is read-only' in markdown_table('registration_node')
    with pytest.raises(ValueError, match='no block'):
        readme_with_tables(readme.replace('<!-- /parameters:accumulator_node -->', ''))


def test_node_declarations_carry_the_metadata(ros):
    """What a running node declares (ros2 param describe) is the field's metadata: the
    description, the range, read-only unless live; every parameter, with its default."""
    from skel_extract_ros.nodes.accumulator_node import AccumulatorNode
    from skel_extract_ros.nodes.joint_estimation_node import JointEstimationNode
    from skel_extract_ros.nodes.registration_node import RegistrationNode
    for cls in (RegistrationNode, AccumulatorNode, JointEstimationNode):
        node = ros.add(cls)
        for d in declarations(node.get_name()):
            descriptor = node.describe_parameter(d.name)
            assert descriptor.description == ros_description(d), d.name
            assert descriptor.read_only == (not d.spec.live), d.name
            value = node.get_parameter(d.name).value
            assert (list(value) if d.default == [] or isinstance(d.default, list) else value) == d.default, d.name
            low, high = d.spec.bounds()
            ranges = list(descriptor.floating_point_range) + list(descriptor.integer_range)
            if low is None or isinstance(d.default, bool):
                assert not ranges, d.name
            else:
                assert (ranges[0].from_value, ranges[0].to_value) == (pytest.approx(low), pytest.approx(high)), d.name
        ros_own = {'use_sim_time', 'start_type_description_service'}
        assert {d.name for d in declarations(node.get_name())} == set(node._parameters) - ros_own
