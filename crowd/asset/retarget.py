"""The built-in zombie's clips, retargeted to a humanoid character whose file has none (an avatar, a
character from a pack whose animations were not bought): issue 44, point 3.

A joint map first: each humanoid role (hips, spine, chest, neck, head, and per side the shoulder, upper
and lower arm, hand, upper and lower leg, foot, toe) is found by name (the common schemes: Mixamo's
"mixamorig:LeftUpLeg", the free packs' "UpperLeg.L", Blender's metarig "thigh.L", "shin.L"), then checked
by the skeleton's shape: the hips are where the two legs meet, the chest where the two arms do.

Then each frame, in float64, in model space:
- each mapped bone points where the zombie's does (its world rotation is the zombie's change from its
  bind pose, applied after turning the character's bone in its bind pose onto the zombie's: rest poses
  aligned, so a character in an A-pose plays a T-posed clip with its arms where the clip puts them);
- each mapped joint sits at its rest offset from the nearest mapped joint above it, turned with that one
  (so a foot that is a root-level IK control, as in the free packs, stays at the end of its leg);
- the hips move as the zombie's hips do, scaled by the ratio of the legs' lengths;
- each ankle goes where the zombie's is, scaled: across the ground from the leg's own root at rest, up
  from the ground; a two-bone IK bends the leg to reach it in the knee's plane (so the feet stay on the
  ground whatever the legs' proportions or rest bend, and a planted foot does not slide);
- joints not mapped keep their rest local transform.
The character's local keys are solved from those world transforms, and that clip is the truth the
bake and the float64 reference hold; its stride, root motion and foot contacts are measured from it as
any clip's are (crowd.sim.motion).
"""

from __future__ import annotations

import re

import numpy as np

from .. import transforms as tf
from ..errors import CrowdError
from .model import Channel, Clip, Skeleton
from .pose import global_matrices, rest_pose, sample_clip

FPS = 30.0  # keys a second of a retargeted clip whose source has more keys than that, or splines
SIDES = ("l", "r")
# Role -> names (lower case, separators and side removed) that mean it, in order of preference.
ALIASES = {
    "head": ("head",),
    "neck": ("neck",),
    "shoulder": ("shoulder", "clavicle", "collar"),
    "upper_arm": ("upperarm", "arm"),
    "lower_arm": ("forearm", "lowerarm", "elbow"),
    "hand": ("hand", "wrist", "fist"),
    "upper_leg": ("upleg", "upperleg", "thigh"),
    "lower_leg": ("leg", "lowerleg", "shin", "calf", "knee"),
    "foot": ("foot", "ankle"),
    "toe": ("toebase", "toe", "ball"),
}
REQUIRED = ("hips", "chest", "head", "upper_arm", "lower_arm", "upper_leg", "lower_leg", "foot")  # (a hand may be its fingers' forearm)
# The humanoid chain: each role's parent role (a role's offset and turn follow it).
PARENT_ROLE = {"spine": "hips", "chest": "spine", "neck": "chest", "head": "neck", "shoulder": "chest", "upper_arm": "shoulder",
               "lower_arm": "upper_arm", "hand": "lower_arm", "upper_leg": "hips", "lower_leg": "upper_leg", "foot": "lower_leg",
               "toe": "foot"}
# Where each role's bone points in the rest pose: toward this child role (none: the bone keeps its rest turn).
BONE_END = {"spine": "chest", "chest": "neck", "neck": "head", "shoulder": "upper_arm", "upper_arm": "lower_arm",
            "lower_arm": "hand", "upper_leg": "lower_leg", "lower_leg": "foot", "foot": "toe"}


class RetargetError(CrowdError, ValueError):
    """A character the built-in clips cannot be retargeted to; the message is one line."""


def _side_and_core(name: str) -> tuple[str | None, str]:
    """(side "l", "r" or None, the name lower-cased without its namespace, side or separators)."""
    low = name.lower().split(":")[-1].split("|")[-1]
    low = re.sub(r"^(def|org|mch)[-_.]", "", low)
    side = None
    for pattern, s in ((r"left", "l"), (r"right", "r")):
        if re.search(pattern, low):
            side, low = s, re.sub(pattern, "", low)
            break
    if side is None:
        m = re.search(r"(^|[._\-\s])([lr])($|[._\-\s]\d*$)", low)
        if m:
            side = m.group(2)
            low = low[:m.start(2)] + low[m.end(2):]
    return side, re.sub(r"[^a-z0-9]", "", low)


def joint_map(skeleton: Skeleton) -> tuple[dict[str, int], str]:
    """Role ("hips", "upper_leg.l", ...) -> joint index, and the naming scheme recognised. Roles that
    cannot be found are absent (the caller checks REQUIRED)."""
    found: dict[str, int] = {}
    parsed = [_side_and_core(n) for n in skeleton.names]
    for role, aliases in ALIASES.items():
        sides = SIDES if role not in ("head", "neck") else (None,)
        for side in sides:
            key = role if side is None else f"{role}.{side}"
            for alias in aliases:
                hit = next((j for j, (s, core) in enumerate(parsed) if s == side and core == alias), None)
                if hit is not None:
                    found[key] = hit
                    break
    parents = skeleton.parents

    def chain(j):
        out = []
        while j >= 0:
            out.append(j)
            j = int(parents[j])
        return out

    def meet(a, b):
        above = set(chain(a))
        return next((j for j in chain(b) if j in above), None)

    if "upper_leg.l" in found and "upper_leg.r" in found:
        hips = meet(found["upper_leg.l"], found["upper_leg.r"])
        if hips is not None:
            found["hips"] = hips
    arms = [found.get(f"shoulder.{s}", found.get(f"upper_arm.{s}")) for s in SIDES]
    if None not in arms:
        chest = meet(*arms)
        if chest is not None and "hips" in found and chest != found["hips"] and found["hips"] in chain(chest):
            found["chest"] = chest
            below = [j for j in chain(chest) if j != chest]
            spine = next((j for j in below if int(parents[j]) == found["hips"]), None)
            found["spine"] = chest if spine is None else spine
    if "head" in found and "chest" in found and "neck" not in found:
        path = [j for j in chain(found["head"])[1:] if j != found["chest"] and found["chest"] in chain(j)]
        found["neck"] = path[-1] if path else found["chest"]
    names = " ".join(skeleton.names).lower()
    scheme = ("Mixamo" if "mixamorig" in names else "the free packs' (UpperLeg.L)" if "upperleg" in names
              else "Blender's metarig" if "thigh" in names and "shin" in names else "matched by name")
    return found, scheme


def _missing(found: dict[str, int]) -> list[str]:
    out = []
    for role in REQUIRED:
        keys = [f"{role}.{s}" for s in SIDES] if role not in ("hips", "chest", "head") else [role]
        out += [k.replace(".l", " left").replace(".r", " right").replace("_", " ") for k in keys if k not in found]
    return out


def retarget_clips(target: Skeleton, source: Skeleton, clips: list[Clip], where: str) -> tuple[list[Clip], str]:
    """`clips` of the `source` skeleton (the built-in zombie's) retargeted to `target`, and one line
    saying how. RetargetError naming the roles it lacks for a skeleton that is not a humanoid."""
    tmap, scheme = joint_map(target)
    smap, _ = joint_map(source)
    missing = _missing(tmap)
    if missing:
        raise RetargetError(f"{where}: no clips, and the built-in clips cannot be retargeted to it: no joint found for "
                            f"{', '.join(missing[:6])}{', ...' if len(missing) > 6 else ''}")
    roles = [r for r in _order() if r in tmap and r in smap]
    t_rest, s_rest = _bind_pose(target), _bind_pose(source)
    ratio = _leg_length(tmap, t_rest) / max(_leg_length(smap, s_rest), 1e-9)
    ground_t, ground_s = (float(np.mean([rest[m[f"foot.{side}"], 1, 3] for side in SIDES])) for m, rest in ((tmap, t_rest), (smap, s_rest)))
    align = {r: _align(r, tmap, smap, t_rest, s_rest) for r in roles}
    out = []
    for clip in clips:
        phases = _key_phases(clip)
        frames = len(phases)
        s_world = global_matrices(source, sample_clip(source, clip, phases))  # (F, J, 4, 4)
        world = np.empty((frames, len(roles), 4, 4))
        at = {}
        for k, role in enumerate(roles):
            tj, sj = tmap[role], smap[role]
            turn = s_world[:, sj, :3, :3] @ np.linalg.inv(s_rest[sj, :3, :3]) @ align[role] @ t_rest[tj, :3, :3]
            if role == "hips":
                place = t_rest[tj, :3, 3] + (s_world[:, sj, :3, 3] - s_rest[sj, :3, 3]) * ratio
            else:
                up = at[_parent_role(role, roles)]
                pj = tmap[_parent_role(role, roles)]
                offset = np.linalg.inv(t_rest[pj, :3, :3]) @ (t_rest[tj, :3, 3] - t_rest[pj, :3, 3])
                place = world[:, up, :3, 3] + np.einsum("fij,j->fi", world[:, up, :3, :3], offset)
            world[:, k, :3, :3], world[:, k, :3, 3] = turn, place
            world[:, k, 3] = (0.0, 0.0, 0.0, 1.0)
            at[role] = k
        for side in SIDES:  # each ankle where the zombie's is, scaled from the ground up: a two-bone IK per leg
            # (Across the ground, from the leg's own root at rest: a rig whose legs hang elsewhere from its hips
            # keeps its stance; up, from the ground.)
            ankle_s = s_world[:, smap[f"foot.{side}"], :3, 3]
            root_s, root_t = s_rest[smap[f"upper_leg.{side}"], :3, 3], t_rest[tmap[f"upper_leg.{side}"], :3, 3]
            want = root_t + (ankle_s - root_s) * ratio
            want[:, 1] = ground_t + (ankle_s[:, 1] - ground_s) * ratio
            _reach(world, at, side, want, tmap, t_rest)
        locals_ = _locals(target, {tmap[r]: world[:, at[r]] for r in roles}, frames)
        times = clip.start + phases * clip.duration
        channels = []
        for j in range(target.joint_count):
            t, q, _, _ = tf.mat4_decompose(locals_[:, j])
            channels.append(Channel(j, "rotation", "LINEAR", times.copy(), _aligned(q)))
            channels.append(Channel(j, "translation", "LINEAR", times.copy(), t))
        # (No stride: the crowd measures it from the retargeted clip's own planted feet, as for any clip.)
        out.append(Clip(clip.name, channels, clip.start, clip.end, clip.loop, dict(clip.markers), None))
    mapped = len([r for r in tmap if r in smap])
    line = (f"no clips: the built-in zombie's {len(out)} clips retargeted to it (joint map: {scheme} names, {mapped} roles mapped; "
            f"legs {ratio:.3g} times the zombie's)")
    return out, line


def _reach(world: np.ndarray, at: dict, side: str, want: np.ndarray, tmap: dict, t_rest: np.ndarray) -> None:
    """The leg of `side` bent so that its ankle reaches `want` (F, 3), in place in `world`: the thigh and
    shin keep their rest lengths and the plane the knee bends in (the aligned pose's), the hip stays, and
    the foot keeps its world rotation (the zombie's). A point out of reach is reached as far as the leg goes."""
    hip, knee, ankle = (at[f"{r}.{side}"] for r in ("upper_leg", "lower_leg", "foot"))
    l1 = float(np.linalg.norm(t_rest[tmap[f"lower_leg.{side}"], :3, 3] - t_rest[tmap[f"upper_leg.{side}"], :3, 3]))
    l2 = float(np.linalg.norm(t_rest[tmap[f"foot.{side}"], :3, 3] - t_rest[tmap[f"lower_leg.{side}"], :3, 3]))
    a, k0, f0 = world[:, hip, :3, 3], world[:, knee, :3, 3], world[:, ankle, :3, 3]
    d = want - a
    dist = np.clip(np.linalg.norm(d, axis=1), abs(l1 - l2) + 1e-9, l1 + l2 - 1e-9)
    u = d / np.maximum(np.linalg.norm(d, axis=1, keepdims=True), 1e-12)
    v = (k0 - a) - np.sum((k0 - a) * u, axis=1, keepdims=True) * u  # toward the knee, square to the hip-ankle line
    v /= np.maximum(np.linalg.norm(v, axis=1, keepdims=True), 1e-12)
    cos = np.clip((l1 * l1 + dist * dist - l2 * l2) / (2.0 * l1 * dist), -1.0, 1.0)[:, None]
    k = a + l1 * (cos * u + np.sqrt(1.0 - cos * cos) * v)
    f = a + u * dist[:, None]
    for j, old_from, old_to, new_from, new_to in ((hip, a, k0, a, k), (knee, k0, f0, k, f)):
        turn = _turns(old_to - old_from, new_to - new_from)
        world[:, j, :3, :3] = turn @ world[:, j, :3, :3]
        world[:, j, :3, 3] = new_from
    world[:, ankle, :3, 3] = f


def _turns(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """(F, 3, 3) rotations taking each direction of `a` onto `b` by the shortest arc (half a turn about
    an axis square to `a` where they are opposite)."""
    a = a / np.maximum(np.linalg.norm(a, axis=1, keepdims=True), 1e-12)
    b = b / np.maximum(np.linalg.norm(b, axis=1, keepdims=True), 1e-12)
    axis = np.cross(a, b)
    s, c = np.linalg.norm(axis, axis=1), np.clip(np.sum(a * b, axis=1), -1.0, 1.0)
    opposite = (s < 1e-12) & (c < 0.0)
    if np.any(opposite):
        other = np.where(np.abs(a[:, :1]) < 0.9, [[1.0, 0.0, 0.0]], [[0.0, 1.0, 0.0]])
        axis = np.where(opposite[:, None], np.cross(a, other), axis)
        s = np.where(opposite, np.linalg.norm(axis, axis=1), s)
    axis = axis / np.maximum(s, 1e-15)[:, None]
    s = np.where(opposite, 0.0, s)  # (sin of half a turn)
    x, y, z = axis[:, 0], axis[:, 1], axis[:, 2]
    one = 1.0 - c
    out = np.empty((len(a), 3, 3))
    out[:, 0] = np.stack([c + x * x * one, x * y * one - z * s, x * z * one + y * s], 1)
    out[:, 1] = np.stack([y * x * one + z * s, c + y * y * one, y * z * one - x * s], 1)
    out[:, 2] = np.stack([z * x * one - y * s, z * y * one + x * s, c + z * z * one], 1)
    return out


def _bind_pose(skeleton: Skeleton) -> np.ndarray:
    """Each joint's model-space transform (J, 4, 4) in the pose the meshes were bound in (the inverse of
    its inverse bind, its rotation made orthonormal): the pose a character was modelled in, which a file's
    node rest pose need not be (the free packs export theirs with the legs bent toward their IK poles).
    A joint without an inverse bind of its own (the identity: an animated node made a joint) keeps its rest."""
    rest = global_matrices(skeleton, rest_pose(skeleton))[0]
    ibm = np.asarray(skeleton.inverse_bind, np.float64)
    out = rest.copy()
    for j in range(skeleton.joint_count):
        if np.allclose(ibm[j], np.eye(4), atol=1e-12):
            continue
        bind = np.linalg.inv(ibm[j])
        u, _, vt = np.linalg.svd(bind[:3, :3])
        out[j, :3, :3] = u @ vt
        out[j, :3, 3] = bind[:3, 3]
    return out


def _key_phases(clip: Clip) -> np.ndarray:
    """Where the retargeted clip is keyed: at the source's own key times (so a rig of the same shape gets
    the source's keys back), or at FPS where the source has more keys than that or none."""
    times = np.unique(np.concatenate([np.asarray(ch.times, np.float64) for ch in clip.channels] + [np.array([clip.start, clip.end])]))
    times = times[(times >= clip.start) & (times <= clip.end)]
    if clip.duration <= 0.0:
        return np.zeros(1)
    if len(times) > clip.duration * FPS + 2 or any(ch.interpolation == "CUBICSPLINE" for ch in clip.channels):
        return np.linspace(0.0, 1.0, max(int(np.ceil(clip.duration * FPS - 1e-9)), 1) + 1)
    return (times - clip.start) / clip.duration


def _leg_length(found: dict[str, int], rest: np.ndarray) -> float:
    """Metres from each hip joint to its knee and on to its ankle in the rest pose, the two legs' mean:
    how far the hips stand from the ground, whatever the joint the rig calls its hips."""
    total = 0.0
    for side in SIDES:
        chain = [found[f"{r}.{side}"] for r in ("upper_leg", "lower_leg", "foot")]
        total += sum(float(np.linalg.norm(rest[b, :3, 3] - rest[a, :3, 3])) for a, b in zip(chain, chain[1:]))
    return total / 2.0


def _order() -> list[str]:
    """Every role, each after its parent role."""
    out = ["hips", "spine", "chest", "neck", "head"]
    for side in SIDES:
        out += [f"{r}.{side}" for r in ("shoulder", "upper_arm", "lower_arm", "hand", "upper_leg", "lower_leg", "foot", "toe")]
    return out


def _parent_role(role: str, roles: list[str]) -> str:
    """The nearest role above `role` that both skeletons have."""
    base, _, side = role.partition(".")
    while True:
        base = PARENT_ROLE[base]
        key = base if base in ("hips", "spine", "chest", "neck", "head") else f"{base}.{side}"
        if key in roles:
            return key


def _align(role: str, tmap, smap, t_rest, s_rest) -> np.ndarray:
    """The rotation (model space) taking the character's rest bone of `role` onto the zombie's."""
    base, _, side = role.partition(".")
    end = BONE_END.get(base)
    if end is None:
        return np.eye(3)
    end_key = end if end in ("spine", "chest", "neck", "head") else f"{end}.{side}"
    if end_key not in tmap or end_key not in smap:
        return np.eye(3)
    a = t_rest[tmap[end_key], :3, 3] - t_rest[tmap[role], :3, 3]
    b = s_rest[smap[end_key], :3, 3] - s_rest[smap[role], :3, 3]
    if np.linalg.norm(a) < 1e-9 or np.linalg.norm(b) < 1e-9:
        return np.eye(3)
    return _turns(a[None], b[None])[0]


def _locals(skeleton: Skeleton, placed: dict[int, np.ndarray], frames: int) -> np.ndarray:
    """Local matrices (F, J, 4, 4) whose chain puts each joint of `placed` at its world transform; the
    others keep their rest local transform."""
    rest = rest_pose(skeleton).matrices()[0]
    world = np.empty((frames, skeleton.joint_count, 4, 4))
    local = np.empty_like(world)
    for j, p in enumerate(skeleton.parents):
        if j in placed:
            world[:, j] = placed[j]
            local[:, j] = placed[j] if p < 0 else np.linalg.inv(world[:, p]) @ placed[j]
        else:
            local[:, j] = rest[j]
            world[:, j] = rest[j] if p < 0 else world[:, p] @ rest[j]
    return local


def _aligned(q: np.ndarray) -> np.ndarray:
    """Quaternion keys with each sign chosen nearest the previous key's."""
    q = tf.quat_normalize(q).copy()
    for k in range(1, len(q)):
        if np.dot(q[k], q[k - 1]) < 0.0:
            q[k] = -q[k]
    return q
