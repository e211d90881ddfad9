"""The cull of any GL 3.3 context, in numpy: each agent's sphere against the view and each shadow cascade's
box, its LOD (one coarser for shadows; the fade band past a switch listed at both LODs), and its entries in
the lists of crowd.draw.cull_lists, uploaded per (pass, list) into a buffer of its own (GL 3.3 draws have no
baseInstance). The same decisions as the compute cull (shaders/cull.comp.glsl, shaders/lod_pick.glsl), in
float64 but for the fade's progress, which is worked out in float32 as the GPU does.
"""

from __future__ import annotations

from dataclasses import dataclass

import moderngl
import numpy as np

from ..frame import Instances
from ..gl import GLObjects, GLStage
from ..spans import over_spans
from .cull_lists import NO_FADE, ListPlan, entries
from .gpu_cull import CullCharacter


def sphere_visible(planes: np.ndarray, centers: np.ndarray, radii: np.ndarray, reach: float | None = None, dist: np.ndarray | None = None) -> np.ndarray:
    """(N,) whether each sphere (`centers` (N, 3), `radii` (N,)) reaches inside all `planes` (and, with
    `reach`, starts within `reach` of the eye: `dist` - radius <= reach). A plane at a time over columns,
    over spans of agents side by side (crowd.spans): the (N, 3) x (3, 6) product and its (N, 6) test took
    23 ms a call at 100,000 agents in the CPU path's frame on the dev container, three calls a frame."""
    out = np.empty(len(centers), bool)

    def test(lo: int, hi: int) -> None:
        c, low = centers[lo:hi], -radii[lo:hi]
        inside = out[lo:hi]
        inside[:] = True
        d = np.empty(hi - lo)
        for a, b, z, w in planes:
            np.multiply(c[:, 0], a, out=d)
            d += c[:, 1] * b
            d += c[:, 2] * z
            d += w
            inside &= d >= low
        if reach is not None:
            inside &= dist[lo:hi] + low <= reach

    over_spans(test, len(centers))
    return out


@dataclass(frozen=True)
class CpuPicks:
    """What the numpy cull decided for one frame: per agent whether the view shows it, each cascade's
    volume holds it, the LOD it is drawn at, and whether it is drawn as its impostor alone (which holds its
    weapon); and per (pass, draw) how many instances it draws."""

    visible: np.ndarray  # bool (N,)
    casting: np.ndarray | None  # bool (cascades, N), None without shadows
    lod: np.ndarray  # int64 (N,)
    held: np.ndarray  # bool (N,)
    counts: np.ndarray  # int64 (1 + cascades, draws)
    cast_visible: list[int]  # agents shown per character
    impostors: int  # agents shown as their impostor


class CpuCull(GLStage):
    """Owns the entry buffer of each (pass, list)."""

    def __init__(self, ctx: moderngl.Context, plan: ListPlan, characters: list[CullCharacter], shadow_cascades: int, group_names: list[str]):
        self._objects = GLObjects()
        self.ctx = ctx
        self.plan = plan
        self.characters = list(characters)
        self.cascades = int(shadow_cascades)
        self.group_names = list(group_names)
        self.lod_fade = 0.0
        self.buffers = [[self._objects.add(ctx.buffer(reserve=4)) for _ in plan.keys] for _ in range(1 + self.cascades)]
        tables = [plan.table(c) for c in range(len(characters))]
        self._columns = np.array([t.shape[1] for t in tables], np.int64)
        self._table_first = np.concatenate([[0], np.cumsum([t.size for t in tables])[:-1]]).astype(np.int64)
        self._table = np.concatenate([t.ravel() for t in tables])
        self._group_first = np.array([plan.group_columns(c) for c in range(len(characters))], np.int64).reshape(len(characters), plan.groups)

    def set_characters(self, characters: list[CullCharacter]) -> None:
        """The characters' bounds, LOD starts and impostor distances, read each frame."""
        self.characters = list(characters)

    def buffer(self, draw: int, cascade: int | None = None) -> moderngl.Buffer:
        """The entries draw `draw` reads in the view's pass or in `cascade`'s."""
        return self.buffers[0 if cascade is None else 1 + cascade][int(self.plan.draw_list[draw])]

    def run(self, instances: Instances, eye: np.ndarray, planes: np.ndarray, culling: bool, shadow_planes=None, reach=None) -> CpuPicks:
        """Cull `instances` (camera `eye`) against the view's `planes` and, with shadows, each cascade's
        (`shadow_planes` (cascades, 6, 4), `reach` (cascades,)), and upload every list."""
        n = len(instances)
        counts = instances.counts()
        kind = np.repeat(np.arange(len(counts), dtype=np.int64), counts)
        bounds = np.array([c.bound for c in self.characters], np.float64)
        impostor_start = np.array([c.impostor_start for c in self.characters], np.float64)
        top = np.asarray(self.plan.mesh_lods, np.int64) - 1
        # Each agent's bounding sphere (camera-relative, float64), its distance, the LOD starts it has passed
        # and its LOD: over spans of agents side by side (crowd.spans), a character's block at a time.
        centers, radii, dist = np.empty((n, 3)), np.empty(n), np.empty(n)
        passed, last_start = np.empty(n, np.int64), np.empty(n)
        firsts = np.concatenate([[0], np.cumsum(counts)]).astype(np.int64)
        for c, character in enumerate(self.characters):
            starts = np.asarray(character.lod_starts, np.float64)
            bound = bounds[c]

            def place(lo: int, hi: int) -> None:
                scale = instances.scale[lo:hi].astype(np.float64)
                cen = centers[lo:hi]
                for axis in range(3):
                    np.subtract(instances.position[lo:hi, axis], eye[axis], out=cen[:, axis])
                    cen[:, axis] += bound[axis] * scale
                np.multiply(bound[3], scale, out=radii[lo:hi])
                np.sqrt(cen[:, 0] * cen[:, 0] + cen[:, 1] * cen[:, 1] + cen[:, 2] * cen[:, 2], out=dist[lo:hi])
                k = np.searchsorted(starts, dist[lo:hi], side="right")
                passed[lo:hi] = k
                last_start[lo:hi] = np.concatenate([[-1.0], starts])[k]

            over_spans(lambda lo, hi: place(firsts[c] + lo, firsts[c] + hi), int(counts[c]))
        as_impostor = dist >= impostor_start[kind]
        mesh_lod = np.minimum(passed, top[kind])
        lod = np.where(as_impostor, top[kind] + 1, mesh_lod)
        visible = sphere_visible(planes, centers, radii) if culling and n else np.ones(n, bool)
        shown = np.flatnonzero(visible)
        picks = [self._view_entries(shown, kind, lod, passed, last_start, dist, as_impostor, impostor_start, top)]
        casting = None
        if self.cascades:
            casting = np.stack([sphere_visible(p, centers, radii, r, dist) if culling and n else np.ones(n, bool)
                                for p, r in zip(shadow_planes, reach)])
            shadow_lod = np.where(as_impostor, top[kind] + 1, np.minimum(passed + 1, top[kind]))
            for in_cascade in casting:
                casting_agents = np.flatnonzero(in_cascade)
                picks.append((casting_agents, shadow_lod[casting_agents], np.full(len(casting_agents), NO_FADE, np.uint32)))
        variants = [instances.variant.get(group) for group in self.group_names]
        pass_counts = np.stack([self._upload(p, *entry, kind, variants) for p, entry in enumerate(picks)])
        held = as_impostor & (dist >= impostor_start[kind] + self.lod_fade)
        cast_visible = np.bincount(kind[shown], minlength=len(counts)).tolist()
        return CpuPicks(visible, casting, lod, held, pass_counts, cast_visible, int(np.count_nonzero(as_impostor[shown])))

    def _view_entries(self, shown, kind, lod, passed, last_start, dist, as_impostor, impostor_start, top):
        """The view's (agents, LODs, fade codes): each shown agent at its LOD, and those within lod_fade of
        the switch behind them again at the finer LOD (lod_pick.glsl's rule)."""
        codes = np.full(len(shown), NO_FADE, np.uint32)
        if not self.lod_fade or not len(shown):
            return shown, lod[shown], codes
        k = kind[shown]
        d = dist[shown]
        impostor = as_impostor[shown]
        raw = passed[shown]
        boundary = np.where(impostor, impostor_start[k], np.where(raw > 0, last_start[shown], -1.0))
        finer = np.where(impostor, np.minimum(raw, top[k]), np.minimum(raw - 1, top[k]))
        fading = (boundary >= 0.0) & (d < boundary + self.lod_fade) & (finer != lod[shown])
        # float32, as the GPU cull works it out
        through = np.clip((d.astype(np.float32) - boundary.astype(np.float32)) / np.float32(self.lod_fade), 0.0, 1.0)
        code = (through * 127.0 + 0.5).astype(np.uint32)
        codes[fading] = np.uint32(128) | code[fading]
        return (np.concatenate([shown, shown[fading]]), np.concatenate([lod[shown], finer[fading]]),
                np.concatenate([codes, code[fading]]))

    def _upload(self, pass_index: int, agents: np.ndarray, lods: np.ndarray, codes: np.ndarray, kind: np.ndarray, variants) -> np.ndarray:
        """Entries (`agents` at `lods` with fade `codes`) into the pass's lists: each entry in its common
        pieces' list and one list per group its character has; returns each draw's instance count."""
        k = kind[agents]
        row = self._table_first[k] + lods * self._columns[k]
        lists, values = [], []
        listed = entries(agents, codes)
        for column in range(-1, self.plan.groups):
            if column < 0:
                key = self._table[row]
            else:
                first = self._group_first[k, column]
                v = variants[column]
                choice = v[agents].astype(np.int64) if v is not None else 0
                key = np.where(first >= 0, self._table[np.where(first >= 0, row + first + choice, 0)], -1)
            keep = key >= 0
            lists.append(key[keep])
            values.append(listed[keep])
        lists, values = np.concatenate(lists), np.concatenate(values)
        if len(self.plan.keys) <= 1 << 16:  # numpy sorts 16-bit keys stably by radix: about 8 times as fast
            lists = lists.astype(np.uint16)
        order = np.argsort(lists, kind="stable")  # agent order within a list (the impostor bake's frames)
        starts = np.searchsorted(lists[order], np.arange(len(self.plan.keys) + 1))
        sorted_values = values[order]
        for index, buffer in enumerate(self.buffers[pass_index]):
            chosen = sorted_values[starts[index]:starts[index + 1]]
            size = max(chosen.nbytes, 4)  # exact: a smaller crowd frees what it no longer needs
            if buffer.size != size:
                buffer.orphan(size)
            if len(chosen):
                buffer.write(chosen)
        return np.diff(starts)[self.plan.draw_list]

    def entry_bytes(self) -> int:
        """Bytes the lists of every pass hold together."""
        return self._objects.gpu_bytes()

    def gpu_bytes(self) -> int:
        return self._objects.gpu_bytes()

    def release(self) -> None:
        if hasattr(self, "_objects"):
            self._objects.release()
