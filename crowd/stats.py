"""The stats of a run, headless or windowed: one JSON shape, read from the pipeline's public state.

Collecting them is not the pipeline's job (it runs frames), so it lives here, beside the one writer.
"""

from __future__ import annotations

import json
import platform
from pathlib import Path

import moderngl
import numpy as np

from .files import atomic_write_bytes
from .gl import GL_LIMITS, describe, feature_level


def percentiles(values) -> dict:
    a = np.asarray(values, np.float64)
    if a.size == 0:
        return {"p50": None, "p95": None, "max": None}
    return {"p50": round(float(np.percentile(a, 50)), 4), "p95": round(float(np.percentile(a, 95)), 4), "max": round(float(a.max()), 4)}


def _round(value, digits: int = 5):
    return None if value is None else round(float(value), digits)


def readback_wait(pipeline) -> dict | None:
    """The CPU's wait on the socket read-back (ms): max and median over the reads so far."""
    if pipeline.readback is None:
        return None
    waits = np.asarray(pipeline.readback_waits or [0.0])
    return {"max": round(float(waits.max()), 4), "median": round(float(np.median(waits)), 4)}


def weapon_stats(pipeline) -> dict:
    if pipeline.weapons is None:
        return {"enabled": False}
    return {"enabled": True, "latency_frames": pipeline.latency,
            "pose_lag_ms": pipeline.pose_lag_ms(),  # simulated time the pose trails by
            "armed": int(np.count_nonzero(pipeline.ai.armed())), "placed": pipeline.weapons.last["weapons"],
            "dropped": pipeline.weapons.last["dropped"], "drawn": pipeline.weapons.last["drawn"],  # drawn: in hand and on the ground
            "triangles": pipeline.weapons.last["triangles"],
            "gathered": pipeline.readback.last_count if pipeline.gpu_crowd is None or pipeline.gpu_crowd.sockets is None
            else pipeline.gpu_crowd.sockets.last_count, "stalls": pipeline.readback_stalls, "reads": pipeline.readback_waits.total}


def survivor_stats(survivor) -> dict | None:
    if survivor is None:
        return None
    return {"health": survivor.health, "kills": survivor.kills, "round": survivor.rounds, "round_s": round(survivor.round_time, 3),
            "best_s": round(max(survivor.best_time, survivor.round_time), 3), "blows_taken": survivor.blows,
            "position": [round(float(v), 4) for v in survivor.position],
            # Every round of the run: the ended ones, then this one (its end "playing").
            "rounds": [*survivor.history, survivor.round_record()]}


def ai_stats(p) -> dict:
    """The crowd AI: where it ran (and why not on the GPU, where "auto" fell back), its states, faults and
    notes, its think budget, and the bytes the CPU sent and read back in the last frame. A crowd on the
    GPU is read back whole here (the end of a run: never in a frame) to be checked as the numpy AI is."""
    ai = p.ai if p.gpu_crowd is None else p.gpu_crowd.store()
    on_gpu = p.gpu_crowd is not None
    return {"path": p.ai_path, "path_note": p.ai_note, "states": ai.counts(), "player_hits_taken": ai.player_hits_taken,
            "faults": ai.check(), "notes": [note for m in p.cast if m.motion is not None for note in m.motion.notes],
            # The think budget: whether this crowd uses it (the GPU's agents all think every substep), and how many do.
            "think_budget": {"on": False, "exact": ai.n} if on_gpu else {"on": ai.budgeted(), "exact": ai.exact_count()},
            **p.frame_bytes()}


def pipeline_stats(pipeline) -> dict:
    """What the pipeline did: its bake, the AI's states, pass timings, passes run, GPU bytes, weapons."""
    p = pipeline
    return {
        "agents": p.agents,
        "processor_path": p.processor.path,
        "cull_path": p.renderer.cull_path,  # gpu (compute), feedback (transform feedback: GL 4.0 to 4.2) or cpu
        "gl_features": feature_level(p.ctx, GL_LIMITS[p.config.gl]),  # the GL version whose features the stages use (the "gl" setting)
        "layers": p.processor.layer_count,
        "bake": {"fps": p.bake.fps, "precision": p.bake.precision, "interpolation": p.processor.interpolation,
                 "clips": [c.name for c in p.bake.clips],
                 "rows": p.bake.rows, "bytes": p.bake.nbytes, "compression": p.bake.compression},
        "roles": p.roles,
        # Every character of the crowd: its agents, what its bake holds, and how many of its agents the last frame drew.
        "cast": [{"name": m.name, "model": str(m.spec.model or "zombie"), "share": m.spec.share, "agents": int(count),
                  "visible": int(visible), "roles": m.roles, "clips": [c.name for c in m.bake.clips], "bytes": m.bake.nbytes,
                  "joints": m.bake.joint_count}
                 for m, count, visible in zip(p.cast, p.counts, p.renderer.last.get("cast_visible", [0] * len(p.cast)))],
        # The player's character: its health, score and round (None without one).
        "survivor": survivor_stats(p.survivor),
        "ai": ai_stats(p),
        "passes_ms": p.timer.medians(),
        # The main thread's CPU ms inside frame(), median of the last 120 frames (the frame's fixed cost where the GPU is not the bound).
        "cpu_ms": _round(float(np.median(p.cpu_ms.recent(120)))) if len(p.cpu_ms) else None,
        "passes_clock": {k: p.timer.clock[k] for k in p.timer.order},
        "passes_run": list(p.passes_run),
        "gpu_bytes": p.gpu_bytes(),
        "last_frame": dict(p.renderer.last),
        # The last frame's agents in view, drawn as meshes and as impostors (one quad each).
        "drawn": {"meshes": int(p.renderer.last["visible"]) - int(p.renderer.last["impostors"]),
                  "impostors": int(p.renderer.last["impostors"])},
        # How each base-colour texture is held ("bc1", or "rgba16f" where BC1's error is over the bound).
        "textures": [] if p.renderer.materials is None else [p.renderer.materials.storage[t] for t in sorted(p.renderer.materials.storage)],
        "weapons": weapon_stats(p),
        "weapon_error_mm": None if p.weapons is None else _round(p.weapon_error_mm()),
        "readback_wait_ms": readback_wait(p),
        # The running crowd's foot skate (crowd.anim.foot_skate), from the sampled agents' feet on the
        # socket read-back; None without a read-back (nobody armed) or before any of them walked 0.5 m.
        "foot_skate": None if p.readback is None else p.foot_skate.summary(),
        "foot_lock": p.foot_lock_state(),
    }


def collect_stats(ctx: moderngl.Context, pipeline, timings: dict[str, list], size, config, frames: int) -> dict:
    """The stats JSON of a run (headless or windowed): device, frame times, passes and the pipeline's own.
    `timings` maps "frame_period_ms" (frames back to back, as a window runs) and "frame_latency_ms"
    (one finish per frame) to their per-frame ms; each is reported as p50, p95 and max with its count,
    or None where the run did not measure it (a window cannot without stalling itself)."""
    stats = describe(ctx)
    stats.update({
        "agents": pipeline.agents,
        "frames": frames,
        "size": list(size),
        "seed": pipeline.config.seed,
        "model": ", ".join(str(m.spec.model or "zombie") for m in pipeline.cast),
        **{key: ({**percentiles(timings[key]), "frames": len(timings[key])} if timings.get(key) else None)
           for key in ("frame_period_ms", "frame_latency_ms")},
        "nan_count": pipeline.processor.nan_rows(),
        "python": platform.python_version(),
        "moderngl": moderngl.__version__,
        "warnings": [w for m in pipeline.cast for w in m.character.warnings + m.bake.warnings] + pipeline.role_notes + _occlusion_note(pipeline)
        + _texture_notes(pipeline),
    })
    stats.update(pipeline_stats(pipeline))
    return stats


def write_stats(path: Path, stats: dict) -> None:
    atomic_write_bytes(Path(path), (json.dumps(stats, indent=2) + "\n").encode())


def _texture_notes(pipeline) -> list[str]:
    """Why base-colour textures stayed RGBA16F other than their error (a driver without BC1)."""
    materials = pipeline.renderer.materials
    return list(materials.notes) if materials is not None else []


def _occlusion_note(pipeline) -> list[str]:
    """Why occlusion culling stopped, where it did (a depth that could not be copied)."""
    pyramid = pipeline.renderer.pyramid
    return [pyramid.unusable] if pyramid is not None and pyramid.unusable else []
