"""Clips: each animation's channels on the skeleton's joints (keys converted into its space: folds and the
factored scale applied), its morph weight channels, loop flag, phase markers and stride, checked so the
stages can draw every pose between keys.

A ``weights`` channel becomes a ``MorphChannel`` of its clip (LINEAR, STEP or CUBICSPLINE, as stored),
over the targets of the mesh its node draws. Old exporters wrote one animation per joint: such a file's
animations are merged back into one clip.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from ... import transforms as tf
from ..model import Channel, Clip, MorphChannel, Skeleton
from ..pose import sample_clip
from .meshes import Morphs
from .reader import (MAX_COORDINATE, MAX_MORPH_WEIGHT, MAX_SCALE, ZERO_QUATERNION, Reader, crowd_extras, first_row, is_number, is_whole,
                     refuse_bad_values, show)
from .tree import Fold, Tree

LOOP_ANGLE_TOLERANCE = np.radians(2.0)  # first and last pose this close → the clip loops
LOOP_DISTANCE_TOLERANCE = 0.01
# Items whose reading costs more than their JSON (about 0.1-0.5 ms each): a game character has a few
# hundred animations and tens of thousands of channels.
MAX_ANIMATIONS = 4096
MAX_CHANNELS = 1 << 18  # channel entries of all animations together
MAX_CLIP_SECONDS = 3600.0


def _channel_targets(r: Reader, anims: list) -> list[set]:
    """The target nodes of each animation's channels, with the channels' structure checked."""
    if len(anims) > MAX_ANIMATIONS:
        r.fail(f"{len(anims):,} animations, more than the {MAX_ANIMATIONS:,} allowed")
    out, channels = [], 0
    for ai, anim in enumerate(anims):
        where = f"animation {ai}"
        if not isinstance(anim, dict):
            r.fail(f"{where} is not a JSON object")
        targets = set()
        channels += len(r.list(anim, "channels", where))
        if channels > MAX_CHANNELS:
            r.fail(f"the animations have more than the {MAX_CHANNELS:,} channels allowed")
        for ci, ch in enumerate(r.list(anim, "channels", where)):
            if not isinstance(ch, dict):
                r.fail(f"{where} channel {ci} is not a JSON object")
            target = r.obj(ch, "target", f"{where} channel {ci}")
            if target is not None:
                targets.add(r.index(target, "node", "nodes", f"{where} channel {ci} target"))
        out.append(targets)
    return out


def read_clips(r: Reader, tree: Tree, skeleton: Skeleton, new_index, folds, factor: float, morphs: Morphs,
                warn: list[str]) -> list[Clip]:
    anims = r.array("animations")
    joint_set = tree.joints
    targets = _channel_targets(r, anims)
    # Old exporters wrote one animation per joint; a set of single-node animations with disjoint
    # targets is one clip split up, so it is merged back.
    merge = len(anims) > 1 and all(len(t) == 1 for t in targets) and len(set().union(*targets)) == len(anims)

    def anim_name(i):
        name = anims[i].get("name")
        return name if isinstance(name, str) and name else None

    groups = [(Path(r.path).stem, list(range(len(anims))))] if merge else [(anim_name(i) or f"clip{i}", [i]) for i in range(len(anims))]
    if merge:
        warn.append(f"merged {len(anims)} single-joint animations (old one-animation-per-joint layout) into one clip")
    clips: list[Clip] = []
    clip_names = set()
    left_out: dict[int, tuple[set, set]] = {}  # non-joint node -> (its paths, the clips) whose channels are left out
    for name, members in groups:
        channels: dict[tuple[int, str], Channel] = {}
        morph_channels: list[MorphChannel] = []
        extras = crowd_extras(anims[members[0]])
        for ai in members:
            anim = anims[ai]
            samplers = r.list(anim, "samplers", f"animation {ai}")
            for ci, ch in enumerate(r.list(anim, "channels", f"animation {ai}")):
                where = f"animation {anim_name(ai) or ai!r} channel {ci}"
                target = ch.get("target")
                if target is None or target.get("node") is None:
                    continue
                node, path = target["node"], target.get("path")
                if path == "weights":
                    channel = _morph_channel(r, anims[ai], ch, node, morphs, where, warn)
                    if channel is not None:
                        channel = _new_morphs(channel, morph_channels, where, warn)
                    if channel is not None:
                        morph_channels.append(channel)
                    continue
                if path not in ("translation", "rotation", "scale"):
                    warn.append(f"{where}: target path {show(path)} is not a joint transform; left out")
                    continue
                if node not in joint_set:
                    paths, names = left_out.setdefault(node, (set(), set()))
                    paths.add(path)
                    names.add(name)
                    continue
                j = new_index[node]
                key = (j, path)
                if key in channels:
                    warn.append(f"{where}: second {path} channel for joint {skeleton.names[j]!r}; left out")
                    continue
                si = ch.get("sampler")
                if not is_whole(si) or not 0 <= si < len(samplers) or not isinstance(samplers[si], dict):
                    r.fail(f"{where} sampler index {show(si)} is out of range")
                sampler = samplers[si]
                interp = r.choice(sampler, "interpolation", where, ("LINEAR", "STEP", "CUBICSPLINE"), default="LINEAR")
                comps = 4 if path == "rotation" else 3
                input_index = r.index(sampler, "input", "accessors", where, required=True)
                output_index = r.index(sampler, "output", "accessors", where, required=True)
                times = r.accessor(input_index, f"key times of {where}", ("SCALAR",))[:, 0].astype(np.float64)
                values = r.accessor(output_index, f"{path} keys of {where}", ("VEC4",) if comps == 4 else ("VEC3",)).astype(np.float64)
                _check_times(r, times, f"accessor {input_index} (key times of {where})")
                k = times.shape[0]
                want = 3 * k if interp == "CUBICSPLINE" else k
                if values.shape[0] != want:
                    r.fail(f"{where}: {values.shape[0]} output values for {k} keys ({interp})")
                if interp == "CUBICSPLINE":
                    values = values.reshape(k, 3, comps)
                _check_keys(r, path, interp, times, values, f"accessor {output_index} ({path} keys of {where})")
                values = _convert_keys(path, values, interp, folds[j], factor, skeleton.parents[j] < 0)
                channels[key] = Channel(j, path, interp, times, values)
        if not channels and not morph_channels:
            warn.append(f"animation {name!r} animates no joint of the skin and no morph target; left out")
            continue
        chans = sorted(channels.values(), key=lambda c: (c.joint, c.path))
        start = min(float(c.times[0]) for c in (*chans, *morph_channels))
        end = max(float(c.times[-1]) for c in (*chans, *morph_channels))
        if end - start > MAX_CLIP_SECONDS:
            r.fail(f"animation {name!r} lasts {end - start:.3g} s, more than the {MAX_CLIP_SECONDS:g} s a clip may last")
        clip = Clip(name, chans, start, end, False, {}, None, morph_channels)
        loop = extras.get("loop")
        clip.loop = bool(loop) if isinstance(loop, bool) else _looks_looped(skeleton, clip)
        markers = extras.get("markers")
        if isinstance(markers, dict):
            if not all(is_number(v) for v in markers.values()):
                r.fail(f"animation {name!r}: extras.crowd.markers must map names to phases, got {show(markers)}")
            clip.markers = {str(k): float(v) for k, v in markers.items()}
        stride = extras.get("stride")
        if is_number(stride):
            if not 0.0 < stride <= MAX_COORDINATE:  # NaN fails this too
                r.fail(f"animation {name!r}: extras.crowd.stride must be a length from 0 to {MAX_COORDINATE:g}, got {show(stride)}")
            clip.stride = float(stride)
        base, n = clip.name, 1
        while clip.name in clip_names:
            n += 1
            clip.name = f"{base}.{n}"
        clip_names.add(clip.name)
        clips.append(clip)
    for node, (paths, names) in sorted(left_out.items()):
        warn.append(_left_out_note(r, tree, node, paths, names))
    return clips


def _left_out_note(r: Reader, tree: Tree, node: int, paths: set, clips: set) -> str:
    """One line for an animated node whose channels no joint plays (a node above a joint is a joint by
    now: crowd.asset.gltf.skins.animated_ancestors), saying whether its motion moves anything drawn."""
    name = tree.nodes[node].get("name")
    label = f"node {node}" + (f" ({name!r})" if isinstance(name, str) and name else "")
    drawn = _drawn_below(tree, node)
    moves = f"it moves {drawn}, which is drawn still" if drawn else "it moves nothing drawn"
    count = f"{len(clips)} clip{'s' if len(clips) > 1 else ''}"
    return f"{label}: its {', '.join(sorted(paths))} channels ({count}) are left out; {moves}"


def _drawn_below(tree: Tree, node: int) -> str | None:
    """The first mesh drawn with `node`'s motion, at or below it (a rigid mesh hanging on a joint, as
    crowd.asset.gltf.meshes.read_rigid draws it; a skinned mesh ignores its node), or None."""
    stack = [node]
    while stack:
        k = stack.pop()
        n = tree.nodes[k]
        if n.get("mesh") is not None and n.get("skin") is None and tree.joint_above(k) is not None:
            name = n.get("name")
            return f"mesh node {k}" + (f" ({name!r})" if isinstance(name, str) and name else "")
        stack.extend(c for c in n.get("children") or [] if is_whole(c))
    return None


def _morph_channel(r: Reader, anim: dict, ch: dict, node: int, morphs: Morphs, where: str, warn: list[str]) -> MorphChannel | None:
    """A `weights` channel: the weights of the targets of the mesh `node` draws, N a key (glTF: the
    output holds K * N values, or 3 * K * N for CUBICSPLINE, key by key)."""
    mesh_index = r.item("nodes", node).get("mesh")
    indices = morphs.of_mesh.get(mesh_index) if is_whole(mesh_index) else None
    if indices is None:
        warn.append(f"{where}: animates the morph weights of node {node}, which draws no skinned mesh with morph targets; left out")
        return None
    samplers = r.list(anim, "samplers", where)
    si = ch.get("sampler")
    if not is_whole(si) or not 0 <= si < len(samplers) or not isinstance(samplers[si], dict):
        r.fail(f"{where} sampler index {show(si)} is out of range")
    sampler = samplers[si]
    interp = r.choice(sampler, "interpolation", where, ("LINEAR", "STEP", "CUBICSPLINE"), default="LINEAR")
    input_index = r.index(sampler, "input", "accessors", where, required=True)
    output_index = r.index(sampler, "output", "accessors", where, required=True)
    times = r.accessor(input_index, f"key times of {where}", ("SCALAR",))[:, 0].astype(np.float64)
    _check_times(r, times, f"accessor {input_index} (key times of {where})")
    what = f"accessor {output_index} (morph weights of {where})"
    values = r.accessor(output_index, f"morph weights of {where}", ("SCALAR",), (5126, 5120, 5121, 5122, 5123))[:, 0].astype(np.float64)
    k, n = times.shape[0], indices.shape[0]
    want = (3 if interp == "CUBICSPLINE" else 1) * k * n
    if values.shape[0] != want:
        r.fail(f"{what}: {values.shape[0]} weights for {k} keys of {n} targets ({interp}: {want})")
    refuse_bad_values(r, values, what, "weight", MAX_MORPH_WEIGHT, "is {value:.6g}, beyond ±{limit:g}")
    values = values.reshape((k, 3, n) if interp == "CUBICSPLINE" else (k, n))
    return MorphChannel(indices.copy(), interp, times, values)


def _new_morphs(channel: MorphChannel, kept: list[MorphChannel], where: str, warn: list[str]) -> MorphChannel | None:
    """What `channel` adds to the clip's `kept` channels: the targets none of them drives. A mesh's nodes
    (its LODs, its pieces) share targets by name, and each node's channel drives them: where they say the
    same (keys, interpolation and weights), the repeat is dropped silently; where they differ, the first
    stays, with a warning."""
    fresh = np.ones(len(channel.morphs), bool)
    for other in kept:
        common, mine, theirs = np.intersect1d(channel.morphs, other.morphs, return_indices=True)
        if not len(common):
            continue
        same = (other.interpolation == channel.interpolation and np.array_equal(other.times, channel.times)
                and np.array_equal(other.values[..., theirs], channel.values[..., mine]))
        if not same:
            warn.append(f"{where}: keys morph targets another weights channel of the clip keys otherwise; the first is kept")
        fresh[mine] = False
    if fresh.all():
        return channel
    if not fresh.any():
        return None
    return MorphChannel(channel.morphs[fresh], channel.interpolation, channel.times, channel.values[..., fresh])


def _check_times(r: Reader, times: np.ndarray, what: str) -> None:
    """glTF: key times are seconds, times[0] >= 0, strictly increasing."""
    refuse_bad_values(r, times, what, "key")
    if times[0] < 0.0:
        r.fail(f"{what}: key 0 is at {times[0]:.6g} s; glTF key times start at 0 or later")
    step = np.diff(times) <= 0.0
    if np.any(step):
        k = first_row(step)
        r.fail(f"{what}: key times do not increase (key {k + 1} at {times[k + 1]:.6g} s follows {times[k]:.6g} s)")


def _check_keys(r: Reader, path: str, interp: str, times: np.ndarray, values: np.ndarray, what: str) -> None:
    """Key values (K, C), or (K, 3, C) for CUBICSPLINE, that the stages can draw."""
    refuse_bad_values(r, values, what, "key")
    keys = values[:, 1] if interp == "CUBICSPLINE" else values
    if path == "rotation":
        zero = np.linalg.norm(keys, axis=-1) < ZERO_QUATERNION
        if np.any(zero):
            r.fail(f"{what}: key {first_row(zero)} is the zero quaternion")
        if interp == "CUBICSPLINE" and len(times) > 1:
            if np.max(np.abs(values)) > MAX_SCALE:
                r.fail(f"{what}: key {first_row(np.abs(values) > MAX_SCALE)} has a value or tangent beyond ±{MAX_SCALE:g}")
            # The spline is normalised after evaluation: it must not pass through zero between keys.
            u = np.linspace(0.0, 1.0, 9)[1:-1, None, None]
            span = np.diff(times)[None, :, None]
            u2, u3 = u * u, u * u * u
            q = ((2 * u3 - 3 * u2 + 1) * values[:-1, 1] + (u3 - 2 * u2 + u) * span * values[:-1, 2]
                 + (-2 * u3 + 3 * u2) * values[1:, 1] + (u3 - u2) * span * values[1:, 0])
            low = np.linalg.norm(q, axis=-1).min(axis=0) < ZERO_QUATERNION
            if np.any(low):
                k = int(np.argmax(low))
                r.fail(f"{what}: the spline between keys {k} and {k + 1} passes through the zero quaternion")
        return
    refuse_bad_values(r, values, what, "key", MAX_COORDINATE if path == "translation" else MAX_SCALE)


def check_scale_chains(r: Reader, skeleton: Skeleton, clips: list[Clip]) -> None:
    """The largest scale each joint reaches (rest and keys, spline overshoot bounded), multiplied down
    every chain, stays within MAX_SCALE: past it a float32 skinning matrix overflows a few joints down."""
    largest = np.max(np.abs(skeleton.rest_scale), axis=1)
    for clip in clips:
        for ch in clip.channels:
            if ch.path != "scale":
                continue
            if ch.interpolation == "CUBICSPLINE":
                span = float(np.max(np.diff(ch.times))) if ch.times.shape[0] > 1 else 0.0
                peak = float(np.max(np.abs(ch.values[:, 1]))) + 0.3 * span * float(np.max(np.abs(ch.values[:, 0::2])))
            else:
                peak = float(np.max(np.abs(ch.values)))
            largest[ch.joint] = max(largest[ch.joint], peak)
    chain = np.empty_like(largest)
    for j, p in enumerate(skeleton.parents):
        chain[j] = largest[j] * (chain[p] if p >= 0 else 1.0)
        if chain[j] > MAX_SCALE:
            r.fail(f"joint {skeleton.names[j]!r}: the scales down its chain multiply to {chain[j]:.3g}, beyond {MAX_SCALE:g}")


def _convert_keys(path: str, values: np.ndarray, interp: str, fold: Fold | None, factor: float, is_root: bool) -> np.ndarray:
    if path == "rotation":
        if interp != "CUBICSPLINE":  # spline keys are normalised after evaluation, not before
            values = tf.quat_normalize(values)
        if fold is not None:
            values = _apply_channel(values, interp, lambda v, tangent: fold.rotation(v))
        return values
    if path == "translation":
        if fold is not None:
            values = _apply_channel(values, interp, lambda v, tangent: fold.translation(v, tangent))
        if not is_root and factor != 1.0:
            values = values * factor
        return values
    if fold is not None:
        values = _apply_channel(values, interp, lambda v, tangent: fold.scale(v))
    if is_root and factor != 1.0:
        values = values / factor
    return values


def _looks_looped(skeleton: Skeleton, clip: Clip) -> bool:
    if clip.duration <= 0.0:
        return False
    pose = sample_clip(skeleton, clip, np.array([0.0, 1.0]))
    dq = np.abs(np.sum(pose.rotation[0] * pose.rotation[1], axis=-1))
    angle = 2.0 * np.arccos(np.clip(dq, 0.0, 1.0))
    moved = np.linalg.norm(pose.translation[0] - pose.translation[1], axis=-1)
    # Root translation is excluded: locomotion clips with root motion still loop.
    moved[skeleton.parents < 0] = 0.0
    return bool(np.max(angle) < LOOP_ANGLE_TOLERANCE and np.max(moved) < LOOP_DISTANCE_TOLERANCE)


def _apply_channel(values: np.ndarray, interpolation: str, fn) -> np.ndarray:
    if interpolation != "CUBICSPLINE":
        return fn(values, False)
    out = values.copy()
    out[:, 1] = fn(values[:, 1], False)
    out[:, 0] = fn(values[:, 0], True)
    out[:, 2] = fn(values[:, 2], True)
    return out

