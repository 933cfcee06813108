"""Parameters that carry their own default, description and valid values.

Every parameter dataclass (the method's here in core, the nodes' own in config.nodes)
declares its fields with `parameter(...)`: the default, one description (what it is, with
its unit), and its range or choices. `validate`, called from each `__post_init__`, checks
the values against them; the ROS parameter declarations, params/skel_extract.yaml and the
README's tables are generated from the same metadata (skel_extract_ros.config).

A range is inclusive, [low, high], unless `above` / `below` replace a bound with a strict
one (the ROS descriptor can only say inclusive, so it shows the bound itself). INF stands
for no upper bound (a ROS range needs a number; float('inf') is then valid too). A field
whose default is None is optional (None: automatic or unset); None is then always valid.
"""
from __future__ import annotations

import dataclasses

INF = 1e300
_KEY = 'parameter'


@dataclasses.dataclass(frozen=True)
class Spec:
    """What a parameter field says about itself (its field metadata)."""

    description: str
    low: float | None = None
    high: float | None = None
    strict_low: bool = False
    strict_high: bool = False
    choices: tuple | None = None
    size: int | None = None        # a sequence of exactly this many numbers ([x, y, z])
    live: bool = False             # a running node applies a new value (else read-only)

    @property
    def ranged(self) -> bool:
        return self.low is not None or self.high is not None

    def bounds(self) -> tuple:
        """(low, high) as the ROS descriptor states them (None, None without a range)."""
        if not self.ranged:
            return None, None
        return (-INF if self.low is None else self.low), (INF if self.high is None else self.high)

    def problem(self, value) -> str | None:
        """Why `value` is not valid, or None."""
        if self.choices is not None and value not in self.choices:
            return f'must be {_one_of(self.choices)}, got {value!r}'
        if self.size is not None and len(value) != self.size:
            return f'must be {self.size} numbers ([x, y, z]), got {list(value)}'
        if self.ranged and not self._in_range(value):
            return f'must be in {self.interval()}, got {value}'
        return None

    def _in_range(self, value) -> bool:
        low, high = self.bounds()
        above = value > low if self.strict_low else value >= low
        below = high >= INF or (value < high if self.strict_high else value <= high)
        return above and below

    def interval(self) -> str:
        low, high = self.bounds()
        if high >= INF:
            return f'{"(" if self.strict_low else "["}{low}, inf)'
        return f'{"(" if self.strict_low else "["}{low}, {high}{")" if self.strict_high else "]"}'


def _one_of(choices: tuple) -> str:
    quoted = [repr(c) for c in choices]
    return ' or '.join(quoted) if len(quoted) < 3 else 'one of ' + ', '.join(quoted)


def parameter(default, description: str, low=None, high=None, *, above=None, below=None, choices=None,
              size=None, live: bool = False):
    """A dataclass field with its default and its Spec: an inclusive range [low, high]
    (`above` / `below` for a strict bound instead), or the valid `choices`, or the `size`
    of an [x, y, z] value; `live`: a running node applies a new value."""
    if choices is not None and default not in choices:
        raise ValueError(f'default {default!r} is not one of its choices {choices}')
    spec = Spec(description, above if above is not None else low, below if below is not None else high,
                above is not None, below is not None, tuple(choices) if choices is not None else None,
                size, live)
    return dataclasses.field(default=default, metadata={_KEY: spec})


def spec(field: dataclasses.Field) -> Spec | None:
    """The Spec of a parameter field (None for a field not declared with `parameter`)."""
    return field.metadata.get(_KEY)


def specs(cls) -> dict:
    """{field name: (field, Spec)} of every parameter field of a dataclass, in order."""
    return {f.name: (f, spec(f)) for f in dataclasses.fields(cls) if spec(f) is not None}


def validate(instance) -> None:
    """ValueError naming every field of `instance` whose value is out of its range or
    choices (a None is valid where the default is None)."""
    problems = []
    for name, (field, field_spec) in specs(type(instance)).items():
        value = getattr(instance, name)
        if value is None and field.default is None:
            continue
        problem = 'must be set, got None' if value is None else field_spec.problem(value)
        if problem:
            problems.append(f'{name} {problem}')
    if problems:
        raise ValueError('; '.join(problems))
