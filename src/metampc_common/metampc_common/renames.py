"""Names retired by a rename: the old one still works for one release, with one warning line
that names the new one; the old and the new one given together is an error.

A key (an experiment YAML's ``learner.horizon``, a node parameter ``-p horizon:=10``) and a
value out of a set of choices (``reference: paper``) are renamed the same way. Each warning is
written once per process: a node parses its parameters again at every live change.
"""
import sys
from typing import Any, Dict, Mapping

_written = set()


def warn_once(line: str) -> None:
    """Write ``warning: <line>`` to stderr, the first time only."""
    if line not in _written:
        _written.add(line)
        print(f'warning: {line}', file=sys.stderr, flush=True)


def renamed_key(values: Mapping[str, Any], old: str, new: str, where: str = ''
                ) -> Dict[str, Any]:
    """`values` with the key `old` renamed `new` (with a warning); `where` prefixes the names
    in the lines (e.g. ``'config: learner.'``).

    Raises:
        ValueError: both `old` and `new` are given.
    """
    if old not in values:
        return dict(values)
    if new in values:
        raise ValueError(f'{where}{old} and {new} are both given: {old} is renamed {new}; '
                         f'give {new} only')
    warn_once(f'{where}{old} is renamed {new}; the old name will be removed in the next '
              'release')
    return {new if key == old else key: value for key, value in values.items()}


def renamed_value(value: Any, renames: Mapping[str, str], where: str) -> Any:
    """`value`, or its new name (with a warning) if `renames` ({old: new}) renames it; `where`
    names the setting in the line (e.g. ``'reference'``)."""
    if isinstance(value, str) and value in renames:
        warn_once(f'{where}: {value!r} is renamed {renames[value]!r}; the old value will be '
                  'removed in the next release')
        return renames[value]
    return value
