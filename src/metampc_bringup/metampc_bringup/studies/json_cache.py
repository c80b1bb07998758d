"""A study's step cached as one JSON object keyed by the settings that made it.

:func:`save` writes the object; :func:`cached` reads it back only when it holds every item of
the settings asked for (a changed setting computes the step again). Used by the Cascaded
Tanks benchmark to resume (:mod:`metampc_bringup.studies.cascaded_tanks`).
"""
import json
import os
from typing import Optional


def cached(path: str, wanted: dict) -> Optional[dict]:
    """The JSON object in `path` if it holds every item of `wanted`, else None."""
    if not os.path.exists(path):
        return None
    with open(path, encoding='utf-8') as f:
        found = json.load(f)
    return found if all(found.get(k) == v for k, v in wanted.items()) else None


def save(path: str, value: dict) -> None:
    """`value` as JSON in `path` (indented by one)."""
    with open(path, 'w', encoding='utf-8') as f:
        json.dump(value, f, indent=1)
