"""Each character's share of the processor (ProcessorPart) and how it is built: its bake's textures,
and its program, or the fragment path's two, from shaders/processor*.glsl with the defines its bake,
masks, legs, morphs and the interpolation call for."""

from __future__ import annotations

import numpy as np

from . import foot_lock as lock
from ..gl import load_shader
from .bake import AnimationBake, uneven_joints
from .compress import PER_KEY
from .morph import ACTIVE_WEIGHT, MAX_MORPH_WEIGHT, MORPH_PAIRS, NOT_HELD
from .palette_reference import SLERP_FIT
from .processor_inputs import ProcessorError
from .reference import CANCELLED_NORM, REST_THRESHOLD

LAYERS_IN = 4  # processor.comp.glsl's storage binding of the layers it reads (0 to 3: the foot lock's, the far agents')

MAX_JOINTS = 256  # one compute work group of 256 invocations holds at least one whole agent
GROUP_SIZE = 256


class ProcessorPart:
    """One character's share of the processor: its bake's textures, program and foot-lock state."""

    def __init__(self, bake: AnimationBake, masks, legs, key: bool = False):
        self.bake = bake
        self.masks = masks
        self.legs = legs
        self.key = bool(key)  # an impostor key texel first (crowd.draw.impostors)
        self.morph = bake.morphs is not None  # a texel of morph pairs before an agent's joints
        self.slots = int(self.key) + int(self.morph)
        # Morph weights held from the panel: (M,) float32, -1 where not held, and whose (crowd.anim.morph.ALL_HELD,
        # NOT_HELD, or an agent's number among the character's).
        self.held = None if bake.morphs is None else np.full(bake.morphs.count, -1.0, np.float32)
        self.held_agent = NOT_HELD
        self.held_written = None  # the held weights the texture holds
        self.program = None
        self.textures: dict = {}
        self.lock_state = self.lock_motion = None
        self.quad = self.quad_vao = None
        self.locals_program = self.locals_vao = None  # the fragment path's first draw (LOCALS_PASS) and its quads
        self.quad_vertices = 0


def joint_mask(joints) -> tuple[int, ...]:
    """A bit a joint, MAX_JOINTS of them, as the processor's uint[8] uniforms read them."""
    bits = np.zeros(MAX_JOINTS, bool)
    bits[np.asarray(joints, np.int64)] = True
    return tuple(int(w) for w in np.packbits(bits, bitorder="little").view(np.uint32))


class CharacterPrograms:
    """AnimationProcessor's building of a character's textures and programs: they go into the
    processor's ownership groups (its ``_texture``), so its release frees them on every path."""

    def _make_part(self, part: ProcessorPart) -> None:
        """A character's textures and program (programs with the same source are shared)."""
        bake, jc = part.bake, part.bake.joint_count
        compressed = bake.packed is not None
        dtype = "f2" if bake.precision == "f16" else "f4"
        anim_rows = bake.gpu_texels
        t = part.textures
        t["u_anim"] = self._texture("animation", (2 * jc, anim_rows.shape[0]), 4, anim_rows, dtype)
        if bake.scale is not None:
            t["u_anim_scale"] = self._texture("animation", (jc, bake.rows), 1, bake.scale, dtype)
        if bake.residual is not None:  # (non-uniform scale: only a character that has it pays for it)
            t["u_anim_residual"] = self._texture("animation", (jc, bake.rows), 3, np.ascontiguousarray(bake.residual, np.float32), "f4")
        if compressed:
            words = bake.packed.word_texture
            t["u_keys"] = self._texture("animation", (words.shape[1], words.shape[0]), 1, words, "u4")
            headers = bake.packed.header_texture
            t["u_tracks"] = self._texture("animation", (4 * jc, headers.shape[0]), 4, headers, "u4")
        t["u_parents"] = self._texture("animation", (jc, 1), 1, bake.parents.astype(np.int32), "i4")
        t["u_clips"] = self._texture("animation", (len(bake.clips), 1), 4, bake.clip_table, "f4")
        if part.masks is not None:
            t["u_masks"] = self._texture("animation", (jc, part.masks.shape[0]), 1, part.masks, "f4")
        defines = {"LAYERS": self.layer_count, "REST_THRESHOLD": f"{REST_THRESHOLD:.1e}", "CANCELLED_NORM": f"{CANCELLED_NORM:.1e}",
                   "MAX_JOINTS": MAX_JOINTS, "ROW_SLOTS": part.slots}
        if part.key:
            defines["IMPOSTOR_KEY"] = 1
        morphs = bake.morphs
        if morphs is not None:  # the morph weight tracks (crowd.anim.morph): only where the scene moves a target
            if len(morphs.clip_rows) != len(bake.clips):
                raise ProcessorError(f"the morph bake has {len(morphs.clip_rows)} clips, the joint bake {len(bake.clips)}")
            t["u_morph_tracks"] = self._texture("morphs", (morphs.count, morphs.tracks.shape[0]), 1, morphs.tracks, "f4")
            t["u_morph_clips"] = self._texture("morphs", (len(bake.clips), 1), 2, morphs.clip_rows.astype(np.int32), "i4")
            t["u_morph_variation"] = self._texture("morphs", (morphs.count, 1), 2, morphs.variation, "f4")
            t["u_morph_held"] = self._texture("morphs", (morphs.count, 1), 1, part.held, "f4")
            part.held_written = part.held
            defines.update(MORPHS=1, MORPH_COUNT=morphs.count, MORPH_PAIRS=MORPH_PAIRS, ACTIVE_WEIGHT=f"{ACTIVE_WEIGHT!r}",
                           MAX_MORPH_WEIGHT=f"{MAX_MORPH_WEIGHT!r}")
        if bake.scale is not None:
            defines["HAS_SCALE"] = 1
        if bake.residual is not None:
            defines["HAS_RESIDUAL"] = 1
        if compressed:
            defines["COMPRESSED"] = 1
            defines["PER_KEY"] = f"{PER_KEY}u"
        if part.masks is not None:
            defines["HAS_MASKS"] = 1
        if part.legs is not None:
            defines.update(FOOT_LOCK=1, LEG_COUNT=len(part.legs), CORRECTION_EPS=f"{lock.CORRECTION_EPS:.1e}",
                           **{name: repr(float(getattr(lock, name))) for name in ("CONTACT_M", "STEP_SHIFT_M", "STEP_TWIST_RAD", "HOLD_SHIFT_M",
                                                                                  "HOLD_TWIST_RAD", "STEP_LIFT_M", "RESET_M", "RESET_RAD",
                                                                                  "MIN_FORWARD_HORIZONTAL")})
        if self.interpolation != "dq_lerp":
            defines["INTERPOLATION_QT"] = 1
        if self.interpolation == "qt_cubic":
            defines["INTERPOLATION_CUBIC"] = 1
        if self.interpolation == "qt_corrected":
            defines["INTERPOLATION_CORRECTED"] = 1
            defines["SLERP_FIT_A"] = "vec3({:.12f}, {:.12f}, {:.12f})".format(*SLERP_FIT[:3])
            defines["SLERP_FIT_B"] = "vec3({:.12f}, {:.12f}, {:.12f})".format(*SLERP_FIT[3:])
        if self.path == "compute":
            source = load_shader("processor.comp.glsl", {**defines, "LAYERS_BUFFER": LAYERS_IN})
            if source not in self._programs:
                self._programs[source] = self.ctx.compute_shader(source)
        else:
            for pass_defines in ({**defines, "LOCALS_PASS": 1}, defines):
                source = load_shader("processor.frag.glsl", pass_defines)
                if source not in self._programs:
                    self._programs[source] = self.ctx.program(vertex_shader=load_shader("processor.vert.glsl"),
                                                              geometry_shader=load_shader("processor.geom.glsl"), fragment_shader=source)
                if "LOCALS_PASS" in pass_defines:
                    part.locals_program = self._programs[source]
        part.program = self._programs[source]
        stride = part.slots + jc
        if stride > GROUP_SIZE:
            raise ProcessorError(f"{jc} joints and a morph slot need {stride} invocations an agent; a work group has {GROUP_SIZE}")
        part.uniforms = {"u_joints": jc, "u_stride": stride, "u_agents_per_group": GROUP_SIZE // stride, "u_rest_row": anim_rows.shape[0] - 1,
                         "u_rest_scale_row": bake.rest_row, "u_layer_agents_per_row": self.layer_agents_per_row}
        if bake.residual is not None:  # the joints whose scale is non-uniform somewhere: only they fetch the residual
            part.uniforms["u_residual_joints"] = joint_mask(uneven_joints(bake.residual))
        if morphs is not None:
            part.uniforms.update(u_morph_seed=morphs.seed, u_character=self.parts.index(part))
        if compressed:
            part.uniforms["u_key_width"] = words.shape[1]
        if part.legs is not None:
            part.leg_bytes = {"u_leg_joints": np.ascontiguousarray(part.legs.joints, np.int32).tobytes(),
                              "u_leg_toe": np.ascontiguousarray(part.legs.toe, np.int32).tobytes(),
                              "u_leg_forward": np.ascontiguousarray(part.legs.forward, np.float32).tobytes(),
                              "u_leg_lowest": np.ascontiguousarray(part.legs.lowest, np.float32).tobytes()}
