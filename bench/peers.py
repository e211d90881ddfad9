"""``crowd-bench peers``: the crowd against what a Python developer would reach for instead, Panda3D's
``Actor``, on the same glTF character, at the same resolution, on the same machine, in one run.

The work, the same on both sides: n agents on the benchmarks' square grid (``bench.common.grid_layout``, 1.5 m
apart, a camera that sees all of them), each looping the walk clip from its own start phase and
heading; in the blend modes each agent also plays the run clip and blends the two at its own weight.
Both sides light the character with shaders/lighting.glsl and draw no ground, shadows or weapons, and
run no AI: what is compared is animating and drawing the crowd.

Modes (``MODES``):
- crowd ``walk`` and ``blend2``: the GPU animation processor and skinned instancing, every agent at LOD0,
  so both sides draw the same triangles; ``walk_lod`` adds the demo's LOD distances (14 m, 40 m).
- panda3d ``cpu_walk``: one Actor per agent with Panda3D's default CPU vertex animation; ``gpu_walk`` and
  ``gpu_blend2``: hardware skinning through a hand-written GLSL 1.50 shader (bench/peers_panda.py says
  why); the blend is ``enableBlend`` / ``setControlEffect``. ``cpu_walk_lod`` and ``gpu_walk_lod``: the
  same Actors built with the character's LOD meshes (``setLODNode`` / ``addLOD``) at the crowd's LOD
  distances, so that ``walk_lod`` is compared with Panda3D drawing the same triangles.
  ``gpu_walk_threaded``: ``gpu_walk`` on Panda3D's threaded pipeline (``threading-model Cull/Draw``: App,
  Cull, where Actors animate, and Draw each on a thread of its own, a frame apart), its answer to a
  CPU-bound frame.

Each (system, mode) runs in a child process of its own, so its process CPU time is its own and the two
GL stacks never share a process. A frame is timed from the start of its CPU work until glFinish returns,
so its GPU work lands in the frame that submitted it. ``cpu_ms`` is the process's CPU time (every thread)
from the start of the frame until glFinish is called: the frame's own CPU work. ``cpu_in_finish_ms`` is
the CPU time spent inside glFinish: llvmpipe's rasteriser threads drawing the frame, or the NVIDIA driver
spinning while it waits for the GPU (which is why it is not added to the first). On the threaded
pipeline a frame is timed from one renderFrame to the next, which waits for the frame before it: the
pipeline's period, its sustained frame time (its latency is longer). Medians over ``frames``
frames after ``warmup``. Agent counts start at 16 and double until the median passes ``limit_ms``; then,
per budget (16.7 and 33.3 ms), the count between the bracketing doublings is bisected ``refine`` times
(3 steps: within 2^(1/8), 9 %). A mode sustains a budget with the largest measured count within it.

Poses are checked, not assumed: each mode draws 16 agents at frame ``SHOT_FRAME`` into a screenshot, and
each Panda3D screenshot's silhouette is compared (intersection over union) with the crowd's at the same
time. The crowd's bind-pose screenshot gives the IoU a peer drawn in its bind pose would get.
"""

from __future__ import annotations

import json
import math
import os
import subprocess
import sys
import tempfile
import time
from importlib.util import find_spec
from pathlib import Path

import numpy as np

from .common import device_cpu
from .peer_work import FRAME_DT, agent_layout
from crowd.frame import CLIP, PHASE, WEIGHT, empty_layers

MODES = {
    ("crowd", "walk"): "GPU processor + skinned instancing, 1 clip, all at LOD0",
    ("crowd", "blend2"): "GPU processor + skinned instancing, 2 clips blended, all at LOD0",
    ("crowd", "walk_lod"): "GPU processor + skinned instancing, 1 clip, LOD at 14 m / 40 m",
    ("panda3d", "cpu_walk"): "one Actor per agent, 1 clip, CPU vertex animation",
    ("panda3d", "gpu_walk"): "one Actor per agent, 1 clip, hardware skinning (GLSL 1.50)",
    ("panda3d", "gpu_blend2"): "one Actor per agent, 2 clips blended, hardware skinning (GLSL 1.50)",
    ("panda3d", "cpu_walk_lod"): "one Actor per agent, 1 clip, CPU vertex animation, LOD at 14 m / 40 m",
    ("panda3d", "gpu_walk_lod"): "one Actor per agent, 1 clip, hardware skinning (GLSL 1.50), LOD at 14 m / 40 m",
    ("panda3d", "gpu_walk_threaded"): "gpu_walk with App, Cull and Draw on three threads (threading-model Cull/Draw)",
}
# The crowd mode whose screenshot each Panda3D mode's poses must match.
POSE_REFERENCE = {"cpu_walk": "walk", "gpu_walk": "walk", "gpu_walk_threaded": "walk", "gpu_blend2": "blend2",
                  "cpu_walk_lod": "walk_lod", "gpu_walk_lod": "walk_lod"}
# Which Panda3D modes each crowd mode is compared with; the ratio takes the fastest of them. The crowd's
# LOD is held against every Panda3D walk, with or without Panda3D's own LOD.
PAIRS = (("walk", ("cpu_walk", "gpu_walk", "gpu_walk_threaded")), ("blend2", ("gpu_blend2",)),
         ("walk_lod", ("cpu_walk", "gpu_walk", "gpu_walk_threaded", "cpu_walk_lod", "gpu_walk_lod")))
BUDGETS_MS = (1000.0 / 60.0, 1000.0 / 30.0)
SHOT_AGENTS = 16
SHOT_FRAME = 12
POSE_IOU_MIN = 0.8  # a peer's silhouette must overlap the crowd's at least this much (bind pose: see the report)


class PeersError(ValueError):
    """Bad peers-benchmark input; the message is one line."""


def panda3d_missing() -> str | None:
    """Why the Panda3D side cannot run here, or None when it can."""
    missing = [name for name, module in (("panda3d", "panda3d"), ("panda3d-gltf", "gltf")) if find_spec(module) is None]
    return f"{' and '.join(missing)} not installed (pip install '.[peers]')" if missing else None


# -- the measurement loop, shared by both sides (run in the child process)

def measure(side, spec: dict) -> dict:
    """Screenshot at 16 agents, then the doubling sweep and the bisection per budget."""
    shot = None
    if spec.get("screenshot"):
        side.set_agents(SHOT_AGENTS)
        for _ in range(SHOT_FRAME + 1):
            side.work()
            side.finish()
        shot = spec["screenshot"]
        side.save_screenshot(shot)
        if spec.get("bind_screenshot"):
            side.save_bind_screenshot(spec["bind_screenshot"])
    rows: dict[int, dict] = {}

    def run(n: int) -> dict:
        side.set_agents(n)
        for _ in range(spec["warmup"]):
            side.work()
            side.finish()
        wall, cpu, in_finish = [], [], []
        for _ in range(spec["frames"]):
            t0, c0 = time.perf_counter(), time.process_time()
            side.work()
            c1 = time.process_time()
            side.finish()
            wall.append((time.perf_counter() - t0) * 1e3)
            cpu.append((c1 - c0) * 1e3)
            in_finish.append((time.process_time() - c1) * 1e3)
        row = {"agents": n, "frame_ms": round(float(np.median(wall)), 3), "cpu_ms": round(float(np.median(cpu)), 3),
               "cpu_in_finish_ms": round(float(np.median(in_finish)), 3), "frame_p95_ms": round(float(np.percentile(wall, 95)), 3)}
        row.update(side.row_extra())
        rows[n] = row
        print(f"  {spec['system']:>8} {spec['mode']:<17} {n:>8} agents  {row['frame_ms']:>9.2f} ms  cpu {row['cpu_ms']:>9.2f} ms"
              f" (+{row['cpu_in_finish_ms']:.2f} in glFinish)", flush=True)
        return row

    n = spec["start"]
    while n <= spec["max_agents"]:
        if run(n)["frame_ms"] > spec["limit_ms"]:
            break
        n *= 2
    for budget in spec["budgets"]:
        for _ in range(spec["refine"]):
            within = [k for k, r in rows.items() if r["frame_ms"] <= budget]
            if not within:
                break
            lo = max(within)
            hi = min((k for k, r in rows.items() if k > lo and r["frame_ms"] > budget), default=None)
            if hi is None or hi - lo <= max(1, lo // 16):
                break
            run(int(round(math.sqrt(lo * hi))))
    return {"system": spec["system"], "mode": spec["mode"], "rows": [rows[k] for k in sorted(rows)], "info": side.info(),
            "host": _host(), "screenshot": shot}


def _host() -> str:
    return f"{device_cpu()}, {os.cpu_count()} CPUs"


def sustained(rows: list[dict], budget_ms: float) -> int:
    """The largest measured agent count whose median frame is within the budget (0: not even the first)."""
    return max((r["agents"] for r in rows if r["frame_ms"] <= budget_ms), default=0)


# -- the crowd side

class CrowdSide:
    """This project's pipeline stages, driven directly: layers → processor → cull/LOD → colour pass."""

    def __init__(self, spec: dict):
        from crowd.anim.roles import bake_roles
        from crowd.asset.gltf import load_character
        from crowd.gl import Offscreen, describe, headless_context
        from crowd.stages import StageSpec, Stages

        self.spec = spec
        self.blend = spec["mode"] == "blend2"
        self.size = tuple(spec["size"])
        self.ctx = headless_context()
        self._describe = describe(self.ctx)
        character = load_character(spec["model"])
        walk, run = spec["clips"]
        # Leave out what the mode does not need: the walk alone, or the walk and the run.
        self.bake = bake_roles(character, {"walk": walk, "run": run if self.blend else None})
        self.layer_count = 2 if self.blend else 1
        lod = spec["lod_distances"] if spec["mode"] == "walk_lod" else (1e9, 1e9, 1e9)
        self.stages = Stages.build(self.ctx, (character, self.bake), StageSpec(layers=self.layer_count, lod_distances=lod,
                                                                             shadows=False, culling=True))
        self.processor, self.renderer = self.stages.processor, self.stages.renderer
        heads = self.renderer.groups[0].get("head", [])
        # The glTF scene wears the first head: Panda3D draws what the scene holds, so this side does too.
        self._head = 0 if heads else None
        self.target = Offscreen(self.ctx, self.size)
        self.fb = self.target.framebuffer
        self.clip_rows = [self.bake.clip_index(c) for c in ((walk, run) if self.blend else (walk,))]
        self.durations = [self.bake.clips[row].duration for row in self.clip_rows]
        self.frame_index = 0
        self.n = 0

    def set_agents(self, n: int) -> None:
        from crowd.frame import Camera, Instances

        pos, yaw, phase, weight, (eye, target, far) = agent_layout(n, self.spec["seed"])
        self.n, self.phase = n, phase
        self.camera = Camera(eye=eye, target=target, aspect=self.size[0] / self.size[1], far=far)
        variants = {"head": np.full(n, self._head)} if self._head is not None else {}
        self.instances = Instances(pos, yaw.astype(np.float32), np.ones(n, np.float32), np.full((n, 4), 255, np.uint8), variants)
        self.processor.resize(n)
        self.layers = empty_layers(n, self.layer_count)
        self.layers[:, 0, CLIP] = self.clip_rows[0]
        self.layers[:, 0, WEIGHT] = weight if self.blend else 1.0
        if self.blend:
            self.layers[:, 1, CLIP] = self.clip_rows[1]
            self.layers[:, 1, WEIGHT] = 1.0 - weight

    def work(self) -> None:
        t = self.frame_index * FRAME_DT
        self.frame_index += 1
        self.layers[:, 0, PHASE] = np.mod(self.phase + t / self.durations[0], 1.0)
        if self.blend:
            self.layers[:, 1, PHASE] = np.mod(self.phase + t / self.durations[1], 1.0)
        self.processor.upload(self.layers)
        self.processor.run()
        view = self.renderer.prepare(self.camera, self.instances)
        self.fb.use()
        self.fb.clear(0.0, 0.0, 0.0, 1.0, depth=1.0)
        self.renderer.color_pass(self.fb, view, self.processor)

    def finish(self) -> None:
        self.ctx.finish()

    def row_extra(self) -> dict:
        last = self.renderer.last
        return {"triangles": int(last["triangles"]), "draws": int(last["draws"]), "visible": int(last["visible"])}

    def save_screenshot(self, path: str) -> None:
        from crowd.images import write_png

        write_png(path, self.target.image())

    def save_bind_screenshot(self, path: str) -> None:
        """The same agents in the bind pose (no layer weight: every joint at rest), for the IoU check."""
        held = self.layers[..., WEIGHT].copy()
        self.layers[..., WEIGHT] = 0.0
        self.frame_index -= 1
        self.work()
        self.finish()
        self.save_screenshot(path)
        self.layers[..., WEIGHT] = held

    def info(self) -> dict:
        import moderngl

        d = self._describe
        return {"gl": f"{d['gl_renderer']}, {d['gl_version']}", "versions": f"moderngl {moderngl.__version__}",
                "processor": self.processor.path}

    def release(self) -> None:
        self.stages.release()
        self.target.release()
        self.ctx.release()


# -- the orchestrator (parent process)

def _run_worker(spec: dict, timeout_s: float) -> dict:
    with tempfile.TemporaryDirectory() as tmp:
        spec = dict(spec, out=str(Path(tmp) / "result.json"))
        spec_path = Path(tmp) / "spec.json"
        spec_path.write_text(json.dumps(spec))
        try:
            proc = subprocess.run([sys.executable, "-m", "bench.peers", str(spec_path)], timeout=timeout_s,
                                  stdout=None, stderr=subprocess.PIPE, text=True)
        except subprocess.TimeoutExpired:
            return {"system": spec["system"], "mode": spec["mode"], "error": f"ran past {timeout_s:.0f} s"}
        out = Path(spec["out"])
        if proc.returncode != 0 or not out.exists():
            lines = [ln for ln in proc.stderr.strip().splitlines() if ln.strip()]
            return {"system": spec["system"], "mode": spec["mode"], "error": (lines[-1] if lines else f"exit status {proc.returncode}")}
        return json.loads(out.read_text())


def _mask(path: Path) -> np.ndarray:
    from PIL import Image

    return np.asarray(Image.open(path).convert("RGB")).max(axis=2) > 8


def _iou(a: np.ndarray, b: np.ndarray) -> float:
    union = np.logical_or(a, b).sum()
    return float(np.logical_and(a, b).sum() / union) if union else 0.0


def pose_checks(results: list[dict], shots: Path) -> list[dict]:
    """Silhouette IoU of each Panda3D mode's screenshot against the crowd's at the same frame."""
    checks = []
    masks: dict[str, np.ndarray] = {}

    def mask(name: str) -> np.ndarray:  # each image is read once
        if name not in masks:
            masks[name] = _mask(shots / name)
        return masks[name]

    bind_iou = _iou(mask("crowd_bind.png"), mask("crowd_walk.png")) if (shots / "crowd_bind.png").exists() and (shots / "crowd_walk.png").exists() else None
    for r in results:
        if r.get("system") != "panda3d" or not r.get("screenshot"):
            continue
        ref = shots / f"crowd_{POSE_REFERENCE[r['mode']]}.png"
        shot = shots / Path(r["screenshot"]).name  # a merged report's paths are another machine's
        if not ref.exists() or not shot.exists():  # said, not passed: e.g. the Panda3D side run alone
            missing = ref.name if not ref.exists() else shot.name
            checks.append({"system": r["system"], "mode": r["mode"], "against": ref.name, "iou": None, "ok": None,
                           "why": f"not checked: no {missing} in {shots}"})
            continue
        check = {"system": r["system"], "mode": r["mode"], "against": ref.name, "iou": round(_iou(_mask(shot), mask(ref.name)), 3)}
        if bind_iou is not None:
            check["bind_pose_iou"] = round(bind_iou, 3)
        check["ok"] = check["iou"] >= POSE_IOU_MIN and check["iou"] > check.get("bind_pose_iou", 0.0)
        checks.append(check)
    return checks


def summarise(results: list[dict], budgets=BUDGETS_MS) -> dict:
    rows, sus, ratios = [], [], []
    for r in results:
        for row in r.get("rows", []):
            rows.append({"system": r["system"], "mode": r["mode"], **row})
        if "rows" in r:
            for b in budgets:
                sus.append({"system": r["system"], "mode": r["mode"], "budget_ms": round(b, 1), "agents": sustained(r["rows"], b)})
    have = {(s["system"], s["mode"], s["budget_ms"]): s["agents"] for s in sus}
    for crowd_mode, peers in PAIRS:
        for b in budgets:
            b = round(b, 1)
            ours = have.get(("crowd", crowd_mode, b))
            theirs = [(have[("panda3d", p, b)], p) for p in peers if ("panda3d", p, b) in have]
            if ours is None or not theirs:
                continue
            best, mode = max(theirs)
            ratios.append({"budget_ms": b, "crowd_mode": crowd_mode, "panda3d_mode": mode, "crowd_agents": ours,
                           "panda3d_agents": best, "ratio": round(ours / best, 1) if best else None})
    return {"rows": rows, "sustained": sus, "ratios": ratios}


def bench_peers(args) -> int:
    from crowd.asset.gltf import load_character
    from crowd.settings import parse
    from crowd.draw.render import DEFAULT_LOD_DISTANCES
    from crowd.anim.roles import match_roles

    size = parse("size", args.size)
    model = Path(args.model).resolve() if args.model else None
    character = load_character(model)
    roles, _ = match_roles(character.clips)
    walk, run = roles["walk"], roles["run"] or roles["walk"]
    if model is None:
        from crowd.asset.zombie import ASSET_PATH

        model_file = ASSET_PATH
    else:
        model_file = model
    systems = [s.strip() for s in args.systems.split(",") if s.strip() and s.strip() != "none"]
    unknown = [s for s in systems if s not in ("crowd", "panda3d")]
    if unknown:
        raise PeersError(f"systems are crowd and panda3d, got {', '.join(unknown)}")
    notes = []
    if "panda3d" in systems and (why := panda3d_missing()):
        print(f"crowd-bench peers: skipping the Panda3D side: {why}", flush=True)
        notes.append(f"Panda3D side skipped: {why}")
        systems.remove("panda3d")
    modes = [m for m in MODES if m[0] in systems and (not args.modes or m[1] in args.modes.split(","))]
    shots = Path(args.screenshots)
    shots.mkdir(parents=True, exist_ok=True)
    base = {"model": str(model_file), "clips": [walk, run], "size": list(size), "frames": args.frames, "warmup": args.warmup,
            "limit_ms": args.limit_ms, "budgets": list(BUDGETS_MS), "refine": args.refine, "start": args.start,
            "max_agents": args.max_agents, "seed": args.seed, "lod_distances": list(DEFAULT_LOD_DISTANCES)}
    results = []
    for system, mode in modes:
        print(f"{system} {mode}: {MODES[(system, mode)]}", flush=True)
        spec = dict(base, system=system, mode=mode, screenshot=str((shots / f"{system}_{mode}.png").resolve()))
        if (system, mode) == ("crowd", "walk"):
            spec["bind_screenshot"] = str((shots / "crowd_bind.png").resolve())
        r = _run_worker(spec, args.timeout)
        if "error" in r:
            print(f"  {system} {mode} failed: {r['error']}", flush=True)
        results.append(r)
    for path in args.merge or []:
        try:
            other = json.loads(Path(path).read_text())
        except (OSError, ValueError) as exc:
            raise PeersError(f"--merge {path}: {exc}") from None
        results += [r for r in other.get("results", []) if (r.get("system"), r.get("mode")) not in {(x["system"], x["mode"]) for x in results}]
        notes += [f"merged from {Path(path).name}: {n}" for n in other.get("notes", [])]
    summary = summarise(results)
    checks = pose_checks(results, shots)
    report = {"device": _device(results), "size": list(size), "model": "built-in zombie" if model is None else model.name,
              "clips": [walk, run], "protocol": {k: base[k] for k in ("frames", "warmup", "limit_ms", "refine", "start", "seed", "lod_distances")},
              **summary, "pose_check": checks, "results": results, "notes": notes,
              "errors": [{"system": r["system"], "mode": r["mode"], "error": r["error"]} for r in results if "error" in r]}
    _print_report(report)
    if args.json:
        from crowd.files import atomic_write_bytes

        atomic_write_bytes(Path(args.json), json.dumps(report, indent=1).encode())
    if args.plot:
        from .plots import peers_plot

        peers_plot(report, Path(args.plot))
    return 1 if report["errors"] or any(c["ok"] is False for c in checks) else 0


def _device(results: list[dict]) -> str:
    # The measuring machine's host, not this one's: a merged report may come from elsewhere.
    cpu = next((r["host"] for r in results if r.get("host")), _host())
    seen = []
    for r in results:
        info = r.get("info")
        if info and (r["system"], info["gl"]) not in [(s, g) for s, g, _ in seen]:
            seen.append((r["system"], info["gl"], info.get("versions", "")))
    return "; ".join(f"{s}: {g}, {v}" for s, g, v in seen) + f"; {cpu}"


def _print_report(report: dict) -> None:
    print(f"\n{report['device']}\n{report['size'][0]}x{report['size'][1]}, {report['model']}, clips {report['clips']}")
    print(f"{'system':<8} {'mode':<17} {'16.7 ms':>9} {'33.3 ms':>9}")
    pairs = {}
    for s in report["sustained"]:
        pairs.setdefault((s["system"], s["mode"]), {})[s["budget_ms"]] = s["agents"]
    for (system, mode), by in pairs.items():
        print(f"{system:<8} {mode:<17} " + " ".join(f"{by.get(round(b, 1), 0):>9}" for b in BUDGETS_MS))
    for r in report["ratios"]:
        print(f"{r['budget_ms']:>5} ms: crowd {r['crowd_mode']} {r['crowd_agents']} / panda3d {r['panda3d_mode']} {r['panda3d_agents']} = {r['ratio']}x")
    for c in report["pose_check"]:
        if c["ok"] is None:
            print(f"pose check {c['mode']}: {c['why']}")
            continue
        print(f"pose check {c['mode']}: IoU {c['iou']} against {c['against']} (bind pose {c.get('bind_pose_iou')}) {'ok' if c['ok'] else 'FAILED'}")
    for e in report["errors"]:
        print(f"error: {e['system']} {e['mode']}: {e['error']}")


def add_parsers(sub) -> None:
    p = sub.add_parser("peers", help="the crowd against Panda3D Actors on the same character: frame ms, CPU ms, agents per budget")
    p.add_argument("--model", type=Path, help="a .glb/.gltf (default: the built-in zombie)")
    p.add_argument("--size", default="1280x720", help='frame size WxH')
    p.add_argument("--systems", default="crowd,panda3d", help="crowd, panda3d, both, or none (only --merge)")
    p.add_argument("--modes", default="", help="comma-separated modes to run (default: all of the systems')")
    p.add_argument("--frames", type=int, default=30, help='timed frames per crowd size')
    p.add_argument("--warmup", type=int, default=5, help='frames before timing')
    p.add_argument("--start", type=int, default=16, help='the first crowd size, doubled until a frame passes --limit-ms')
    p.add_argument("--limit-ms", type=float, default=100.0, help="stop doubling once a frame's median passes this")
    p.add_argument("--max-agents", type=int, default=1 << 20, help='the largest crowd size tried')
    p.add_argument("--refine", type=int, default=3, help="bisection steps per budget")
    p.add_argument("--seed", type=int, default=1, help='random seed of the crowd')
    p.add_argument("--timeout", type=float, default=1800.0, help="seconds per mode")
    p.add_argument("--screenshots", default="out/peers", help="folder for each mode's screenshot")
    p.add_argument("--merge", action="append", help="a report from another run (e.g. the Panda3D side run alone) to merge")
    p.add_argument("--json", type=Path, help='write the results as JSON to this file')
    p.add_argument("--plot", type=Path, help='PNG of frame ms against agent count for each mode')
    p.set_defaults(run=_checked(bench_peers))


def _checked(fn):
    def run(args):
        try:
            return fn(args)
        except PeersError as exc:
            print(f"crowd-bench peers: {exc}", file=sys.stderr)
            return 2
    return run


def _worker_main(spec_path: str) -> int:
    spec = json.loads(Path(spec_path).read_text())
    if spec["system"] == "crowd":
        side = CrowdSide(spec)
    else:
        from .peers_panda import PandaSide

        side = PandaSide(spec)
    try:
        result = measure(side, spec)
    finally:
        side.release()
    Path(spec["out"]).write_text(json.dumps(result))
    return 0


if __name__ == "__main__":
    if len(sys.argv) != 2:  # the worker that bench_peers starts; people run `crowd-bench peers`
        print("usage: python -m bench.peers SPEC.json (run by crowd-bench peers)", file=sys.stderr)
        raise SystemExit(2)
    raise SystemExit(_worker_main(sys.argv[1]))
