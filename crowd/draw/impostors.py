"""Animated impostors: the crowd's last LOD (issue 24), a quad per agent past the impostor distance.

**The atlas** (``crowd.draw.impostor_bake.bake_atlas``, numpy, cached on disk by ``load_atlas`` there): for each clip of a character's
bake (the clips its scene's roles play, nothing else), frames at ``ImpostorSettings.rate`` (a looping
clip's at phases k / n, the last blending into the first; another's at k / (n - 1)), each seen from
``views`` directions around the up axis (view 0 looks at the agent's front) at each of ``elevations``,
rendered by the animation processor and the skinned draw (skin.vert.glsl and skin.frag.glsl with
IMPOSTOR_BAKE) with an orthographic camera into a cell of ``cell`` pixels. A cell holds the albedo before
lighting and tint with its coverage (RGBA8), and the model-space normal (octahedral, 2 x 8 bits) with
the depth toward the camera (16 bits) (RGBA8). Cells are laid out frame by frame in rows, views and
elevations across, in as many layers of a texture array as the frames need.

Each clip has one box (its cells' extent, metres at scale 1: half width, bottom, height, depth half-range),
the smallest that holds every frame from every view, found from the float64 reference palette's skinned
LOD0 vertices, so a standing clip's cells are not spent on a dying clip's span.

What is baked, and what is not (issue 24 asks to say):
- variation pieces: each group's first choice (the built-in zombie: head_a); the agent's tint is applied
  when drawn, as for its meshes. The other heads are not in the atlas; the error this costs is measured.
- morph targets: not baked (the pose only);
- weapons: not baked (each would be a variant of the whole atlas: over the 64 MB budget). An impostor holds
  its weapon as a mesh instead: each prop's coarsest mesh skinned to the socket joint alone, a piece of
  the impostor's LOD chosen per agent (``held_pieces``, group HELD_GROUP), placed by the skinned draw from
  the agent's palette row with no read-back, so the CPU places weapons only for agents drawn as meshes;
- actions (attack, hit, death): baked like locomotion; an impostor shows its heaviest layer's clip.

**The cache**: a file per (model bytes, bake, settings) under the user's cache folder, kept by crowd.cache's
rule (written atomically with a checksum of its arrays); a file that does not load or check is rebuilt,
with one line saying so.
"""

from __future__ import annotations

import hashlib
import math
from dataclasses import dataclass, field
from pathlib import Path

import moderngl
import numpy as np

from ..errors import CrowdError
from ..anim.bake import AnimationBake
from ..asset.model import Character
from ..cache import CacheError, checksum, read_arrays, write_arrays
from ..gl import GLObjects, GLStage, set_uniforms

FORMAT = 2  # the cache files' layout; a change makes every older file a miss (2: crowd.cache's checksum over every array)
MAX_ELEVATIONS = 4  # impostor.vert.glsl's u_elevation
# An impostor shorter than this on screen shows its nearest cell instead of blending four (two views by
# two frames): the blend's eight atlas fetches a fragment were most of the colour pass at 1,000,000 agents.
BLEND_PX = 24.0


class ImpostorError(CrowdError, ValueError):
    """Impostor settings or an atlas that cannot be used; the message is one line."""


@dataclass(frozen=True)
class ImpostorSettings:
    """What the atlas is baked at. The defaults come from `crowd-bench impostor` (docs/BENCHMARKS.md)."""

    # crowd-bench impostor (docs/BENCHMARKS.md, "Impostors"): the cell size hardly mattered at the switch
    # distance (a 48-pixel-tall cell is about the agent's height on a 1080-row screen at 60 m); a second
    # elevation did most, then views. These fit the demo's zombie and brute in 48 MB.
    views: int = 12  # around the up axis
    elevations: tuple = (10.0, 40.0)  # degrees above the horizon, ascending
    cell: tuple = (24, 48)  # pixels, width and height
    rate: float = 10.0  # frames per second of clip

    def validate(self) -> "ImpostorSettings":
        if not 4 <= int(self.views) <= 64:
            raise ImpostorError(f"impostor views must be 4 to 64, got {self.views}")
        e = tuple(float(x) for x in self.elevations)
        if not 1 <= len(e) <= MAX_ELEVATIONS or any(not -30.0 <= x <= 85.0 for x in e) or list(e) != sorted(set(e)):
            raise ImpostorError(f"impostor elevations must be 1 to {MAX_ELEVATIONS} distinct ascending angles of -30 to 85 degrees, got {self.elevations}")
        if len(self.cell) != 2 or any(not 8 <= int(c) <= 1024 for c in self.cell):
            raise ImpostorError(f"an impostor cell must be 8 to 1024 pixels each way, got {self.cell}")
        if not (math.isfinite(self.rate) and 1.0 <= self.rate <= 60.0):
            raise ImpostorError(f"the impostor frame rate must be 1 to 60 frames a second, got {self.rate}")
        return self

    @property
    def columns(self) -> int:
        return int(self.views) * len(self.elevations)


@dataclass
class ImpostorAtlas:
    """A character's impostors, as numpy arrays (what the cache holds)."""

    settings: ImpostorSettings
    clip_names: tuple
    clips: np.ndarray  # (C, 2, 4) float32: (first frame, frames, loop, 0), then the box (half width, bottom, height, depth half-range)
    albedo: np.ndarray  # (layers, rows * cell height, columns * cell width, 4) uint8: albedo, coverage
    normal_depth: np.ndarray  # the same shape: octahedral normal, depth high and low bytes
    rows: int  # frames a layer holds
    notes: list = field(default_factory=list)  # one line each: what loading it said (a rebuilt cache)
    bake: object = field(default=None, repr=False, compare=False)  # the AnimationBake it shows (load_atlas): a new bake needs a new atlas

    @property
    def frames(self) -> int:
        return int(self.clips[:, 0, 1].sum())

    @property
    def nbytes(self) -> int:
        return int(self.albedo.nbytes + self.normal_depth.nbytes + self.clips.nbytes)

    def validate(self) -> "ImpostorAtlas":
        s = self.settings.validate()
        c = len(self.clip_names)
        cw, ch = (int(x) for x in s.cell)
        if self.clips.shape != (c, 2, 4) or self.clips.dtype != np.float32 or not np.all(np.isfinite(self.clips)):
            raise ImpostorError(f"the atlas's clip table has shape {self.clips.shape}, not ({c}, 2, 4) finite float32")
        frames = self.clips[:, 0, 1]
        first = np.concatenate([[0], np.cumsum(frames)[:-1]])
        if np.any(frames < 1) or not np.array_equal(self.clips[:, 0, 0], first) or np.any(self.clips[:, 1, [0, 2, 3]] <= 0):
            raise ImpostorError("the atlas's clip table is not a run of frames with positive boxes")
        layers = max(1, -(-self.frames // max(self.rows, 1)))
        shape = (layers, self.rows * ch, s.columns * cw, 4)
        for name in ("albedo", "normal_depth"):
            a = getattr(self, name)
            if a.shape != shape or a.dtype != np.uint8:
                raise ImpostorError(f"the atlas's {name} has shape {a.shape} {a.dtype}, not {shape} uint8")
        return self

    def checksum(self) -> str:
        return checksum((self.clips, self.albedo, self.normal_depth))

    def cell_bounds(self) -> np.ndarray:
        """(frames, columns, 4) float32: the rectangle of each cell its covered texels lie in, with a texel
        of margin each way, as (u0, v0, u1, v1) of the cell (0 to 1): the quad is drawn over it alone, the
        clip's box's other texels being empty (a cell with nothing covered gets an empty rectangle)."""
        cw, ch = (int(x) for x in self.settings.cell)
        layers, height, width, _ = self.albedo.shape
        rows, columns = height // ch, width // cw
        covered = (self.albedo[..., 3] > 0).reshape(layers, rows, ch, columns, cw)
        across, up = covered.any(axis=2), covered.any(axis=4)  # (layers, rows, columns, cw), (layers, rows, ch, columns)
        up = up.transpose(0, 1, 3, 2)
        out = np.zeros((layers * rows, columns, 4), np.float32)
        for axis, texels, (lo, hi) in ((across, cw, (0, 2)), (up, ch, (1, 3))):
            flat = axis.reshape(layers * rows, columns, texels)
            seen = flat.any(axis=2)
            first = np.argmax(flat, axis=2)
            last = texels - 1 - np.argmax(flat[..., ::-1], axis=2)
            out[..., lo] = np.where(seen, np.maximum(first - 1, 0) / texels, 0.5)
            out[..., hi] = np.where(seen, np.minimum(last + 2, texels) / texels, 0.5)
        return out[: self.frames]


# -- baking


def clip_frames(bake: AnimationBake, rate: float) -> list[tuple[int, np.ndarray, bool]]:
    """Per clip of the bake: (frames, their phases, loops)."""
    out = []
    for c in bake.clips:
        duration = (c.frame_count - 1) / c.fps if c.fps > 0 else 0.0
        n = max(1, int(math.ceil(duration * rate - 1e-9)))
        if c.loop:
            out.append((n, np.arange(n) / n, True))
        else:
            n = max(n + 1, 2)  # the last pose too
            out.append((n, np.arange(n) / (n - 1), False))
    return out


def view_axes(azimuth: float, elevation: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(right, up, toward the camera) of the view from `azimuth` (0: the agent's front, +Z) and
    `elevation` (radians above the horizon), in the agent's frame."""
    toward = np.array([math.sin(azimuth) * math.cos(elevation), math.sin(elevation), math.cos(azimuth) * math.cos(elevation)])
    right = np.array([math.cos(azimuth), 0.0, -math.sin(azimuth)])
    return right, np.cross(toward, right), toward


def _default_meshes(character: Character) -> list:
    """LOD0 of the pieces an agent of default choices wears: the common ones and each group's first."""
    first = {}
    for m in character.meshes:
        if m.lod == 0 and m.group:
            first.setdefault(m.group, m.piece)
    return [m for m in character.meshes if m.lod == 0 and (not m.group or first[m.group] == m.piece)]


def skinned_points(character: Character, palettes: np.ndarray) -> np.ndarray:
    """(T, V, 3) float64 model-space positions of the default pieces' LOD0 vertices in each of the
    palettes (T, J, 3, 4) (linear blend skinning, as the draw does)."""
    meshes = _default_meshes(character)
    positions = np.concatenate([m.positions for m in meshes]).astype(np.float64)
    joints = np.concatenate([m.joints for m in meshes]).astype(np.int64)
    weights = np.concatenate([m.weights for m in meshes]).astype(np.float64)
    weights /= np.maximum(weights.sum(axis=1, keepdims=True), 1e-12)
    p = np.c_[positions, np.ones(len(positions))]
    out = np.zeros((len(palettes), len(positions), 3))
    for k in range(joints.shape[1]):
        m = palettes[:, joints[:, k]]  # (T, V, 3, 4)
        out += weights[None, :, k, None] * np.einsum("tvrc,vc->tvr", m, p)
    return out


def clip_boxes(points: np.ndarray, frame_clip: np.ndarray, clips: int, settings: ImpostorSettings) -> np.ndarray:
    """(C, 4) float32 boxes: per clip the half width, bottom, height and depth half-range that hold its
    frames' points from every view, plus a texel of margin all round."""
    cw, ch = (int(x) for x in settings.cell)
    boxes = np.zeros((clips, 4), np.float32)
    for c in range(clips):
        pts = points[frame_clip == c].reshape(-1, 3)
        half, lo, hi, depth = 1e-3, np.inf, -np.inf, 1e-3
        for elevation in settings.elevations:
            for v in range(settings.views):
                right, up, toward = view_axes(2.0 * math.pi * v / settings.views, math.radians(elevation))
                x, y, z = pts @ right, pts @ up, pts @ toward
                half = max(half, float(np.abs(x).max()))
                lo, hi = min(lo, float(y.min())), max(hi, float(y.max()))
                depth = max(depth, float(np.abs(z).max()))
        height = max(hi - lo, 1e-3)
        # The box fills the cell each way (its texels need not be square), with a texel of margin all
        # round, so bilinear filtering stays within the cell.
        half *= cw / (cw - 2.0)
        grow = height * (ch / (ch - 2.0) - 1.0)
        boxes[c] = (half, lo - grow / 2.0, height + grow, depth * 1.01)
    return boxes


# -- weapons held by impostors

HELD_GROUP = "held"  # the variation group of an impostor's weapon: choice 0 holds nothing, choice w + 1 the character's prop w
HELD_NONE = "held:none"  # choice 0's piece, which no LOD has


def held_pieces(character: Character, lod: int) -> list:
    """An impostor's weapons, as pieces of its character skinned to the socket joint alone (weight 1):
    each prop's coarsest mesh, placed at bind as the weapon stage places it (socket at bind times the
    inverse grip), at LOD `lod` in the group HELD_GROUP. The skinned draw then places them from the agent's
    own palette row, with no read-back: the CPU places weapons only for agents drawn as meshes."""
    from ..asset.model import SkinnedMesh

    if not character.armed:
        return []
    joint = int(next(iter(character.sockets.values())))
    socket_bind = np.linalg.inv(np.asarray(character.skeleton.inverse_bind, np.float64))[joint]
    pieces = []
    for name, prop in character.props.items():
        mesh = prop.lods[-1]
        m = socket_bind @ np.linalg.inv(np.asarray(prop.grip, np.float64))
        positions = (np.c_[mesh.positions.astype(np.float64), np.ones(len(mesh.positions))] @ m.T)[:, :3]
        normals = mesh.normals.astype(np.float64) @ np.linalg.inv(m[:3, :3])  # the inverse transpose, applied on the right
        normals /= np.maximum(np.linalg.norm(normals, axis=1, keepdims=True), 1e-12)
        v = len(positions)
        joints = np.zeros((v, 4), np.uint16)
        joints[:, 0] = joint
        weights = np.zeros((v, 4), np.float32)
        weights[:, 0] = 1.0
        pieces.append(SkinnedMesh(f"{name} (held)", f"{HELD_GROUP}:{name}", lod, positions.astype(np.float32), normals.astype(np.float32), joints,
                                  weights, mesh.indices, mesh.colors, mesh.base_color, HELD_GROUP, mesh.texture, mesh.uvs, unlit=mesh.unlit))
    return pieces


# -- the cache


def atlas_key(character: Character, bake: AnimationBake, settings: ImpostorSettings) -> str:
    """A name for the atlas of this model, these clips and these settings: a hash of everything the bake
    reads (the drawn meshes' vertices and colours, the skeleton, the baked clips' frames)."""
    h = hashlib.sha256(f"impostor atlas {FORMAT} {settings!r}".encode())
    for m in _default_meshes(character):
        for a in (m.positions, m.normals, m.joints, m.weights, m.indices, m.colors, m.uvs):
            if a is not None:
                h.update(np.ascontiguousarray(a).tobytes())
        h.update(f"{m.piece} {m.texture} {m.base_color}".encode())
    for t in character.textures:
        h.update(np.ascontiguousarray(t.pixels).tobytes())
        h.update(f"{t.wrap} {t.mag_filter} {t.min_filter}".encode())
    h.update(np.ascontiguousarray(bake.parents).tobytes())
    h.update(np.ascontiguousarray(bake.gpu_texels).tobytes())
    h.update(np.ascontiguousarray(bake.clip_table).tobytes())
    h.update(" ".join(c.name for c in bake.clips).encode())
    return h.hexdigest()[:32]


def save_atlas(path: Path, atlas: ImpostorAtlas) -> None:
    s = atlas.settings
    write_arrays(path, {"clips": atlas.clips, "albedo": atlas.albedo, "normal_depth": atlas.normal_depth, "rows": np.int64(atlas.rows),
                        "names": np.array(atlas.clip_names), "views": np.int64(s.views), "elevations": np.array(s.elevations, np.float64),
                        "cell": np.array(s.cell, np.int64), "rate": np.float64(s.rate)})


def read_atlas(path: Path) -> ImpostorAtlas:
    """The atlas a cache file holds, checked (crowd.cache's rule); ImpostorError (one line) for anything else."""
    try:
        z = read_arrays(path)
        settings = ImpostorSettings(int(z["views"]), tuple(float(x) for x in z["elevations"]), tuple(int(x) for x in z["cell"]), float(z["rate"]))
        atlas = ImpostorAtlas(settings, tuple(str(n) for n in z["names"]), z["clips"], z["albedo"], z["normal_depth"], int(z["rows"]))
    except CacheError as exc:
        raise ImpostorError(str(exc)) from None
    except ImpostorError:
        raise
    except Exception as exc:  # a checked file of some other kind: missing keys, wrong shapes
        raise ImpostorError(f"{path}: not an impostor atlas ({type(exc).__name__}: {str(exc).splitlines()[0] if str(exc) else ''})") from None
    return atlas.validate()


# -- on the GPU


class ImpostorTextures(GLStage):
    """One character's atlas on the GPU: two RGBA8 texture arrays, the clip table and each cell's covered
    rectangle, bound for impostor.vert.glsl and impostor.frag.glsl."""

    ALBEDO_UNIT, NORMAL_UNIT, CLIPS_UNIT, BOUNDS_UNIT = 8, 9, 10, 11  # after the palette (0-2), shadows (3), albedo (6) and pyramid (7)

    def __init__(self, ctx: moderngl.Context, atlas: ImpostorAtlas):
        atlas.validate()
        self.atlas = atlas
        self._objects = GLObjects()
        layers, height, width, _ = atlas.albedo.shape
        try:
            self.albedo = self._objects.add(ctx.texture_array((width, height, layers), 4, atlas.albedo.tobytes()))
            self.normal_depth = self._objects.add(ctx.texture_array((width, height, layers), 4, atlas.normal_depth.tobytes()))
            for t in (self.albedo, self.normal_depth):
                t.filter = (moderngl.LINEAR, moderngl.LINEAR)
                t.repeat_x = t.repeat_y = False
            self.clips = self._objects.add(ctx.texture((len(atlas.clip_names), 2), 4, np.ascontiguousarray(atlas.clips.transpose(1, 0, 2)).tobytes(),
                                                       dtype="f4"))
            self.clips.filter = (moderngl.NEAREST, moderngl.NEAREST)
            bounds = atlas.cell_bounds()  # (frames, columns, 4): a texel (column, frame)
            self.bounds = self._objects.add(ctx.texture((bounds.shape[1], bounds.shape[0]), 4, bounds.tobytes(), dtype="f4"))
            self.bounds.filter = (moderngl.NEAREST, moderngl.NEAREST)
        except BaseException:
            self._objects.release()
            raise
        s = atlas.settings
        elevations = np.zeros(MAX_ELEVATIONS, np.float32)
        elevations[: len(s.elevations)] = np.radians(s.elevations)
        self._uniforms = {"u_atlas_albedo": self.ALBEDO_UNIT, "u_atlas_normal_depth": self.NORMAL_UNIT, "u_impostor_clips": self.CLIPS_UNIT,
                          "u_cell_bounds": self.BOUNDS_UNIT, "u_views": int(s.views), "u_elevations": len(s.elevations), "u_columns": s.columns,
                          "u_rows": int(atlas.rows), "u_elevation": elevations.tobytes()}

    def bind(self, prog: moderngl.Program, key_offset: int) -> None:
        """The atlas on its units and its constants in `prog` (written where they changed: each character's
        impostors have programs of their own, so once)."""
        self.albedo.use(self.ALBEDO_UNIT)
        self.normal_depth.use(self.NORMAL_UNIT)
        self.clips.use(self.CLIPS_UNIT)
        self.bounds.use(self.BOUNDS_UNIT)
        set_uniforms(prog, **self._uniforms, u_key_offset=int(key_offset), u_blend_px=BLEND_PX)

    def gpu_bytes(self) -> int:
        return self._objects.gpu_bytes()

    def release(self) -> None:
        self._objects.release()
