"""What the renderer's last frame drew, as counts: ``CrowdRenderer.last`` and the lists' entries
(``listed``). The CPU path knows them when it culls; the GPU paths get them back a frame or two late
through the culls' rings, read when ``last`` is read rather than every frame."""

from __future__ import annotations

import numpy as np


class CountsWhenAsked:
    """A stage's ``last`` (its ``_last``) where the GPU hands counts back a frame or two late: a frame sets
    ``_counts_due`` and ``refresh_counts()`` reads them when ``last`` is read, not every frame."""

    @property
    def last(self) -> dict:
        if self._counts_due:
            self.refresh_counts()
        return self._last


class DrawnCounts(CountsWhenAsked):
    """A base of CrowdRenderer: its ``last`` (what the last frame drew: triangles, instances, visible agents,
    draws, agents per LOD, shadow instances, visible agents per character, impostors), ``refresh_counts``
    and ``listed`` (``_last``, ``_counts_due``, the culls and the draws are the renderer's)."""

    def refresh_counts(self, wait: bool = False) -> None:
        """``last`` on the GPU paths: the newest counts the GPU has handed back (a frame or two old; `wait`
        finishes the frames queued: stats at the end of a run, tests). A no-op on the CPU path."""
        cull = self.gpu or self.feedback
        if cull is None:
            return
        counts = cull.counts(wait).astype(np.int64)
        agents = cull.agent_counts().astype(np.int64)  # (characters, LOD slots): each kept agent once
        lod_counts = [int(x) for x in np.pad(agents.sum(axis=0), (0, self.lod_count))[: self.lod_count]]
        cast_visible = [int(x) for x in agents.sum(axis=1)]
        impostors = sum(int(agents[k, slot]) for k, slot in enumerate(self.impostor_lods) if 0 <= slot < agents.shape[1])
        for draw, c in zip(self.draws, counts):
            draw.count = int(c)
        shadow = cull.shadow_counts(wait).astype(np.int64) if self.shadows else np.zeros((0, len(self.draws)), np.int64)
        for d, draw in enumerate(self.draws):
            draw.shadow_counts = [int(c) for c in shadow[:, d]]
        self._counts_due = False
        self._last = {"triangles": int(sum(c * d.triangles for c, d in zip(counts, self.draws))), "instances": int(counts.sum()),
                     "visible": int(sum(lod_counts)), "draws": int(np.count_nonzero(counts)), "lod_counts": lod_counts,
                     "shadow_instances": int(shadow.sum()), "cast_visible": cast_visible, "impostors": impostors}

    def listed(self, index: int, cascade: int | None = None) -> np.ndarray:
        """uint32 entries draw `index` drew in the view's pass (or `cascade`'s) of the last frame
        (synchronous: tests and benchmarks; crowd.draw.cull_lists.entry_agents reads them)."""
        if self.cpu is not None:
            count = self.draws[index].count if cascade is None else self.draws[index].shadow_counts[cascade]
            return np.frombuffer(self.cpu.buffer(index, cascade).read(), np.uint32)[:count].copy()
        return self._cull.listed(index, cascade)
