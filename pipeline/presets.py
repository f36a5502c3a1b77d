"""Named presets of a config: one table type and one getter for every stage.

``PRESETS = Presets("fit", quick=FitConfig(...), default=FitConfig(...))``;
``PRESETS.lookup("quick", steps=10)`` is that preset with fields replaced, and an unknown name raises
:class:`zoo.errors.InputError` listing the known ones. ``default`` is, by convention, what the
shipped models use.
"""

from __future__ import annotations

from dataclasses import replace

from zoo.errors import InputError


class Presets(dict):
    """{name: config dataclass} of one stage; ``what`` names the stage in errors ("fit", "triangle")."""

    def __init__(self, what: str, **presets):
        super().__init__(presets)
        self.what = what

    def lookup(self, name: str, **overrides):
        """The preset ``name``, with ``overrides`` (field=value) replaced; InputError for an unknown name."""
        if name not in self:
            raise InputError(f"unknown {self.what} preset {name!r}; choose one of {', '.join(sorted(self))}")
        return replace(self[name], **overrides) if overrides else self[name]

    def lookup_or_default(self, name: str):
        """The preset ``name`` if this stage has one, else ``default`` (a run's preset that only some stages name)."""
        return self[name] if name in self else self["default"]
