"""The README's parameter tables and params/skel_extract.yaml, generated from the
parameter dataclasses (config.values.declarations): rewrite both with
`python -m skel_extract_ros.config.docs`; tests keep them equal to what this generates."""
from __future__ import annotations

from pathlib import Path

from .files import DEFAULT_PARAMS_FILE
from .nodes import LIVE_FROM, NODES
from .values import declarations

README_FILE = DEFAULT_PARAMS_FILE.parents[1] / 'README.md'
README_BEGIN = '<!-- parameters:{node} (generated: python -m skel_extract_ros.config.docs) -->'
README_END = '<!-- /parameters:{node} -->'
READ_ONLY_NOTE = ' [read-only: set at start, in the params file or with --ros-args -p]'
YAML_HEADER = """\
# Parameters of the skel_extract_ros nodes and of `skel-extract run --params`.
# Defaults are the paper's Table 1 (Lu et al., AAAI 2018) where the paper gives a value.
# Nested keys are ROS dotted parameter names (preprocess.target_points, ...); 0.0 for an
# optional number is 'automatic', [] for an optional list 'unset'.
# What each one means, with its unit: README.md ("ROS API") or `ros2 param describe`.
# Generated from the parameter dataclasses (python -m skel_extract_ros.config.docs).
"""


def ros_description(declaration) -> str:
    """The description a node's ParameterDescriptor carries (read-only ones say so)."""
    return declaration.spec.description + ('' if declaration.spec.live else READ_ONLY_NOTE)


def _format_default(value) -> str:
    if isinstance(value, bool):
        return str(value).lower()
    return str(value)


def markdown_table(node: str) -> str:
    """The README table of a node's parameters: name, default, live, meaning (with unit)."""
    lines = ['| parameter | default | live | meaning (unit) |', '|---|---|---|---|']
    node_declarations = declarations(node)
    for d in node_declarations:
        live = 'yes' if d.spec.live else ''
        lines.append(f'| `{d.name}` | `{_format_default(d.default)}` | {live} | {d.spec.description} |')
    if any(d.spec.live for d in node_declarations):
        lines.append(f'\n`live`: `ros2 param set` applies it from {LIVE_FROM[node]}; the others are '
                     'read-only (a set fails with the reason).')
    else:
        lines.append('\nEvery parameter of this node is read-only once it runs (a set fails with the reason).')
    return '\n'.join(lines)


def readme_with_tables(text: str) -> str:
    """`text` with every node's generated block replaced by the current table (ValueError
    if a block's markers are missing)."""
    for node in NODES:
        begin, end = README_BEGIN.format(node=node), README_END.format(node=node)
        if begin not in text or end not in text:
            raise ValueError(f'the README has no block {begin} ... {end}')
        head, rest = text.split(begin, 1)
        _, tail = rest.split(end, 1)
        text = f'{head}{begin}\n{markdown_table(node)}\n{end}{tail}'
    return text


def yaml_scalar(value) -> str:
    """A default as YAML that PyYAML and ROS both read back as the same type (a float
    always has a '.': PyYAML reads 1e-06 as a string)."""
    if isinstance(value, bool):
        return str(value).lower()
    if isinstance(value, float):
        mantissa, e, exponent = repr(value).partition('e')
        return f'{mantissa}{"" if "." in mantissa else ".0"}{e}{exponent}'
    if isinstance(value, list):
        return '[' + ', '.join(map(yaml_scalar, value)) + ']'
    return str(value)


def params_yaml() -> str:
    """params/skel_extract.yaml: every node's parameters and defaults, by section."""
    lines = [YAML_HEADER.rstrip('\n')]
    for node in NODES:
        lines += [f'{node}:', '  ros__parameters:']
        by_section = {}
        for d in declarations(node):
            by_section.setdefault(d.section, []).append(d)
        for section, members in by_section.items():
            indent = '    '
            if section.prefix:
                lines.append(f"{indent}{section.prefix.rstrip('.')}:  # {section.title}")
                indent += '  '
            else:
                lines.append(f'{indent}# --- {section.title} ---')
            lines += [f'{indent}{d.name[len(section.prefix):]}: {yaml_scalar(d.default)}' for d in members]
    return '\n'.join(lines) + '\n'


def main(argv=None) -> int:
    """python -m skel_extract_ros.config.docs [README.md]: rewrite the README's tables in
    place and params/skel_extract.yaml."""
    import sys
    paths = (argv if argv is not None else sys.argv[1:]) or [README_FILE]
    for path in map(Path, paths):
        path.write_text(readme_with_tables(path.read_text()))
    DEFAULT_PARAMS_FILE.write_text(params_yaml())
    return 0


if __name__ == '__main__':
    raise SystemExit(main())
