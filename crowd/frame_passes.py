"""The frame's draw, pass by pass: after the crowd's step and its processor pass, ``CrowdPipeline``
runs DRAW_PASSES in order, each where the scene needs it, timed on its clock and named in passes_run.
Each pass is a function of the pipeline (its stages, camera and crowd) and of ``FrameWork``, what one
frame's passes hand each other.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import moderngl
import numpy as np

from .agent_rows import weapon_of_agent
from .draw.readback import SocketRead
from .draw.render import FrameView
from .draw.weapons import AgentFrames


@dataclass
class FrameState:
    """What the last frame decided, kept until the next one replaces it whole."""

    index: int = -1  # the frame number (-1: none yet)
    view: FrameView | None = None  # the camera, view and light matrices and visible set every pass got
    read: SocketRead | None = None  # the socket read-back that arrived in this frame (from frame index - N)
    row_offset: int | np.ndarray = 0  # the first palette row each agent was drawn from
    agent_frames: AgentFrames | None = None  # where each agent stood, for the weapons


@dataclass
class FrameWork:
    """What one frame's passes hand each other, made anew each frame."""

    framebuffer: moderngl.Framebuffer
    index: int
    instances: object  # Instances (the numpy AI's), or the GPU AI's SimFrame
    row_offset: object  # the first palette row each agent is drawn from (crowd.draw.sync)
    read: SocketRead | None  # the socket read-back that arrived in this frame
    agent_weapon: np.ndarray | None  # each row's weapon (crowd.agent_rows.weapon_of_agent), or None: found by attach
    fallen: np.ndarray | None = None  # who is down, a flag per row (the GPU AI's facts; attach finds the numpy AI's)
    view: FrameView | None = None  # what the cull decided (cull_lod)
    agent_frames: AgentFrames | None = None  # where each agent stood, for the weapons (the numpy AI's)


def cull_lod(p, w: FrameWork) -> None:
    """The CPU path culls and packs here; the GPU path packs and uploads every agent's record and then
    dispatches the cull ("cull": its GPU time; a query around the upload would also count the CPU's
    copying while the GPU waits for it)."""
    r = p.renderer
    r.set_view_height(w.framebuffer.viewport[3])
    # The shadow cascades cover the AI's world square (crowd.draw.shadows), known without a pass over the agents.
    half, centre = p.ai.half_extent, p.ai.origin
    top = 0.0 if p.town is None else p.town.height  # (the town's roofs cast shadows into the streets)
    r.crowd_box = (np.array([centre[0] - half, 0.0, centre[1] - half]), np.array([centre[0] + half, top, centre[1] + half]))
    w.view = r.prepare(p.camera, w.instances, w.row_offset, cull_now=False, palette=p.processor.layout)
    if r.culls_on_gpu and p.rows:
        with p.timer.gpu("cull"):
            r.cull(p.processor)
        p.note_pass("cull")


def town_cull(p, w: FrameWork) -> None:
    p.town.prepare(w.view)


def attach(p, w: FrameWork) -> None:
    """Each placed weapon on its agent's socket, from the read-back's palette (crowd.draw.weapons)."""
    on_gpu, view = p.gpu_crowd is not None, w.view
    if w.agent_weapon is None:
        w.agent_weapon = weapon_of_agent(p.ai, [m.character for m in p.cast], p.survivor)
    if not on_gpu:
        w.agent_frames = AgentFrames(w.instances.position, w.instances.yaw, w.instances.scale, p.camera.eye)
        w.fallen = ~p.ai.alive() if p.survivor is None else np.append(~p.ai.alive(), False)
    gpu = p.renderer.gpu
    # (An agent drawn as its impostor alone holds its weapon in its impostor: none placed for it.)
    shown, casting = (view.visible, view.casting) if view.held is None or view.visible is None else \
        (view.visible & ~view.held, None if view.casting is None else view.casting & ~view.held[None])
    # (the GPU paths' visibility: the compute cull's buffers, or the feedback cull's texture)
    visibility = (gpu.visible, gpu.agents_buffer) if gpu is not None else \
        p.renderer.feedback.visible if p.renderer.feedback is not None else None
    synced = p.sync.synced(w.read, p.rows, w.row_offset[2] if on_gpu else None)
    p.weapons.attach(synced, w.agent_frames, w.agent_weapon, shown, visibility, casting, view.lod, fallen=w.fallen)


def clear(p, w: FrameWork) -> None:
    p.last = FrameState(w.index, w.view, w.read, w.row_offset, w.agent_frames)
    w.framebuffer.use()
    w.framebuffer.clear(*p.renderer.clear_color(), 1.0, depth=1.0)


def shadow(p, w: FrameWork) -> None:
    p.renderer.shadow_pass(w.view, p.processor)
    if p.weapons is not None and p.weapons.casts_shadows():
        p.weapons.depth_pass(w.view, p.renderer)
    if p.town is not None:
        p.town.depth_pass(w.view, p.renderer)


@dataclass(frozen=True)
class Pass:
    """One pass of the frame's draw: `run(pipeline, work)` where `needed(pipeline, work)`, timed on its
    `clock` ("cpu" or "gpu"; None: untimed and not named in passes_run)."""

    name: str
    clock: str | None
    run: Callable
    needed: Callable = lambda p, w: True


DRAW_PASSES = (
    Pass("cull_lod", "cpu", cull_lod),
    Pass("town_cull", "cpu", town_cull, lambda p, w: p.town is not None),
    Pass("attach", "cpu", attach, lambda p, w: p.weapons is not None),
    Pass("clear", None, clear),
    Pass("shadow", "gpu", shadow, lambda p, w: p.renderer.shadows),
    # the smallest impostors, before the quads (crowd.draw.splat)
    Pass("splat", "gpu", lambda p, w: p.renderer.splat_pass(w.framebuffer, w.view, p.processor),
         lambda p, w: p.renderer.splat is not None and p.renderer.draws_anything(p.rows)),
    Pass("draw", "gpu", lambda p, w: p.renderer.color_pass(w.framebuffer, w.view, p.processor), lambda p, w: p.renderer.draws_anything(p.rows)),
    Pass("weapons", "gpu", lambda p, w: p.weapons.color_pass(w.framebuffer, w.view, p.renderer),
         lambda p, w: p.weapons is not None and p.weapons.placed_any()),
    Pass("town", "gpu", lambda p, w: p.town.color_pass(w.framebuffer, w.view, p.renderer), lambda p, w: p.town is not None),
    Pass("ground", "gpu", lambda p, w: p.renderer.ground_pass(w.framebuffer, w.view)),
    # the next frame's occlusion test reads this frame's depth
    Pass("hiz", "gpu", lambda p, w: p.renderer.capture_depth(w.framebuffer, w.view), lambda p, w: p.renderer.pyramid is not None and p.rows > 0),
)
