"""The import stage's output contract: a skeleton, skinned meshes, clips, attachments and props.

Everything here is plain numpy, float64 for transforms and keys (the truth), float32 / integer for
vertex data (what the GPU gets). ``validate()`` on each type is called by every stage that takes it,
so a malformed character is reported where it enters, not as a wrong pose three stages later.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np
from ..errors import CrowdError

INTERPOLATIONS = ("LINEAR", "STEP", "CUBICSPLINE")
# Sampler values as glTF (and GL) write them.
NEAREST, LINEAR = 9728, 9729
MIPMAP_FILTERS = (9984, 9985, 9986, 9987)  # {NEAREST, LINEAR}_MIPMAP_{NEAREST, LINEAR}
REPEAT, CLAMP_TO_EDGE, MIRRORED_REPEAT = 10497, 33071, 33648
WRAPS = (REPEAT, CLAMP_TO_EDGE, MIRRORED_REPEAT)
# A textured piece whose coordinates span at most this (on each axis) has them packed as unorm16 across
# their box, which keeps 1/4 texel of a 2048 texture; a wider span is drawn with float coordinates.
PACKED_UV_SPAN = 16.0
PATHS = {"translation": 3, "rotation": 4, "scale": 3}
# Morph targets (blend shapes): at most this many in one character, all its meshes' together (a face rig
# has 50 to 300; the bound keeps a hostile file's per-agent weight rows finite).
MAX_MORPHS = 1024


# Feet: the joints the foot-skate measure watches (crowd.anim.foot_skate) and the AI turns agents about
# (crowd.sim.motion), found by name, and the height above its lowest point within which one is on the ground.
FOOT_WORDS = ("foot", "ankle", "toe", "ball")
CONTACT_M = 0.03


def foot_joints(skeleton: "Skeleton") -> list[int]:
    """The joints named like a foot, an ankle, a toe or a ball, in skeleton order."""
    return [j for j, name in enumerate(skeleton.names) if any(word in name.lower() for word in FOOT_WORDS)]


class ModelError(CrowdError, ValueError):
    """A character, clip or mesh that breaks the contract. The message is one line and names the culprit."""


def _finite(name: str, a: np.ndarray) -> None:
    if not np.all(np.isfinite(a)):
        raise ModelError(f"{name} holds NaN or Inf")


def vertex_normals(pos: np.ndarray, idx: np.ndarray) -> np.ndarray:
    """Area-weighted smooth vertex normals of a triangle list (for meshes that come without them)."""
    tri = idx.reshape(-1, 3)
    face = np.cross(pos[tri[:, 1]] - pos[tri[:, 0]], pos[tri[:, 2]] - pos[tri[:, 0]])
    n = np.zeros_like(pos)
    for k in range(3):
        np.add.at(n, tri[:, k], face)
    length = np.linalg.norm(n, axis=1, keepdims=True)
    return np.where(length > 1e-12, n / np.maximum(length, 1e-12), np.array([0.0, 1.0, 0.0]))


@dataclass
class Skeleton:
    """Joints sorted parents-first; transforms are local (relative to the parent joint)."""

    names: tuple[str, ...]
    parents: np.ndarray  # int32 (J,), -1 for a root
    rest_translation: np.ndarray  # float64 (J, 3)
    rest_rotation: np.ndarray  # float64 (J, 4), xyzw
    rest_scale: np.ndarray  # float64 (J, 3)
    inverse_bind: np.ndarray  # float64 (J, 4, 4)

    @property
    def joint_count(self) -> int:
        return len(self.names)

    def index(self, name: str) -> int:
        try:
            return self.names.index(name)
        except ValueError:
            raise ModelError(f"no joint named {name!r}; joints are {', '.join(self.names)}") from None

    def validate(self) -> "Skeleton":
        j = len(self.names)
        if j == 0:
            raise ModelError("skeleton has no joints")
        if len(set(self.names)) != j:
            raise ModelError("skeleton has duplicate joint names")
        for attr, shape in (
            ("parents", (j,)),
            ("rest_translation", (j, 3)),
            ("rest_rotation", (j, 4)),
            ("rest_scale", (j, 3)),
            ("inverse_bind", (j, 4, 4)),
        ):
            a = getattr(self, attr)
            if not isinstance(a, np.ndarray) or a.shape != shape:
                raise ModelError(f"skeleton.{attr} must have shape {shape}, got {getattr(a, 'shape', type(a))}")
            _finite(f"skeleton.{attr}", a)
        zero = np.linalg.norm(self.rest_rotation, axis=-1) == 0.0
        if np.any(zero):
            raise ModelError(f"joint {self.names[int(np.argmax(zero))]!r}: rest rotation is the zero quaternion")
        for i, p in enumerate(self.parents):
            if not (-1 <= p < i):
                raise ModelError(f"joint {self.names[i]!r} has parent {p}: joints must be sorted parents-first")
        return self

    def depth(self) -> np.ndarray:
        d = np.zeros(self.joint_count, dtype=np.int32)
        for i, p in enumerate(self.parents):
            d[i] = 0 if p < 0 else d[p] + 1
        return d


@dataclass
class Channel:
    """One animated property of one joint, exactly as the source stores it.

    ``values`` is (K, C) for LINEAR and STEP and (K, 3, C) for CUBICSPLINE (in-tangent, value, out-tangent).
    """

    joint: int
    path: str
    interpolation: str
    times: np.ndarray  # float64 (K,)
    values: np.ndarray

    def validate(self, joint_count: int, where: str) -> None:
        if self.path not in PATHS:
            raise ModelError(f"{where}: unknown channel path {self.path!r}")
        if self.interpolation not in INTERPOLATIONS:
            raise ModelError(f"{where}: unknown interpolation {self.interpolation!r}")
        if not 0 <= self.joint < joint_count:
            raise ModelError(f"{where}: joint index {self.joint} out of range")
        k = self.times.shape[0] if self.times.ndim == 1 else -1
        if k < 1:
            raise ModelError(f"{where}: a channel needs at least one key")
        c = PATHS[self.path]
        want = (k, 3, c) if self.interpolation == "CUBICSPLINE" else (k, c)
        if self.values.shape != want:
            raise ModelError(f"{where}: {self.path} values have shape {self.values.shape}, expected {want}")
        _finite(f"{where} times", self.times)
        _finite(f"{where} values", self.values)
        if self.path == "rotation":
            keys = self.values[:, 1] if self.interpolation == "CUBICSPLINE" else self.values
            zero = np.linalg.norm(keys, axis=-1) == 0.0
            if np.any(zero):  # a pose with no rotation: every sampler downstream would divide by zero
                raise ModelError(f"{where}: key {int(np.argmax(zero))} is the zero quaternion")
        if k > 1 and np.any(np.diff(self.times) <= 0.0):
            raise ModelError(f"{where}: key times must increase strictly")


@dataclass
class MorphChannel:
    """The weights of some of the character's morph targets over a clip, as one glTF ``weights`` channel
    stores them (the targets of the mesh its node draws): ``values`` is (K, N) for LINEAR and STEP and
    (K, 3, N) for CUBICSPLINE (in-tangent, value, out-tangent), N = len(morphs). Weights interpolate
    linearly (no slerp), and are not clamped: glTF allows any real weight."""

    morphs: np.ndarray  # int64 (N,): indices into Character.morphs
    interpolation: str
    times: np.ndarray  # float64 (K,)
    values: np.ndarray

    path = "weights"  # (read by crowd.asset.pose.sample_channel, as a Channel's)

    def validate(self, morph_count: int, where: str) -> None:
        if self.interpolation not in INTERPOLATIONS:
            raise ModelError(f"{where}: unknown interpolation {self.interpolation!r}")
        m = np.asarray(self.morphs)
        if m.ndim != 1 or not m.size or np.any(m < 0) or np.any(m >= morph_count) or len(set(m.tolist())) != m.size:
            raise ModelError(f"{where}: morph indices {m.tolist()} must be distinct and below {morph_count}")
        k = self.times.shape[0] if self.times.ndim == 1 else -1
        if k < 1:
            raise ModelError(f"{where}: a channel needs at least one key")
        want = (k, 3, m.size) if self.interpolation == "CUBICSPLINE" else (k, m.size)
        if self.values.shape != want:
            raise ModelError(f"{where}: weights have shape {self.values.shape}, expected {want}")
        _finite(f"{where} times", self.times)
        _finite(f"{where} weights", self.values)
        if k > 1 and np.any(np.diff(self.times) <= 0.0):
            raise ModelError(f"{where}: key times must increase strictly")


@dataclass
class Clip:
    name: str
    channels: list[Channel]
    start: float  # seconds; phase 0 maps here (glTF clips may start after t = 0)
    end: float
    loop: bool
    # Phase markers in [0, 1): for locomotion, left_foot_down = 0.0 and right_foot_down = 0.5.
    markers: dict[str, float] = field(default_factory=dict)
    stride: float | None = None  # metres travelled per cycle, for locomotion clips played in place
    morph_channels: list[MorphChannel] = field(default_factory=list)  # no morph is driven by two

    @property
    def duration(self) -> float:
        return self.end - self.start

    def validate(self, skeleton: Skeleton, morph_count: int | None = None) -> "Clip":
        """Checks the clip against `skeleton`, and its morph weight channels against `morph_count`
        morph targets (None: not checked, for users of the joints alone such as the joint bake)."""
        where = f"clip {self.name!r}"
        if not np.isfinite(self.start) or not np.isfinite(self.end):
            raise ModelError(f"{where}: start/end must be finite")
        if self.end < self.start:
            raise ModelError(f"{where}: ends before it starts")
        seen = set()
        for ch in self.channels:
            ch.validate(skeleton.joint_count, f"{where}, joint {skeleton.names[ch.joint] if 0 <= ch.joint < skeleton.joint_count else ch.joint} {ch.path}")
            key = (ch.joint, ch.path)
            if key in seen:
                raise ModelError(f"{where}: two {ch.path} channels for joint {skeleton.names[ch.joint]!r}")
            seen.add(key)
        driven: set[int] = set()
        for k, ch in enumerate(self.morph_channels if morph_count is not None else ()):
            ch.validate(morph_count, f"{where}, morph weights channel {k}")
            if driven & set(ch.morphs.tolist()):
                raise ModelError(f"{where}: morph weights channel {k} drives a morph target another channel drives")
            driven |= set(ch.morphs.tolist())
        for name, phase in self.markers.items():
            if not 0.0 <= phase < 1.0:
                raise ModelError(f"{where}: marker {name!r} phase {phase} is outside [0, 1)")
        return self


@dataclass
class Texture:
    """A base-colour image as the file authored it, with its sampler.

    ``pixels`` is sRGB-encoded RGBA8 with row 0 at v = 0 (glTF puts the image's first row at the top,
    where v = 0, as GL's first uploaded row is t = 0, so no flip is needed anywhere). Textures that use
    one image share one ``pixels`` array object: the draw stage packs each image into the texture array
    once.
    """

    name: str
    pixels: np.ndarray  # uint8 (H, W, 4)
    wrap: tuple[int, int] = (REPEAT, REPEAT)  # s, t
    mag_filter: int = LINEAR
    min_filter: int = 9987  # LINEAR_MIPMAP_LINEAR: glTF leaves it to the viewer when a file says nothing

    def validate(self) -> "Texture":
        p = self.pixels
        if not isinstance(p, np.ndarray) or p.dtype != np.uint8 or p.ndim != 3 or p.shape[2] != 4 or 0 in p.shape:
            raise ModelError(f"texture {self.name!r}: pixels must be uint8 (H, W, 4), got {getattr(p, 'dtype', type(p))} {getattr(p, 'shape', '')}")
        if any(w not in WRAPS for w in self.wrap) or len(self.wrap) != 2:
            raise ModelError(f"texture {self.name!r}: wrap must be two of {WRAPS}, got {self.wrap}")
        if self.mag_filter not in (NEAREST, LINEAR) or self.min_filter not in (NEAREST, LINEAR, *MIPMAP_FILTERS):
            raise ModelError(f"texture {self.name!r}: unknown filter ({self.mag_filter}, {self.min_filter})")
        return self


@dataclass
class SkinnedMesh:
    name: str
    piece: str  # "body", "head_a", ...: pieces of one variation group are swapped per agent
    lod: int
    positions: np.ndarray  # float32 (V, 3), bind space
    normals: np.ndarray  # float32 (V, 3)
    joints: np.ndarray  # uint16 (V, 4)
    weights: np.ndarray  # float32 (V, 4), sum 1
    indices: np.ndarray  # uint32 (3T,)
    colors: np.ndarray | None = None  # float32 (V, 4) linear RGBA, or None
    base_color: tuple[float, float, float, float] = (1.0, 1.0, 1.0, 1.0)
    group: str = ""  # variation group ("head"), empty for pieces every agent wears
    # Base-colour texture: an index into Character.textures (-1: none) and the texture coordinates
    # it is sampled at, KHR_texture_transform already applied (float32 (V, 2)).
    texture: int = -1
    uvs: np.ndarray | None = None
    # Morph targets: per target, the character's morph it is (an index into Character.morphs) and its
    # per-vertex differences of position and normal, in bind space: drawn, a vertex is
    # position + sum over targets of weight * delta, before skinning (glTF).
    morph_targets: np.ndarray | None = None  # int64 (T,), distinct
    morph_positions: np.ndarray | None = None  # float32 (T, V, 3)
    morph_normals: np.ndarray | None = None  # float32 (T, V, 3), zeros where the source gives none
    unlit: bool = False  # KHR_materials_unlit: drawn in its base colour, without the sun, sky or shadows

    @property
    def triangle_count(self) -> int:
        return int(self.indices.shape[0] // 3)

    @property
    def morph_count(self) -> int:
        return 0 if self.morph_targets is None else int(self.morph_targets.shape[0])

    def validate(self, joint_count: int, texture_count: int = 0, morph_count: int = 0) -> "SkinnedMesh":
        where = f"mesh {self.name!r}"
        v = self.positions.shape[0]
        for attr, shape, dtype in (
            ("positions", (v, 3), np.float32),
            ("normals", (v, 3), np.float32),
            ("joints", (v, 4), np.uint16),
            ("weights", (v, 4), np.float32),
        ):
            a = getattr(self, attr)
            if a.shape != shape or a.dtype != dtype:
                raise ModelError(f"{where}: {attr} must be {np.dtype(dtype).name} {shape}, got {a.dtype} {a.shape}")
        if self.colors is not None and self.colors.shape != (v, 4):
            raise ModelError(f"{where}: colors must be (V, 4)")
        _check_texture(where, self.texture, self.uvs, v, texture_count)
        _finite(f"{where} positions", self.positions)
        _finite(f"{where} normals", self.normals)
        _finite(f"{where} weights", self.weights)
        if self.indices.ndim != 1 or self.indices.shape[0] % 3:
            raise ModelError(f"{where}: indices must be a flat triangle list")
        if self.indices.size and int(self.indices.max()) >= v:
            raise ModelError(f"{where}: an index points past the last vertex")
        if self.joints.size and int(self.joints.max()) >= joint_count:
            raise ModelError(f"{where}: a vertex references joint {int(self.joints.max())} of {joint_count}")
        if np.any(self.weights < 0.0) or np.any(np.abs(self.weights.sum(axis=1) - 1.0) > 1e-4):
            raise ModelError(f"{where}: weights must be non-negative and sum to 1")
        _check_morphs(where, self, v, morph_count)
        return self


def _check_morphs(where: str, mesh: "SkinnedMesh", vertices: int, morph_count: int) -> None:
    fields = (mesh.morph_targets, mesh.morph_positions, mesh.morph_normals)
    if all(f is None for f in fields):
        return
    if any(f is None for f in fields):
        raise ModelError(f"{where}: morph_targets, morph_positions and morph_normals come together")
    t = mesh.morph_targets
    if t.ndim != 1 or not t.size or np.any(t < 0) or np.any(t >= morph_count) or len(set(t.tolist())) != t.size:
        raise ModelError(f"{where}: morph targets {t.tolist()[:8]} must be distinct indices below {morph_count}")
    for attr in ("morph_positions", "morph_normals"):
        a = getattr(mesh, attr)
        if a.shape != (t.size, vertices, 3) or a.dtype != np.float32:
            raise ModelError(f"{where}: {attr} must be float32 {(t.size, vertices, 3)}, got {a.dtype} {a.shape}")
        _finite(f"{where} {attr}", a)


def _check_texture(where: str, texture: int, uvs, vertices: int, texture_count: int) -> None:
    if texture < 0:
        return
    if texture >= texture_count:
        raise ModelError(f"{where}: texture {texture} of {texture_count}")
    if not isinstance(uvs, np.ndarray) or uvs.shape != (vertices, 2) or uvs.dtype != np.float32:
        raise ModelError(f"{where}: a textured mesh needs float32 uvs (V, 2), got {getattr(uvs, 'shape', None)}")
    _finite(f"{where} uvs", uvs)


@dataclass
class RigidMesh:
    name: str
    positions: np.ndarray  # float32 (V, 3)
    normals: np.ndarray  # float32 (V, 3)
    indices: np.ndarray  # uint32 (3T,)
    colors: np.ndarray | None = None
    base_color: tuple[float, float, float, float] = (1.0, 1.0, 1.0, 1.0)
    texture: int = -1  # as SkinnedMesh
    uvs: np.ndarray | None = None
    unlit: bool = False  # as SkinnedMesh

    @property
    def triangle_count(self) -> int:
        return int(self.indices.shape[0] // 3)


@dataclass
class Attachment:
    """A rigid mesh that follows one joint: world = joint_world @ offset."""

    mesh: RigidMesh
    joint: int
    offset: np.ndarray  # float64 (4, 4)


@dataclass
class Prop:
    """A hand-held prop (weapon). ``grip`` is the grip frame in the prop's mesh space.

    The prop is placed so that its grip frame coincides with a socket joint:
    prop_world = socket_world @ inverse(grip).
    """

    mesh: RigidMesh
    grip: np.ndarray  # float64 (4, 4)
    # Coarser meshes in the same space, for LOD1, LOD2, ... of the agent holding it (the last one also
    # serves every coarser LOD): a weapon as detailed as a far agent's whole body would double its draw.
    coarser: tuple[RigidMesh, ...] = ()

    @property
    def lods(self) -> tuple[RigidMesh, ...]:
        return (self.mesh, *self.coarser)


@dataclass(frozen=True)
class MergedMesh:
    """One mesh the import made of several of the file's meshes at one LOD, to share a draw
    (crowd.asset.merge): it takes the name and piece of its first source."""

    lod: int
    piece: str
    name: str
    sources: tuple[str, ...]  # the meshes' names, in file order


@dataclass
class Character:
    name: str
    skeleton: Skeleton
    meshes: list[SkinnedMesh]
    clips: list[Clip]
    attachments: list[Attachment] = field(default_factory=list)
    props: dict[str, Prop] = field(default_factory=dict)
    sockets: dict[str, int] = field(default_factory=dict)  # socket name -> joint index
    warnings: list[str] = field(default_factory=list)  # what the import left out or approximated
    textures: list[Texture] = field(default_factory=list)  # base-colour textures the meshes index
    # Morph targets by name, across meshes (a mesh's targets and its LODs' share a name), and each one's
    # weight where no clip drives it (glTF's mesh or node default weights).
    morphs: tuple[str, ...] = ()
    morph_defaults: np.ndarray = field(default_factory=lambda: np.zeros(0))  # float64 (M,)
    # Metres from the camera where LOD1, LOD2, ... start for this character alone, ascending (LODs past
    # the last one cast shadows only); None: the global lod_distances setting, as for the built-ins.
    # crowd.asset.lod sets them for the LODs it makes, from each LOD's measured error.
    lod_distances: tuple[float, ...] | None = None
    merged: list[MergedMesh] = field(default_factory=list)  # the meshes made of several that share a draw

    @property
    def armed(self) -> bool:
        """Whether it can hold its props: it has some, and a socket joint to hold them in."""
        return bool(self.props) and bool(self.sockets)

    def clip(self, name: str) -> Clip:
        for c in self.clips:
            if c.name == name:
                return c
        raise ModelError(f"no clip named {name!r}; clips are {', '.join(c.name for c in self.clips)}")

    def validate(self) -> "Character":
        self.skeleton.validate()
        for t in self.textures:
            t.validate()
        m = len(self.morphs)
        if m > MAX_MORPHS or len(set(self.morphs)) != m or not all(isinstance(n, str) for n in self.morphs):
            raise ModelError(f"character {self.name!r}: morph names must be at most {MAX_MORPHS} distinct strings")
        if not isinstance(self.morph_defaults, np.ndarray) or self.morph_defaults.shape != (m,):
            raise ModelError(f"character {self.name!r}: morph_defaults must have shape ({m},)")
        _finite(f"character {self.name!r} morph_defaults", self.morph_defaults)
        for mesh in self.meshes:
            mesh.validate(self.skeleton.joint_count, len(self.textures), m)
        _check_lod_distances(self)
        names = [c.name for c in self.clips]
        if len(set(names)) != len(names):
            raise ModelError(f"character {self.name!r} has duplicate clip names")
        for c in self.clips:
            c.validate(self.skeleton, m)
        return self


def _check_lod_distances(character: Character) -> None:
    d = character.lod_distances
    if d is None:
        return
    top = max((m.lod for m in character.meshes), default=0)
    numbers = isinstance(d, tuple) and all(isinstance(x, (int, float)) and not isinstance(x, bool) and math.isfinite(x) and x > 0 for x in d)
    if not numbers or not 1 <= len(d) <= top or any(b <= a for a, b in zip(d, d[1:])):
        raise ModelError(f"character {character.name!r}: lod_distances must be 1 to {top} (its coarsest LOD) ascending finite metres "
                         f"above 0, got {d!r}")


def cast_weapons(characters) -> tuple[list[int], list[str]]:
    """The weapons of a crowd of `characters` (in the cast's order): every prop of every character that
    can hold them, numbered in that order. Returns each character's first weapon's number and every
    weapon's name (the prop's, after its character's where several characters are armed)."""
    armed = [c for c in characters if c.armed]
    first, names = [], []
    for c in characters:
        first.append(len(names))
        if c.armed:
            names += [name if len(armed) == 1 else f"{c.name}/{name}" for name in c.props]
    return first, names
