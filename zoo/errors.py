"""The errors sdfzoo raises. Every message says what was wrong and what to do.

All derive from :class:`ZooError`, so ``except zoo.errors.ZooError`` catches them all; each
also derives from the builtin a Python user would expect (``ValueError`` for bad input,
``LookupError`` for unknown names, ...).
"""

from __future__ import annotations


class ZooError(Exception):
    """Base class of every error sdfzoo raises on purpose."""


class InputError(ZooError, ValueError):
    """An argument has the wrong shape, dtype or value (NaN, Inf, empty, out of range)."""


class ModelNotFoundError(ZooError, LookupError):
    """An unknown model name, version, shape or file."""


class ChecksumError(ZooError):
    """A file's sha256 does not match the one recorded for it (corrupt or changed)."""


class DataError(ZooError):
    """Input data (a mesh, an HDF5 file, a manifest, a checkpoint) is missing or unreadable."""


class MissingDependencyError(ZooError, ImportError):
    """An optional dependency is needed for this call but is not installed."""


class DeviceError(ZooError, RuntimeError):
    """A torch device that this machine or this torch build cannot use (no CUDA, no such GPU)."""


def require(module: str, extra: str = "pipeline"):
    """Import an optional dependency, or say which package extra installs it."""
    import importlib

    try:
        return importlib.import_module(module)
    except ImportError as exc:  # pragma: no cover - depends on the environment
        raise MissingDependencyError(
            f"this needs the optional dependency {module!r}: pip install 'sdfzoo[{extra}]'"
        ) from exc
