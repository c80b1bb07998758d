"""Plant families by name, found through the entry-point group ``metampc.plant_families``.

A package (this one, or a user's installed with pip into the same environment) registers a
:class:`~metampc_plant.family.PlantFamily` under its ``name`` with one entry point in its
setup.cfg; nothing in this project changes for it to be listed and used. Within one process,
:func:`register` adds a family defined in code (other processes, the nodes, only see installed
entry points). :func:`get_family` refuses an unknown name (:class:`UnknownFamily`, naming the
known ones). How to add one: docs/families.md.
"""
from importlib.metadata import entry_points
from typing import Dict, Tuple

from metampc_plant.family import PlantFamily

GROUP = 'metampc.plant_families'
DEFAULT = 'vanderpol'

_loaded: Dict[str, PlantFamily] = {}


class UnknownFamily(ValueError):
    """No installed package registers a family of that name (or it is broken)."""


def family_names() -> Tuple[str, ...]:
    """The registered family names (installed and registered in this process), sorted."""
    return tuple(sorted({ep.name for ep in entry_points(group=GROUP)} | set(_loaded)))


def register(family: PlantFamily) -> PlantFamily:
    """Make `family` known by its name in this process (ValueError if an installed family or
    another registered one has that name); returns it."""
    if not isinstance(family, PlantFamily):
        raise ValueError(f'need a PlantFamily, got {type(family).__name__}')
    known = _loaded.get(family.name)
    installed = any(ep.name == family.name for ep in entry_points(group=GROUP))
    if (known is not None and known != family) or (known is None and installed):
        raise ValueError(f'a plant family named {family.name!r} exists already')
    _loaded[family.name] = family
    return family


def get_family(name: str) -> PlantFamily:
    """The family registered as `name`; UnknownFamily (one line naming the installed ones)."""
    if name in _loaded:
        return _loaded[name]
    matches = [ep for ep in entry_points(group=GROUP) if ep.name == name]
    if not matches:
        raise UnknownFamily(f'unknown plant family {name!r}; installed: '
                            f'{", ".join(family_names()) or "none"}')
    try:
        family = matches[0].load()
    except Exception as err:  # a user's package: report, whatever it raised
        raise UnknownFamily(f'plant family {name!r} ({matches[0].value}) failed to load: '
                            f'{type(err).__name__}: {err}') from None
    if not isinstance(family, PlantFamily) or family.name != name:
        raise UnknownFamily(f'entry point {name} = {matches[0].value} must be a PlantFamily '
                            f'named {name!r}')
    _loaded[name] = family
    return family


__all__ = ['GROUP', 'DEFAULT', 'UnknownFamily', 'family_names', 'get_family', 'register']
