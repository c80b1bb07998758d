"""Parameters declared once: on the fields of the typed config dataclasses. No rclpy.

A config field that is a node parameter is declared with :func:`param` (default, one-line
description, range or choices, ``live``). From those fields come the node's declaration table
(:func:`table`: name -> :class:`ParamSpec`, which ``node_main`` declares; live ones may change
while the node runs, the others are read-only), the parse and range checks of raw ROS values
(:func:`build` -> the typed config, or a :class:`ParameterError` naming the first bad
parameter; then the config's own ``validate()``), the checks of a config built in code
(:func:`check_fields`) and the docs' parameter rows (test/test_docs.py). A parameter is named
after its field with the section's prefix, or an explicit rename; one renamed in this release
keeps its former name or choice for one release (``formerly=``, ``renamed=``; :mod:`.renames`).
See docs/architecture.md.
"""
import dataclasses
import math
import numbers
from typing import Any, Dict, List, Mapping, NamedTuple, Optional, Sequence, Tuple, Union

from metampc_common.renames import renamed_key, renamed_value

Value = Union[bool, int, float, str, List[float], List[int], List[str]]
PARAM = 'metampc_param'      # the metadata key of a parameter field


class ParameterError(ValueError):
    """A node parameter is missing, of the wrong type or out of range."""


class ParamSpec(NamedTuple):
    """One declared node parameter: its default (which fixes its type), description, whether
    it may change while the node runs (else it is read-only), its name before a rename ('':
    none) and its renamed choices ((old, new) pairs)."""

    default: Value
    description: str
    live: bool = False
    formerly: str = ''
    renamed: Tuple[Tuple[str, str], ...] = ()


@dataclasses.dataclass(frozen=True)
class Rule:
    """What a parameter field accepts (see :func:`param`)."""

    description: str
    ge: Optional[float] = None
    gt: Optional[float] = None
    le: Optional[float] = None
    lt: Optional[float] = None
    choices: Tuple[str, ...] = ()
    item: Optional[type] = None      # element type of a list (default: the default's)
    length: Optional[int] = None     # exact length of a list
    scalar: bool = False             # a lone number is a list of one (`-p theta:=0.7`)
    live: bool = False               # may change while the node runs
    infinite: bool = False           # +-inf accepted (a bound that is no bound); never NaN
    formerly: str = ''               # the field's name before a rename
    renamed: Tuple[Tuple[str, str], ...] = ()   # (old, new) names of renamed choices

    def bounds(self) -> str:
        """'> 0', '>= 1', 'in [0, 1)', 'one of a, b' or ''."""
        if self.choices:
            return 'one of ' + ', '.join(self.choices)
        low = ('[', self.ge) if self.ge is not None else ('(', self.gt)
        high = (']', self.le) if self.le is not None else (')', self.lt)
        if low[1] is not None and high[1] is not None:
            return f'in {low[0]}{low[1]:g}, {high[1]:g}{high[0]}'
        if low[1] is not None:
            return ('>= ' if low[0] == '[' else '> ') + f'{low[1]:g}'
        if high[1] is not None:
            return ('<= ' if high[0] == ']' else '< ') + f'{high[1]:g}'
        return ''


def param(default: Any, description: str, *, ge: Optional[float] = None,
          gt: Optional[float] = None, le: Optional[float] = None, lt: Optional[float] = None,
          choices: Sequence[str] = (), item: Optional[type] = None,
          length: Optional[int] = None, scalar: bool = False, live: bool = False,
          infinite: bool = False, formerly: str = '', renamed: Mapping[str, str] = {}) -> Any:
    """A dataclass field that is a node parameter.

    Args:
        default: the one default; its type is the parameter's (a tuple default is a list
            parameter; floats accept integers).
        description: one line, without the range (added from the bounds).
        ge, gt, le, lt: bounds of a number, or of each element of a list.
        choices: the accepted strings.
        item: element type of a list whose default is empty.
        length: exact length of a list.
        scalar: a list that also takes a lone number, as a list of one (a one-input family's
            bound, a one-component theta).
        live: the node takes a new value while it runs (``ros2 param set``; the node says how
            and when it applies it); the others are read-only.
        infinite: numbers may be +-inf (e.g. a bound that leaves one side free); NaN never.
        formerly: the field's name before it was renamed: the parameter's former name (with
            the section's prefix) still works for one release, with a warning.
        renamed: {old: new} choices renamed: an old one still works for one release, with a
            warning.
    """
    rule = Rule(description, ge, gt, le, lt, tuple(choices), item, length, scalar, live,
                infinite, formerly, tuple(renamed.items()))
    if isinstance(default, (list, tuple)):
        frozen = tuple(default)
        return dataclasses.field(default=frozen, metadata={PARAM: rule})
    return dataclasses.field(default=default, metadata={PARAM: rule})


def number(name: str, value: Value, integer: bool = False) -> Union[int, float]:
    """`value` as an int or a float; ParameterError naming `name` if it is neither.

    Integers are accepted for floats, so that `-p rate_hz:=50` works as users expect (numpy
    scalars too: configs are also built from arrays).
    """
    ok = isinstance(value, numbers.Integral if integer else numbers.Real)
    if isinstance(value, bool) or not ok:
        kind = 'an integer' if integer else 'a number'
        raise ParameterError(f'{name} must be {kind}, got {value!r}')
    return int(value) if integer else float(value)


def _in_range(name: str, x: float, rule: Rule) -> None:
    ok = ((rule.ge is None or x >= rule.ge) and (rule.gt is None or x > rule.gt)
          and (rule.le is None or x <= rule.le) and (rule.lt is None or x < rule.lt))
    if not ok:
        raise ParameterError(f'{name} must be {rule.bounds()}, got {x:g}')


YAML_BOOL_WORDS = {False: 'off', True: 'on'}


def _scalar(name: str, value: Value, kind: type, rule: Rule) -> Any:
    if kind is bool:
        if not isinstance(value, bool):
            raise ParameterError(f'{name} must be true or false, got {value!r}')
        return value
    if kind is str:
        # ROS reads `-p adaptation:=off` as YAML 1.1, where off/on (no/yes) are booleans; a
        # choice spelled that way is what the user meant.
        if isinstance(value, bool) and YAML_BOOL_WORDS[value] in rule.choices:
            value = YAML_BOOL_WORDS[value]
        value = renamed_value(value, dict(rule.renamed), name)
        if not isinstance(value, str):
            raise ParameterError(f'{name} must be a string, got {value!r}')
        if rule.choices and value not in rule.choices:
            raise ParameterError(f'{name} must be one of {", ".join(rule.choices)}, '
                                 f'got {value!r}')
        return value
    x = number(name, value, integer=kind is int)
    if not math.isfinite(x) and not (rule.infinite and not math.isnan(x)):
        raise ParameterError(f'{name} must be finite, got {x}')
    _in_range(name, x, rule)
    return x


def check_value(name: str, value: Value, default: Any, rule: Rule) -> Any:
    """`value` typed like `default` and within `rule` (a list as a tuple); else ParameterError."""
    if not isinstance(default, tuple):
        return _scalar(name, value, type(default), rule)
    kind = rule.item or (type(default[0]) if default else float)
    if value is None or value == b'':   # how rclpy gives `-p name:=[]` (NOT_SET) or an
        value = ()                      # undeclared-type [] (an empty byte array): no items
    if rule.scalar and isinstance(value, numbers.Real) and not isinstance(value, bool):
        value = (value,)
    if isinstance(value, (str, bytes, bool)) or not hasattr(value, '__len__'):
        raise ParameterError(f'{name} must be a list of {_plural(kind)}, got {value!r}')
    if rule.length is not None and len(value) != rule.length:
        raise ParameterError(f'{name} must be a list of {rule.length} {_plural(kind)}, '
                             f'got {list(value)!r}')
    return tuple(_scalar(name, v, kind, rule) for v in value)


def _plural(kind: type) -> str:
    return {int: 'integers', float: 'numbers', str: 'strings', bool: 'booleans'}[kind]


def param_fields(cls: type) -> List[dataclasses.Field]:
    """The fields of a config dataclass that are node parameters, in order."""
    return [f for f in dataclasses.fields(cls) if PARAM in f.metadata]


class Section(NamedTuple):
    """The parameters of one config dataclass in a node's table.

    Attributes:
        cls: the config dataclass.
        prefix: prepended to each field name.
        rename: {field: parameter name} where the name is not prefix + field.
    """

    cls: type
    prefix: str = ''
    rename: Mapping[str, str] = {}

    def name(self, field: str) -> str:
        """The node parameter of `field`."""
        return self.rename.get(field, self.prefix + field)


def table(sections: Sequence[Section]) -> Dict[str, ParamSpec]:
    """The declaration table of a node: {name: ParamSpec(default, description (range), live)}."""
    out: Dict[str, ParamSpec] = {}
    for section in sections:
        for f in param_fields(section.cls):
            name = section.name(f.name)
            if name in out:
                raise ValueError(f'parameter {name} declared twice')
            rule = f.metadata[PARAM]
            bounds = rule.bounds()
            default = list(f.default) if isinstance(f.default, tuple) else f.default
            out[name] = ParamSpec(default, rule.description + (f' ({bounds})' if bounds else ''),
                                  rule.live, section.name(rule.formerly) if rule.formerly else '',
                                  rule.renamed)
    return out


def current_names(values: Mapping[str, Any], table: Mapping[str, ParamSpec], where: str = ''
                  ) -> Dict[str, Any]:
    """`values` by parameter name, a former name replaced by today's (with a warning; `where`
    prefixes the names in the lines).

    Raises:
        ParameterError: a parameter given under both names.
    """
    out = dict(values)
    for name, spec in table.items():
        if spec.formerly:
            try:
                out = renamed_key(out, spec.formerly, name, where)
            except ValueError as err:
                raise ParameterError(str(err)) from None
    return out


def upgraded(values: Mapping[str, Value], table: Mapping[str, ParamSpec], where: str = ''
             ) -> Dict[str, Value]:
    """`values` under today's names (:func:`current_names`) and choices (a renamed choice
    replaced by today's, with a warning)."""
    out = current_names(values, table, where)
    for name, spec in table.items():
        if spec.renamed and name in out:
            out[name] = renamed_value(out[name], dict(spec.renamed), f'{where}{name}')
    return out


def build(section: Section, values: Mapping[str, Value], **others: Any) -> Any:
    """The config of `section` from raw values (keyword `others` for its other fields), checked
    field by field, then by its ``validate()`` (a ValueError becomes a ParameterError)."""
    kwargs = {f.name: check_value(section.name(f.name), values[section.name(f.name)],
                                  f.default, f.metadata[PARAM])
              for f in param_fields(section.cls)}
    config = section.cls(**kwargs, **others)
    validate = getattr(config, 'validate', None)
    if validate is not None:
        try:
            validate()
        except ValueError as err:
            raise ParameterError(str(err)) from None
    return config


def check_fields(config: Any, skip: Sequence[str] = ()) -> None:
    """Every parameter field of a config built in code (but those in `skip`, which the config
    checks itself) within its rule; ValueError (a ParameterError) naming the first one that is
    not."""
    for f in param_fields(type(config)):
        if f.name not in skip:
            check_value(f.name, getattr(config, f.name), f.default, f.metadata[PARAM])
