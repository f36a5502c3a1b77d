"""Atomic writes and sha256 checksums: nothing half-written, nothing corrupt loaded silently."""

from __future__ import annotations

import contextlib
import hashlib
import json
import os
import tempfile
from pathlib import Path

from .errors import ChecksumError, DataError

CHECKSUMS = "SHA256SUMS"


def sha256_file(path: str | os.PathLike, chunk: int = 1 << 20) -> str:
    """Hex sha256 of a file's bytes."""
    h = hashlib.sha256()
    with open(path, "rb") as f:
        for block in iter(lambda: f.read(chunk), b""):
            h.update(block)
    return h.hexdigest()


def current_umask() -> int:
    """The process's umask, read without changing it where the OS shows it (Linux), else set and restored."""
    try:
        with open("/proc/self/status") as f:
            for line in f:
                if line.startswith("Umask:"):
                    return int(line.split()[1], 8)
    except OSError:
        pass
    mask = os.umask(0o022)
    os.umask(mask)
    return mask


@contextlib.contextmanager
def atomic_path(path: str | os.PathLike):
    """Yield a temporary path beside ``path``; rename it onto ``path`` only if the block succeeds.

    A crash (even SIGKILL) leaves either the old file or the new one, never a half-written one.
    """
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".tmp", dir=path.parent)
    os.close(fd)
    os.chmod(tmp, 0o666 & ~current_umask())  # mkstemp makes it 0600; the file gets the mode open() would give it
    try:
        yield Path(tmp)
        with open(tmp, "rb") as f:
            os.fsync(f.fileno())
        os.replace(tmp, path)
    finally:
        if os.path.exists(tmp):
            os.unlink(tmp)


def atomic_write_text(path: str | os.PathLike, text: str) -> None:
    with atomic_path(path) as tmp:
        Path(tmp).write_text(text)


def write_safetensors(path: str | os.PathLike, tensors: dict, metadata: dict | None = None) -> Path:
    """Write ``tensors`` as a safetensors file, atomically and byte for byte reproducibly.

    safetensors (0.8) writes ``__metadata__`` in the order of a Rust HashMap, which changes from
    one process to the next: with two or more metadata keys, the same tensors gave different
    bytes (and sha256) in every run. The header is rewritten here with those keys sorted (the
    same JSON, the same length); the tensor data are untouched.
    """
    from safetensors.torch import save

    data = save(tensors, metadata=metadata)
    n = int.from_bytes(data[:8], "little")
    header = json.loads(data[8 : 8 + n])
    if len(header.get("__metadata__") or {}) > 1:
        header["__metadata__"] = dict(sorted(header["__metadata__"].items()))
        text = json.dumps(header, separators=(",", ":"), ensure_ascii=False).encode()
        if len(text) <= n:  # always, as only the order changed; else keep safetensors' own bytes
            data = data[:8] + text + b" " * (n - len(text)) + data[8 + n :]
    path = Path(path)
    with atomic_path(path) as tmp:
        Path(tmp).write_bytes(data)
    return path


def write_checksums(directory: str | os.PathLike) -> dict[str, str]:
    """Write ``SHA256SUMS`` listing every file under ``directory`` (but itself); return {relpath: sha256}."""
    directory = Path(directory)
    sums = {
        p.relative_to(directory).as_posix(): sha256_file(p)
        for p in sorted(directory.rglob("*"))
        if p.is_file() and p.name != CHECKSUMS and not p.name.startswith(".")
    }
    atomic_write_text(directory / CHECKSUMS, "".join(f"{h}  {name}\n" for name, h in sums.items()))
    return sums


def read_checksums(directory: str | os.PathLike) -> dict[str, str]:
    path = Path(directory) / CHECKSUMS
    if not path.is_file():
        raise DataError(f"{directory} has no {CHECKSUMS}: it is not an sdfzoo package (create one with `zoo package`)")
    sums = {}
    for line in path.read_text().splitlines():
        if line.strip():
            digest, _, name = line.partition("  ")
            sums[name.strip()] = digest.strip()
    return sums


def verify_file(directory: str | os.PathLike, name: str, sums: dict[str, str] | None = None) -> Path:
    """Check one file of a package against its recorded sha256; return its path."""
    sums = read_checksums(directory) if sums is None else sums
    path = Path(directory) / name
    if name not in sums:
        raise ChecksumError(f"{path} is not listed in {CHECKSUMS}; the package is incomplete: re-create it with `zoo package`")
    if not path.is_file():
        raise DataError(f"{path} is missing from the package; re-download or re-create it")
    actual = sha256_file(path)
    if actual != sums[name]:
        raise ChecksumError(
            f"{path} is corrupt or changed: sha256 {actual} but {CHECKSUMS} expects {sums[name]}; "
            "re-download or re-create the package"
        )
    return path


def verify_directory(directory: str | os.PathLike) -> dict[str, str]:
    """Verify every file listed in ``SHA256SUMS``; return the listing."""
    sums = read_checksums(directory)
    for name in sums:
        verify_file(directory, name, sums)
    return sums
