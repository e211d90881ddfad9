"""What the AI hands the frame: the processor's layers (locomotion blend and the cross-faded action, an
attack on the upper body), the render's instances, and the invariants every step keeps."""

from __future__ import annotations

import numpy as np

from ..frame import CLIP, MASK, PHASE, WEIGHT, Instances, cast_firsts
from ..spans import over_spans
from .config import ACT_ATTACK, ACT_DEATH, LAYERS, NO_ACTION, STATE_NAMES, AIError
from .locomotion import locomotion_weights
from .motion import Motion
from .workers import HEADINGS, WRITE_LAYERS

LAYER_RUN = 16_384  # agents whose layers write_layers fills at a time (1 MB: they stay in the cache)
MAX_ACTION_WEIGHT = 1000.0  # an upper-body action at full fade: 99.9 % of the upper body


class OutputsMixin:
    """CrowdAI's part that writes its outputs: layers, instances, the checks and the counts."""

    def action_fade(self, agents: np.ndarray | None = None) -> np.ndarray:
        """0..1 per agent (or per agent of `agents`): how much of the action layer shows, cross-faded in
        and, except for death, out again."""
        action = self.action if agents is None else self.action[agents]
        elapsed = self.action_time if agents is None else self.action_time[agents]
        fade_len = max(self.config.crossfade, 1e-6)
        fade_in = np.minimum(elapsed * (1.0 / fade_len), 1.0)
        kind = self._kind_of(self, agents) if agents is not None else self._kind_of(self)
        fade_out = np.minimum(np.maximum((self.action_length(action, kind) - elapsed) * (1.0 / fade_len), 0.0), 1.0)
        fade = np.minimum(fade_in, np.where(action == ACT_DEATH, 1.0, fade_out))
        return np.where(action == NO_ACTION, 0.0, fade)

    def write_layers(self, out: np.ndarray | None = None) -> np.ndarray:
        """The processor's (N, 4, 4) float32 input: idle, walk, run, action, written into `out` in place,
        or into the AI's own array (None: no copy; the workers write it in shared memory). Returns it."""
        if out is not None and (out.shape != (self.n, LAYERS, 4) or out.dtype != np.float32):
            raise AIError(f"layers must be float32 ({self.n}, {LAYERS}, 4), got {out.dtype} {out.shape}")
        ranges = self._ready_ranges() if self.n else 1
        if ranges == 1:
            target = self._layer_out if out is None else out
            self._write_layer_range(target, 0, self.n)
            return target
        self._phase(WRITE_LAYERS, ranges)
        if out is None:
            return self._layer_out
        np.copyto(out, self._layer_out)
        return out

    def _write_layer_range(self, out: np.ndarray, lo: int, hi: int) -> None:
        """Layers of agents lo..hi. Most agents play no action, so the action layer is written for the
        acting ones only. In a cast of several characters each character's block takes its own clips."""
        first = cast_firsts(self.cast)
        for k, m in enumerate(self.motions):
            a, b = max(lo, int(first[k])), min(hi, int(first[k + 1]))
            if a < b:
                self._write_locomotion(out, a, b, k, m)
        acting = lo + np.flatnonzero(self.action[lo:hi])
        if acting.size:
            action = self.action[acting]
            kind = self._kind_of(self, acting)
            fade = self.action_fade(acting)
            mask = self._upper_mask[kind]
            upper = (action == ACT_ATTACK) & (mask >= 0)
            # Whole-body actions replace locomotion as they fade in; an upper-body action leaves the legs.
            out[acting, :3, WEIGHT] *= np.where(upper, 1.0, 1.0 - fade)[:, None]
            out[acting, 3, CLIP] = self._action_clip[kind, action]
            out[acting, 3, PHASE] = np.minimum(self.action_time[acting] / self.action_length(action, kind), 1.0)
            # Upper body: weight W against the locomotion's 1 gives the share W / (W + 1) = fade.
            out[acting, 3, WEIGHT] = np.where(upper, np.minimum(fade / np.maximum(1.0 - fade, 1e-12), MAX_ACTION_WEIGHT), fade)
            out[acting, 3, MASK] = np.where(upper, mask, -1)

    def _write_locomotion(self, out: np.ndarray, lo: int, hi: int, kind: int, m: Motion) -> None:
        """The locomotion layers of agents lo..hi, all of character `kind` (Motion `m`)."""
        # The constant columns copied from a run's worth of template (4x a broadcast's speed), then the
        # phase (rounded to float32 once) and the weights (each written by the operation that makes it)
        # into their strided columns, a run of agents at a time: each column is a strided pass over its
        # run, and a run of 16,384 agents' layers (1 MB) stays in the cache for all of them, where a
        # million agents' (64 MB) went through memory once per column.
        clips = tuple(m.clip[role] for role in ("idle", "walk", "run"))
        if self._layer_template.get(kind, (None,))[0] != clips:  # the first frame, or a new bake
            template = np.zeros((LAYER_RUN, LAYERS, 4), np.float32)
            template[:, :3, CLIP] = clips
            template[:, :, MASK] = -1.0
            self._layer_template[kind] = (clips, template)
        template = self._layer_template[kind][1]
        for start in range(lo, hi, LAYER_RUN):
            run = slice(start, min(start + LAYER_RUN, hi))
            o = out[run]
            o[:] = template[: len(o)]
            phase = self.phase[run].astype(np.float32)
            for layer in range(3):
                o[:, layer, PHASE] = phase
            vx, vz = self.vx[run], self.vz[run]
            locomotion_weights(m, np.sqrt(vx * vx + vz * vz), self.walk_top[run], self.speed_factor[run],
                               out=[o[:, layer, WEIGHT] for layer in range(3)])

    def layers(self) -> np.ndarray:
        return self.write_layers(np.empty((self.n, LAYERS, 4), np.float32))

    def instances(self, extra: int = 0) -> Instances:
        """The render's input: positions, headings, scales, tints, variants (fresh arrays, kept by the
        frame; the headings' arctangents are shared out to the workers, the rest is copies, over spans of
        agents side by side: crowd.spans). With `extra` > 0 every array has that many rows after the
        crowd's, zero, for the caller to fill (the survivor's), so nothing is copied twice to append
        them; with none, the scales and tints are the AI's own arrays."""
        n, rows = self.n, self.n + int(extra)
        pos = np.empty((rows, 3))
        yaw = np.empty(rows, np.float32)
        ranges = self._ready_ranges() if self.n else 1
        if ranges > 1:
            self._phase(HEADINGS, ranges)
        heads = any(m.head_count for m in self.motions)
        scale, tint = (self.scale, self.tint) if not extra else (np.empty(rows, np.float32), np.empty((rows, 4), np.uint8))
        head = self.head if not extra or not heads else np.empty(rows, self.head.dtype)

        def fill(lo: int, hi: int) -> None:
            pos[lo:hi, 0] = self.x[lo:hi]
            pos[lo:hi, 1] = 0.0
            pos[lo:hi, 2] = self.z[lo:hi]
            if ranges > 1:
                yaw[lo:hi] = self._yaw_out[lo:hi]
            else:
                np.arctan2(self.hx[lo:hi], self.hz[lo:hi], out=yaw[lo:hi], casting="same_kind")
            if extra:
                scale[lo:hi] = self.scale[lo:hi]
                tint[lo:hi] = self.tint[lo:hi]
                if heads:
                    head[lo:hi] = self.head[lo:hi]

        over_spans(fill, n)
        if extra:
            pos[n:], yaw[n:], scale[n:], tint[n:] = 0.0, 0.0, 0.0, 0
            if heads:
                head[n:] = 0
        variant = {"head": head} if heads else {}
        return Instances(pos, yaw, scale, tint, variant, None if len(self.cast) == 1 else self.cast)

    def check(self) -> list[str]:
        """Invariants every step must keep; empty when all hold (tests, and the stats' `ai_faults`)."""
        faults = []
        if any(not np.all(np.isfinite(a)) for a in (self.x, self.z, self.vx, self.vz, self.hx, self.hz, self.phase, self.action_time)):
            faults.append("non-finite agent state")
        slack = 1e-9 * max(1.0, float(np.max(np.abs(self.origin))))
        for p, o in ((self.x, self.origin[0]), (self.z, self.origin[1])):
            if self.n and (p.min() < o - self.half_extent - slack or p.max() > o + self.half_extent + slack):
                faults.append("agent outside the world bounds")
                break
        w = self.layers()[..., WEIGHT]
        if not np.all(np.isfinite(w)) or np.any(w < 0):
            faults.append("layer weight not finite or negative")
        return faults

    def counts(self) -> dict[str, int]:
        return {name: int(np.count_nonzero(self.state == code)) for code, name in enumerate(STATE_NAMES)}
