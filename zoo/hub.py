"""Packages on the Hugging Face Hub: ``zoo.load("hf-hub:ORG/NAME@TAG")`` resolves through huggingface_hub's cache.

huggingface_hub is imported here, inside the call, and nowhere else in ``zoo``: a simulator that
loads bundled models never pays for it. Its environment (``HF_HUB_OFFLINE``, ``HF_HUB_CACHE``,
``HF_HOME``) is read at call time rather than trusted from huggingface_hub's import-time
constants, so setting it in a running process (a test, a notebook) takes effect.
"""

from __future__ import annotations

import os
import re
from pathlib import Path

from .errors import DataError, ModelNotFoundError, require

_REPO_ID = re.compile(r"[A-Za-z0-9][A-Za-z0-9_.-]*/[A-Za-z0-9][A-Za-z0-9_.-]*")
_TRUE = {"1", "ON", "YES", "TRUE"}


def parse_hub_spec(spec: str) -> tuple[str, str]:
    """``"ORG/NAME@TAG"`` -> ``("ORG/NAME", "TAG")``; no ``@`` means the ``main`` branch."""
    repo_id, _, revision = spec.partition("@")
    if not _REPO_ID.fullmatch(repo_id):
        raise ModelNotFoundError(f"hf-hub:{spec} does not name a Hub repository; write hf-hub:ORG/NAME@TAG (for example hf-hub:acme/mugs@1.0.0)")
    return repo_id, revision or "main"


def hub_offline() -> bool:
    return any(os.environ.get(var, "").upper() in _TRUE for var in ("HF_HUB_OFFLINE", "TRANSFORMERS_OFFLINE"))


def hub_cache_dir() -> Path | None:
    """``HF_HUB_CACHE``, else ``HF_HUB_CACHE``'s legacy name, else ``$HF_HOME/hub``; None lets huggingface_hub decide."""
    for var in ("HF_HUB_CACHE", "HUGGINGFACE_HUB_CACHE"):
        if os.environ.get(var):
            return Path(os.path.expandvars(os.environ[var])).expanduser()
    if os.environ.get("HF_HOME"):
        return Path(os.path.expandvars(os.environ["HF_HOME"])).expanduser() / "hub"
    return None


def zoo_cache_dir() -> Path:
    """Where sdfzoo keeps what it derives and reuses across runs (baked SDF proxies, :mod:`zoo.proxy`):
    ``ZOO_CACHE``, else ``$XDG_CACHE_HOME/sdfzoo``, else ``~/.cache/sdfzoo``; read at call time, as the Hub's."""
    if os.environ.get("ZOO_CACHE"):
        return Path(os.path.expandvars(os.environ["ZOO_CACHE"])).expanduser()
    base = os.environ.get("XDG_CACHE_HOME")
    return (Path(os.path.expandvars(base)).expanduser() if base else Path.home() / ".cache") / "sdfzoo"


def snapshot_dir(spec: str, pin: str | None = None) -> Path:
    """The local folder of ``ORG/NAME@REVISION``: downloaded if needed, from the cache when offline; ``pin``
    (a commit) replaces the revision: the files of that commit, whatever the tag points at now."""
    repo_id, revision = parse_hub_spec(spec)
    revision = pin or revision
    hub = require("huggingface_hub", extra="pipeline")
    from huggingface_hub.errors import (
        IncompleteSnapshotError,
        LocalEntryNotFoundError,
        RepositoryNotFoundError,
        RevisionNotFoundError,
    )

    cache = hub_cache_dir()
    offline = hub_offline()
    try:
        folder = hub.snapshot_download(repo_id, revision=revision, cache_dir=cache, local_files_only=offline)
    except (RevisionNotFoundError, RepositoryNotFoundError) as exc:
        raise ModelNotFoundError(
            f"hf-hub:{repo_id}@{revision}: the Hub has no such repository or revision ({type(exc).__name__}); "
            "check the name and the tag (tags are the model versions, for example 1.0.0)"
        ) from exc
    except IncompleteSnapshotError as exc:
        raise DataError(f"hf-hub:{repo_id}@{revision}: the cached snapshot is incomplete ({exc})") from exc
    except LocalEntryNotFoundError as exc:
        where = cache if cache is not None else "the default Hugging Face cache"
        raise ModelNotFoundError(
            f"hf-hub:{repo_id}@{revision} is not in {where}"
            + (" and HF_HUB_OFFLINE is set: download it once with network access" if offline else " and the Hub could not be reached")
            + " (or set HF_HUB_CACHE / HF_HOME to the cache that holds it)"
        ) from exc
    return Path(folder)
