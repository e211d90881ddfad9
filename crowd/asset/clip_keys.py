"""Clips as keys: each authoring function of a spec sampled at SOURCE_FPS into joint channels, grounded
where the spec asks, loops closed, quantised, and keyed with the snarl (the zombie's specs by default)."""

from __future__ import annotations

import numpy as np

from .. import transforms as tf
from .mesh_builder import _quantise
from .model import Channel, Clip, MorphChannel, Skeleton
from .morph_targets import MORPH_TARGETS
from .pose_angles import _globals, _pose_to_joints
from .rig import SOCKET_JOINT, ZOMBIE_BODY, Body
from .zombie_clips import CLIP_SPECS, SNARL

SOURCE_FPS = 30  # clips are authored as keys at this rate; the bake resamples them


def _ground(skeleton: Skeleton, joints: dict[str, np.ndarray], hips_t: np.ndarray, body: Body = ZOMBIE_BODY) -> np.ndarray:
    """Lift or drop the hips so the lowest foot point rests on the ground at every key (no floating, no sinking)."""

    g = _globals(skeleton, joints, hips_t)
    # Sole points under the heel and the toe of each foot, in the foot/toe joints' frames.
    lows = []
    for side in "lr":
        heel = g[:, skeleton.index(f"foot_{side}")] @ np.array([*body.heel, 1.0])
        tip = g[:, skeleton.index(f"toe_{side}")] @ np.array([*body.tip, 1.0])
        lows += [heel[:, 1], tip[:, 1]]
    low = np.min(np.stack(lows), axis=0)
    out = hips_t.copy()
    out[:, 1] -= low
    return out


def build_clips(skeleton: Skeleton, specs=None, body: Body = ZOMBIE_BODY, snarl: bool = True) -> list[Clip]:
    """The clips of `specs` (CLIP_SPECS' shape; default the zombie's) on `skeleton`, built for `body`,
    each keying the snarl target where SNARL names it (`snarl` True)."""
    clips = []
    socket = skeleton.index(SOCKET_JOINT)
    for name, fn, duration, loop, markers, stride, grounded in CLIP_SPECS if specs is None else specs:
        count = int(round(duration * SOURCE_FPS)) + 1
        times = np.arange(count) / SOURCE_FPS
        joints, hips_t = _pose_to_joints(fn(times / duration), count, body)
        if grounded:
            hips_t = _ground(skeleton, joints, hips_t, body)
        if loop:  # close the loop exactly: the last key repeats the first
            hips_t[-1] = hips_t[0]
            for q in joints.values():
                q[-1] = q[0]
        channels = [Channel(0, "translation", "LINEAR", times.copy(), _quantise(hips_t, 1e-6))]
        for jname, q in joints.items():
            j = skeleton.index(jname)
            if j == socket:
                continue
            q = tf.align_quat_track(tf.quat_normalize(q))
            channels.append(Channel(j, "rotation", "LINEAR", times.copy(), _quantise(q, 1e-7)))
        channels.sort(key=lambda c: (c.joint, c.path))
        morph = []
        if snarl and name in SNARL:
            morph = [MorphChannel(np.array([MORPH_TARGETS.index("snarl")]), "LINEAR", times.copy(),
                                  _quantise(SNARL[name](times / duration), 1e-6)[:, None])]
        clips.append(Clip(name, channels, 0.0, float(times[-1]), loop, dict(markers), stride, morph))
    return clips
