"""KHR_draco_mesh_compression: a primitive's attributes and indices decoded by DracoPy (Google's Draco
decoder, the optional extra ``crowd[draco]``), handed to the reader as its accessors' elements, so every
check an uncompressed accessor gets (counts, types, values, budgets) holds for the decoded data too.

Decoding is Draco's: written by hand it would be thousands of lines of entropy coding that are not the
point of this project, and DracoPy ships wheels for Linux, macOS and Windows (measured: docs/GUIDE.md).
"""

from __future__ import annotations

import numpy as np

from .reader import DRACO, Reader, is_whole, show


def decode_primitive(r: Reader, prim: dict, label: str) -> None:
    """Where `prim` is Draco-compressed: its data decoded into ``r.decoded`` for the accessors its
    attributes and indices name (a file's uncompressed fallback, if any, is not read)."""
    extensions = prim.get("extensions")
    ext = extensions.get(DRACO) if isinstance(extensions, dict) else None
    if ext is None:
        return
    where = f"{label} {DRACO}"
    if not isinstance(ext, dict):
        r.fail(f"{where} is not a JSON object")
    try:
        import DracoPy
    except ImportError:
        r.fail(f"{label} is Draco-compressed ({DRACO}): install the optional extra with pip install 'crowd[draco]' (DracoPy)")
    data, start, length, _ = r.view(r.index(ext, "bufferView", "bufferViews", where, required=True))
    names = r.obj(ext, "attributes", where)
    if not names:
        r.fail(f"{where} names no attributes")
    attributes = r.obj(prim, "attributes", label) or {}
    if prim.get("indices") is None:
        r.fail(f"{where}: a compressed primitive needs an indices accessor for the triangles Draco decodes")
    try:
        mesh = DracoPy.decode(bytes(data[start:start + length]))
    except Exception as exc:  # DracoPy raises its own types, and ValueError, for data that is not Draco's
        r.fail(f"{where}: the Draco data does not decode ({type(exc).__name__}: {str(exc)[:80]})")
    faces = getattr(mesh, "faces", None)
    if faces is None:
        r.fail(f"{where}: the Draco data is a point cloud, not triangles")
    by_id = {a["unique_id"]: a for a in mesh.attributes}
    for semantic, uid in names.items():
        if not is_whole(uid) or uid not in by_id:
            r.fail(f"{where}: attribute {semantic} names Draco attribute {show(uid)}, which the data does not hold")
        accessor = attributes.get(semantic)
        if accessor is None:
            r.fail(f"{where} compresses {semantic}, which the primitive's attributes do not name")
        values = np.asarray(by_id[uid]["data"])
        r.decoded[accessor] = values.reshape(len(values), -1)
    r.decoded[prim["indices"]] = np.asarray(faces).reshape(-1, 1)
