"""Typed, range-checked node parameters, shared by every metampc node. No rclpy.

A node keeps a table ``{name: ParamSpec(default, description)}``; :mod:`metampc_common.node_main`
declares it and hands the values to the node's own parse function, which builds a typed config
with :func:`number` and raises :class:`ParameterError` naming the first bad parameter.
"""
from typing import List, NamedTuple, Union

Value = Union[bool, int, float, str, List[float], List[int], List[str]]


class ParameterError(ValueError):
    """A node parameter is missing, of the wrong type or out of range."""


class ParamSpec(NamedTuple):
    """One node parameter: its default (which fixes its type) and a one-line description."""

    default: Value
    description: str


def number(name: str, value: Value, integer: bool = False) -> Union[int, float]:
    """`value` as an int or a float; ParameterError naming `name` if it is neither.

    Integers are accepted for floats, so that `-p rate_hz:=50` works as users expect.
    """
    ok = isinstance(value, int) if integer else isinstance(value, (int, float))
    if isinstance(value, bool) or not ok:
        kind = 'an integer' if integer else 'a number'
        raise ParameterError(f'{name} must be {kind}, got {value!r}')
    return int(value) if integer else float(value)
