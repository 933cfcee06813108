"""Parameter values between the dataclasses and ROS / YAML, in one place.

ROS parameters cannot be None: an optional number (default None, 'automatic') is 0.0 and
an optional list ('unset') is [] in a node and in the YAML file; [x, y, z] tuples are
lists of floats. `declarations` lists a node's parameters as it declares them, and
`node_params` builds a node's dataclasses back from {name: value}.
"""
from __future__ import annotations

import dataclasses
import typing

from ..core.parameters import Spec, specs
from .files import ParamsError
from .nodes import NODE_KEY, NODES, Section


@dataclasses.dataclass(frozen=True)
class Declaration:
    """One ROS parameter of a node: `name` (dotted), `default` as the node declares it,
    and the `spec` (description, range or choices, live) of its dataclass field."""

    name: str
    default: object
    spec: Spec
    section: Section

    @property
    def untyped(self) -> bool:
        """An empty list by default: its ROS type comes with the first value set."""
        return self.default == []


def ros_default(field: dataclasses.Field, hint) -> object:
    """The value a node declares for a dataclass field: None -> 0.0 for an optional number,
    [] for an optional list; a tuple -> a list of floats."""
    default = field.default
    if default is None:
        return 0.0 if float in typing.get_args(hint) else []
    if isinstance(default, tuple):
        return [float(v) for v in default]
    return default


def from_ros(field: dataclasses.Field, value) -> object:
    """A ROS / YAML value as the dataclass field takes it (the inverse of ros_default)."""
    default = field.default
    sequence = not isinstance(value, (str, bytes)) and hasattr(value, '__len__')
    if default is None and (value in (0, 0.0, '') if not sequence else len(value) == 0):
        return None
    if sequence:
        return tuple(value)
    if isinstance(default, float) and isinstance(value, int) and not isinstance(value, bool):
        return float(value)
    return value


def declarations(node: str) -> list:
    """Every parameter of a node, in declaration order."""
    result = []
    for section in NODES[node]:
        hints = typing.get_type_hints(section.cls)
        for name, (field, spec) in specs(section.cls).items():
            result.append(Declaration(section.prefix + name, ros_default(field, hints[name]), spec, section))
    return result


def parameter_defaults(node: str) -> dict:
    """{name: default as the node declares it (and the YAML file holds it)} of a node."""
    return {d.name: d.default for d in declarations(node)}


_PREFIXES = {section.prefix for sections in NODES.values() for section in sections if section.prefix}


def _flat(values: dict, prefix: str = '') -> dict:
    """Nested YAML mappings as dotted names (an empty section, `rest_pose:`, is no parameter)."""
    flat = {}
    for key, value in values.items():
        if isinstance(value, dict) or (value is None and f'{prefix}{key}.' in _PREFIXES):
            flat.update(_flat(value or {}, f'{prefix}{key}.'))
        else:
            flat[prefix + key] = value
    return flat


def node_params(node: str, values: dict) -> dict:
    """{section key: dataclass} of a node from {name: value} (dotted names or nested
    mappings; a missing name takes its default). ParamsError (a ValueError) names the
    node, the section and the parameter that is unknown or out of range."""
    values = _flat(values)
    fields = {d.name: d.section for d in declarations(node)}
    unknown = sorted(set(values) - set(fields))
    if unknown:
        prefix = unknown[0].rpartition('.')[0]
        valid = sorted(n for n in fields if n.rpartition('.')[0] == prefix)
        raise ParamsError(f'{node}: unknown parameter(s) {", ".join(unknown)}; valid: {", ".join(valid)}')
    built = {}
    for section in NODES[node]:
        cls_fields = {f.name: f for f in dataclasses.fields(section.cls)}
        mine = {name[len(section.prefix):]: value for name, value in values.items() if fields[name] is section}
        try:
            built[section.key] = section.cls(**{k: from_ros(cls_fields[k], v) for k, v in mine.items()})
        except (TypeError, ValueError) as error:
            where = node + ('.' + section.prefix.rstrip('.') if section.prefix else '')
            raise ParamsError(f'{where}: {error}') from error
    return built


def pipeline_params(nodes: dict) -> dict:
    """Keyword arguments of SkeletonPipeline from a loaded parameter file ({node name:
    {name: value}}): every node's method dataclasses (its own are validated, not returned)."""
    kwargs = {}
    for node in NODES:
        built = node_params(node, nodes.get(node, {}))
        kwargs.update({key: value for key, value in built.items() if key != NODE_KEY})
    return kwargs
