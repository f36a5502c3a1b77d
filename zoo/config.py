"""Config dataclasses <-> plain dicts (JSON), one mechanism for every config of zoo and the pipeline.

:func:`to_dict` writes the fields in declaration order, nested dataclasses as dicts and tuples
as lists, so ``json.dumps(to_dict(c))`` is what the hand-written methods it replaces wrote
(package config.json files and their sha256s stay byte-identical). :func:`from_dict` is its
inverse: nested dataclass fields are rebuilt from their dicts, list values of tuple fields
become tuples (of float / int where the annotation says so), and a key the dataclass does not
have raises :class:`zoo.errors.InputError` naming it (``ignore`` lists descriptive keys that
are dropped instead). :class:`DictConfig` gives a dataclass both as methods.
"""

from __future__ import annotations

import dataclasses
import functools
import typing

from .errors import InputError


def to_dict(config) -> dict:
    """The dataclass ``config`` as a JSON-able dict: fields in order, nested dataclasses and tuples unpacked."""
    return {f.name: _plain(getattr(config, f.name)) for f in dataclasses.fields(config)}


def _plain(value):
    if dataclasses.is_dataclass(value) and not isinstance(value, type):
        return to_dict(value)
    if isinstance(value, (tuple, list)):
        return [_plain(v) for v in value]
    if isinstance(value, dict):
        return {k: _plain(v) for k, v in value.items()}
    return value


def from_dict(cls, d: dict, what: str | None = None, ignore: tuple[str, ...] = (), hint: str = ""):
    """The dataclass ``cls`` built from ``d`` (as written by :func:`to_dict`); InputError for unknown keys.

    ``what`` names the config in the error ("fit config"); ``ignore``: keys that are accepted and
    dropped; ``hint`` ends the error message (what to do about an unknown key).
    """
    if not isinstance(d, dict):
        raise InputError(f"a {what or cls.__name__} must be a mapping of field names to values, got {type(d).__name__}")
    types = _field_types(cls)
    unknown = set(d) - set(types) - set(ignore)
    if unknown:
        raise InputError(f"unknown {what or cls.__name__} keys {sorted(unknown)}; known: {sorted(types)}{hint}")
    return cls(**{k: _typed(types[k], v) for k, v in d.items() if k in types})


@functools.cache
def _field_types(cls) -> dict:
    """{field name: resolved annotation} of a dataclass (``from __future__ import annotations`` safe)."""
    hints = typing.get_type_hints(cls)
    return {f.name: hints.get(f.name) for f in dataclasses.fields(cls) if f.init}


def _typed(annotation, value):
    """``value`` converted to what ``annotation`` asks: a nested dataclass from a dict, a tuple from a list."""
    if isinstance(annotation, type) and dataclasses.is_dataclass(annotation) and isinstance(value, dict):
        return annotation.from_dict(value) if issubclass(annotation, DictConfig) else from_dict(annotation, value)
    if typing.get_origin(annotation) is tuple and isinstance(value, (list, tuple)):
        args = [a for a in typing.get_args(annotation) if a is not Ellipsis]
        scalar = args[0] if args and all(a is args[0] for a in args) and args[0] in (int, float) else None
        return tuple(scalar(v) if scalar else v for v in value)
    return value


class DictConfig:
    """Mixin: ``to_dict()`` and ``from_dict(d)`` for a config dataclass.

    Class attributes: ``_config_name`` names it in errors, ``_ignored_keys`` are dropped on reading,
    ``_unknown_hint`` ends the unknown-key error.
    """

    _config_name: typing.ClassVar[str | None] = None
    _ignored_keys: typing.ClassVar[tuple[str, ...]] = ()
    _unknown_hint: typing.ClassVar[str] = ""

    def to_dict(self) -> dict:
        return to_dict(self)

    @classmethod
    def from_dict(cls, d: dict):
        return from_dict(cls, d, cls._config_name, cls._ignored_keys, cls._unknown_hint)
