"""File digests for provenance (trials, model files)."""

from __future__ import annotations

import hashlib


def file_sha256(path) -> str:
    """Hex SHA-256 of a file, read in 1 MiB chunks (memory stays bounded for any size)."""
    h = hashlib.sha256()
    with open(path, "rb") as fh:
        for chunk in iter(lambda: fh.read(1 << 20), b""):
            h.update(chunk)
    return h.hexdigest()
