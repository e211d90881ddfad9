"""What the crowd works out once and keeps on disk (the impostor atlases, the LODs made for imported
characters): where it is kept, and the one rule for every file there.

Each file is a numpy archive of named arrays plus a ``checksum`` of them, written atomically
(crowd.files); ``read_arrays`` gives the arrays back only when the file reads whole and its arrays match
the checksum, and otherwise raises CacheError in one line, so the caller rebuilds and says so. A file's
name carries a hash of everything its contents depend on: a changed input is a new name, never a stale hit.
"""

from __future__ import annotations

import hashlib
import io
import os
from pathlib import Path

import numpy as np

from .errors import CrowdError
from .files import atomic_write_bytes


class CacheError(CrowdError, ValueError):
    """A cache file that cannot be used; the message is one line and names the file."""


def cache_dir(kind: str) -> Path:
    """Where files of `kind` ("impostors", "lods") are kept: $CROWD_CACHE_DIR (every kind together), else
    the user's cache folder ($XDG_CACHE_HOME or ~/.cache) /crowd/<kind>."""
    if os.environ.get("CROWD_CACHE_DIR"):
        return Path(os.environ["CROWD_CACHE_DIR"])
    base = os.environ.get("XDG_CACHE_HOME") or os.path.join(os.path.expanduser("~"), ".cache")
    return Path(base) / "crowd" / kind


def checksum(arrays) -> str:
    """SHA-256 (hex) of the arrays' bytes, one after another."""
    h = hashlib.sha256()
    for a in arrays:
        h.update(np.ascontiguousarray(a).tobytes())
    return h.hexdigest()


def write_arrays(path: Path, arrays: dict[str, np.ndarray]) -> None:
    """`arrays` (no pickled objects) and their checksum (in name order), atomically."""
    buffer = io.BytesIO()
    np.savez(buffer, checksum=np.array(checksum(arrays[k] for k in sorted(arrays))), **arrays)
    atomic_write_bytes(path, buffer.getvalue())


def read_arrays(path: Path) -> dict[str, np.ndarray]:
    """The arrays ``write_arrays`` wrote to `path`, checked against their checksum; CacheError otherwise."""
    try:
        with np.load(path, allow_pickle=False) as z:
            arrays = {k: z[k] for k in z.files}
    except Exception as exc:  # a truncated or foreign file: zip, pickle, key and shape errors alike
        raise CacheError(f"{path}: not a cache file ({type(exc).__name__}: {str(exc).splitlines()[0] if str(exc) else ''})") from None
    stored = arrays.pop("checksum", None)
    if stored is None or stored.shape != () or checksum(arrays[k] for k in sorted(arrays)) != str(stored):
        raise CacheError(f"{path}: its arrays do not match its checksum")
    return arrays
