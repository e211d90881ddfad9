"""``crowd-bench meshopt``: how long the hand-written meshopt decoder (crowd.asset.gltf.meshopt) takes.

Three things, on this machine's CPU: importing meshopt-compressed files beside the plain one (median of
runs, side by side); the decoder's throughput per codec on the files' own views; and the slowest stream
per byte the budget lets through (every group of the attribute codec at 2 bits, so each 16 bytes cost a
Python step; triangles whose every index is an explicit 5-byte varint; index sequences of 5-byte varints),
timed at a size and scaled to reader.MAX_MESHOPT_BYTES, to show how long a hostile file can keep an
import busy.
"""

from __future__ import annotations

import json
import statistics
import time
from pathlib import Path

from crowd.files import atomic_write_bytes

from .common import device_cpu


def _median_ms(fn, runs: int) -> float:
    times = []
    for _ in range(runs):
        t0 = time.perf_counter()
        fn()
        times.append((time.perf_counter() - t0) * 1e3)
    return statistics.median(times)


def _slow_attributes(size: int, stride: int = 256) -> tuple[bytes, int]:
    """A version-0 attribute stream of `size` decoded bytes in which every group is 2-bit coded."""
    count = size // stride
    block = min((8192 // stride) & ~15, 256)
    out = bytearray(b"\xa0")
    for row in range(0, count, block):
        groups = (min(count - row, block) + 15) // 16
        out += (b"\x55" * ((groups + 3) // 4) + b"\x00" * (4 * groups)) * stride
    return bytes(out + bytes(max(stride, 32))), count


def _slow_triangles(triangles: int) -> bytes:
    """A triangle stream whose every index is explicit and as long as a varint may be: code 0xff, then
    three 5-byte index deltas of 0."""
    return b"\xe1" + b"\xff" * triangles + (b"\xff" + b"\x80\x80\x80\x80\x00" * 3) * triangles + bytes(16)


def _slow_indices(count: int) -> bytes:
    """An index sequence of 5-byte varints."""
    return b"\xd1" + b"\x80\x80\x80\x80\x00" * count + bytes(4)


def run(args) -> int:
    from crowd.asset.gltf import load_character, meshopt, reader

    rows = []
    files = [Path(f) for f in args.files]
    for path in files:
        rows.append({"what": f"import {path.name}", "ms": round(_median_ms(lambda: load_character(path, merge=False), args.runs), 2)})

    for path in files:
        r = reader.Reader(path)
        for mode in meshopt.MODES:
            views = [i for i, v in enumerate(r.doc.get("bufferViews", []))
                     for ext in meshopt.EXTENSIONS if v.get("extensions", {}).get(ext, {}).get("mode") == mode]
            if not views:
                continue
            size = sum(r.item("bufferViews", i)["byteLength"] for i in views)

            def decode_all():
                fresh = reader.Reader(path)  # a new reader decodes every view again (it keeps what it decoded)
                for i in views:
                    fresh.view(i)
            ms = _median_ms(decode_all, args.runs)
            rows.append({"what": f"{path.name} {mode} views", "bytes": size, "ms": round(ms, 2), "MB_per_s": round(size / ms / 1e3, 1)})

    size = args.slow_mb << 20
    src, count = _slow_attributes(size)
    ms = _median_ms(lambda: meshopt.decode_attributes(src, count, 256, False), 1)
    rows.append({"what": "slowest attributes (2-bit groups)", "bytes": count * 256, "ms": round(ms, 1),
                 "s_at_budget": round(ms / 1e3 * reader.MAX_MESHOPT_BYTES / (count * 256), 1)})
    budget_indices = reader.MAX_MESHOPT_BYTES // reader.MESHOPT_INDEX_BYTES
    triangles = size // 64
    src = _slow_triangles(triangles)
    ms = _median_ms(lambda: meshopt.decode_triangles(src, 3 * triangles), 1)
    rows.append({"what": "slowest triangles (5-byte explicit indices)", "indices": 3 * triangles, "ms": round(ms, 1),
                 "s_at_budget": round(ms / 1e3 * budget_indices / (3 * triangles), 1)})
    src = _slow_indices(3 * triangles)
    ms = _median_ms(lambda: meshopt.decode_sequence(src, 3 * triangles), 1)
    rows.append({"what": "slowest indices (5-byte)", "indices": 3 * triangles, "ms": round(ms, 1),
                 "s_at_budget": round(ms / 1e3 * budget_indices / (3 * triangles), 1)})

    print(f"meshopt decoding on {device_cpu()}")
    for row in rows:
        print("  " + ", ".join(f"{k}: {v}" for k, v in row.items()))
    if args.json:
        atomic_write_bytes(Path(args.json), json.dumps({"cpu": device_cpu(), "rows": rows}, indent=1).encode())
    return 0


def add_parsers(sub) -> None:
    p = sub.add_parser("meshopt", help="import time of meshopt-compressed files, decoder throughput, and its slowest streams at the budget")
    p.add_argument("files", nargs="*", default=[], help=".glb/.gltf files to import and decode (e.g. the plain and compressed zombie)")
    p.add_argument("--runs", type=int, default=7, help="runs a median is taken over")
    p.add_argument("--slow-mb", type=int, default=8, help="MB of the slowest streams timed (scaled to the budget)")
    p.add_argument("--json", type=Path, help="write the rows here as JSON (atomically)")
    p.set_defaults(run=run)
