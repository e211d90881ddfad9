"""`crowd-bench compaction`: the GPU cull's compacted lists (crowd/draw/gpu_cull.py): what its three
dispatches (count, scan, write) cost the GPU for the demo's crowd and camera, how many entries they list,
and what every pass's lists hold per agent.

The crowd is the demo's (the default scene's AI and camera, every agent's record written once); the cull
is timed with a timer query over `repeats` back-to-back runs after 10 to bring the clocks up, reading each
query before the next run (so the GPU idles between runs: this is the cull's own time, not its share of a
frame). Before it is timed, its lists are checked against the numpy cull's on the same agents: the entries
in one and not the other are agents within float32's reach of a plane or a LOD distance.
"""

from __future__ import annotations

import numpy as np

from crowd.draw.cull_lists import entry_agents


def _lists(renderer, cascades: int) -> set:
    """(pass, list key, agent) of every entry: the view's pass 0, then each cascade's."""
    out = set()
    for p in range(1 + cascades):
        for d in range(len(renderer.draws)):
            key = renderer.plan.keys[int(renderer.plan.draw_list[d])]
            out |= {(p, key, a) for a in entry_agents(renderer.listed(d, None if p == 0 else p - 1))[0].tolist()}
    return out


def measure(ctx, pipeline, cpu_renderer=None, repeats: int = 40) -> dict:
    """The pipeline's GPU cull on its AI's agents and its camera: the lists compared with `cpu_renderer`'s
    (a renderer of the numpy cull over the same cast, or None), then timed."""
    renderer = pipeline.renderer
    cull = renderer.gpu
    instances = pipeline.instances()
    renderer.prepare(pipeline.camera, instances, 0, cull_now=False, palette=pipeline.processor.layout)
    pending = renderer._pending
    renderer.cull()
    ctx.finish()
    differ = None
    if cpu_renderer is not None:
        cpu_renderer.crowd_box = renderer.crowd_box  # (the shadow cascades fit it)
        cpu_renderer.prepare(pipeline.camera, instances, 0, palette=pipeline.processor.layout)
        differ = len(_lists(cpu_renderer, cull.cascades) ^ _lists(renderer, cull.cascades))
    listed = int(sum(len(renderer.listed(d, None if p == 0 else p - 1)) for p in range(1 + cull.cascades) for d in range(len(renderer.draws))))
    query = ctx.query(time=True)
    samples = []
    for k in range(10 + repeats):
        renderer._pending = pending
        with query:
            renderer.cull()
        if k >= 10:
            samples.append(query.elapsed / 1e6)
    held = renderer.gpu_bytes()
    agents = max(cull.agents, 1)
    return {"agents": cull.agents, "draws": cull.draw_count, "lists": cull.lists, "passes": cull.passes, "shared_counters": cull.shared,
            "entries_unlike_the_numpy_cull": differ, "entries": listed, "ms": round(float(np.median(samples)), 4),
            "list_bytes": held["lists"], "list_bytes_per_agent": round(held["lists"] / agents, 2), "record_bytes_per_agent": round(held["records"] / agents, 2),
            "cull_bytes": held["cull"]}
