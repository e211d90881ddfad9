"""A contact sheet of a character's clips, skinned on the CPU by the float64 reference: one row per clip,
labelled with its name, framed on the skinned poses.

It is a debugging and documentation view (``python -m bench.preview out.png``), independent of the
GPU processor, so it can show whether a clip or an import is right before anything else is built.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from pyglm import glm
import numpy as np

from crowd.anim import reference
from crowd.gl import headless_context, load_shader
from crowd.asset.model import Character


def _view_proj(aspect: float, target, distance: float, yaw: float, pitch: float) -> bytes:
    eye = glm.vec3(*target) + distance * glm.vec3(np.sin(yaw) * np.cos(pitch), np.sin(pitch), np.cos(yaw) * np.cos(pitch))
    proj = glm.perspective(glm.radians(35.0), aspect, 0.05, 100.0)
    view = glm.lookAt(eye, glm.vec3(*target), glm.vec3(0, 1, 0))
    return (proj * view).to_bytes()  # column-major, as GLSL expects


LABEL_HEIGHT = 18  # pixels of the strip above each row that names its clip


def skinned_cells(character: Character, clip_names: list[str], columns: int, meshes) -> list[list[list[np.ndarray]]]:
    """Per clip, per column, per mesh: the (triangle corner, 10) rows of position, normal and colour,
    skinned by the float64 reference. The sheet is framed on these, not on the bind-space positions:
    a character skinned to another size or place than its bind meshes still fills its cells."""
    sk = character.skeleton
    cells = []
    for name in clip_names:
        clip = character.clip(name)
        phases = np.linspace(0.0, 1.0, columns, endpoint=not clip.loop)
        skin = reference.skinning_matrices(sk, reference.sample_clip(sk, clip, phases))
        row = []
        for c in range(columns):
            parts = []
            for m in meshes:
                p = reference.skin_points(skin[c : c + 1], m.positions, m.joints, m.weights)[0]
                nrm = reference.skin_points(skin[c : c + 1] * np.array([1, 1, 1, 0]), m.normals, m.joints, m.weights)[0]
                col = m.colors if m.colors is not None else np.ones((p.shape[0], 4))
                parts.append(np.concatenate([p, nrm, col], axis=1)[m.indices])
            row.append(parts)
        cells.append(row)
    return cells


def render_sheet(character: Character, clip_names: list[str], columns: int, cell: int, out: Path, yaw: float = 0.6,
                 pieces: tuple[str, ...] = ("body", "head_a")) -> Path:
    """One row per clip, labelled with its name, `columns` poses across its length, every cell framed on
    the skinned poses of all rows (one scale for the whole sheet, so the rows compare)."""
    from PIL import Image, ImageDraw

    meshes = [m for m in character.meshes if m.lod == 0 and (m.piece in pieces or not pieces)]
    if not meshes:
        meshes = [m for m in character.meshes if m.lod == 0]
    cells = skinned_cells(character, clip_names, columns, meshes)
    points = np.concatenate([part[:, :3] for row in cells for parts in row for part in parts])
    low, high = points.min(axis=0), points.max(axis=0)
    size = float(np.max(high - low)) or 1.0
    centre = (low + high) / 2.0
    ground = np.array([[-1, 0, -1], [1, 0, -1], [1, 0, 1], [-1, 0, -1], [1, 0, 1], [-1, 0, 1]], dtype=np.float64) * size
    ground[:, 0] += centre[0]
    ground[:, 2] += centre[2]
    ground[:, 1] = low[1]
    floor = np.concatenate([ground, np.tile([0, 1, 0], (6, 1)), np.tile([0.3, 0.32, 0.3, 1], (6, 1))], axis=1)

    ctx = headless_context(330)
    prog = fbo = None
    try:
        prog = ctx.program(vertex_shader=load_shader("bench/preview.vert.glsl"), fragment_shader=load_shader("bench/preview.frag.glsl"))
        rows = len(clip_names)
        row_height = cell + LABEL_HEIGHT
        width, height = columns * cell, rows * row_height
        fbo = ctx.simple_framebuffer((width, height), samples=0)
        fbo.use()
        ctx.enable(ctx.DEPTH_TEST)
        fbo.clear(0.16, 0.18, 0.22, 1.0)
        prog["u_light_dir"].value = tuple(glm.normalize(glm.vec3(-0.4, -1.0, -0.5)))
        prog["u_view_proj"].write(_view_proj(1.0, centre, 1.7 * size, yaw, 0.25))
        for r, row in enumerate(cells):
            for c, parts in enumerate(row):
                ctx.viewport = (c * cell, (rows - 1 - r) * row_height, cell, cell)
                data = np.concatenate([*parts, floor]).astype(np.float32)
                vbo = ctx.buffer(data.tobytes())
                vao = ctx.vertex_array(prog, [(vbo, "3f 3f 4f", "in_position", "in_normal", "in_color")])
                vao.render()
                vao.release()
                vbo.release()
        img = Image.frombytes("RGB", (width, height), fbo.read(components=3)).transpose(Image.Transpose.FLIP_TOP_BOTTOM)
    finally:
        for obj in (fbo, prog):
            if obj is not None:
                obj.release()
        ctx.release()
    draw = ImageDraw.Draw(img)
    for r, name in enumerate(clip_names):
        clip = character.clip(name)
        draw.text((4, r * row_height + 3), f"{name}  ({clip.duration:.2f} s{', loops' if clip.loop else ''})", fill=(230, 230, 230))
    out = Path(out)
    out.parent.mkdir(parents=True, exist_ok=True)
    img.save(out)
    return out


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description="Render a contact sheet of a character's clips (CPU-skinned, float64).")
    parser.add_argument("out", type=Path)
    parser.add_argument("--model", type=Path, help="a .glb/.gltf (default: the built-in zombie)")
    parser.add_argument("--clips", nargs="*", help="clip names (default: all)")
    parser.add_argument("--columns", type=int, default=6)
    parser.add_argument("--cell", type=int, default=200)
    parser.add_argument("--yaw", type=float, default=0.6, help="camera yaw in radians (0 = front)")
    args = parser.parse_args(argv)
    from crowd.asset.gltf import load_character
    from crowd.asset.gltf.reader import GltfImportError
    from crowd.asset.model import ModelError

    try:
        character = load_character(args.model)
        names = args.clips or [c.name for c in character.clips]
        pieces = ("body", "head_a") if args.model is None else ()  # (the loaded zombie wears its shirt in its body piece)
        render_sheet(character, names, args.columns, args.cell, args.out, args.yaw, pieces)
    except (GltfImportError, ModelError) as exc:  # a bad file, or a --clips name it lacks: one line, no traceback
        print(f"bench.preview: {exc}", file=sys.stderr)
        return 2
    print(f"wrote {args.out}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
