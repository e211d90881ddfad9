"""Builds small skinned glTF files with chosen features, so the importer is tested feature by feature.

The character: a chain of 3 joints (root → mid → tip) under an optional non-joint armature node, a
strip of 6 vertices skinned to them, and one clip that rotates `mid` about Z and moves `root`.
`expected_skinning` recomputes what the file means with plain matrices, independently of the importer.
"""

from __future__ import annotations

import base64
import json
from pathlib import Path

import numpy as np

from crowd import transforms as tf

KEY_TIMES = np.array([0.5, 1.0, 1.5])  # the clip starts after t = 0
MID_ANGLES = np.array([0.0, 1.2, 2.4])  # radians about Z
ROOT_MOVES = np.array([[0.0, 0.0, 0.0], [0.3, 0.0, 0.0], [0.6, 0.1, 0.0]])
JOINT_T = np.array([[0.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 1.0, 0.0]])
POSITIONS = np.array([[-0.1, 0.0, 0], [0.1, 0.0, 0], [-0.1, 1.0, 0], [0.1, 1.0, 0], [-0.1, 2.0, 0], [0.1, 2.0, 0]], dtype=np.float32)
JOINTS = np.array([[0, 1, 0, 0], [0, 0, 0, 0], [1, 0, 2, 0], [1, 2, 0, 0], [2, 1, 0, 0], [2, 0, 0, 0]])
WEIGHTS = np.array([[0.7, 0.3, 0, 0], [1, 0, 0, 0], [0.5, 0.25, 0.25, 0], [0.6, 0.4, 0, 0], [0.8, 0.2, 0, 0], [1, 0, 0, 0]])
# Morph targets (morph=True): "bulge" pushes the middle pair out along z and tilts their normals, "stretch"
# lengthens the top pair; the mesh's default weights are overridden by the node's; the clip keys both.
MORPH_NAMES = ["bulge", "stretch"]
MORPH_POSITIONS = np.zeros((2, 6, 3), np.float32)
MORPH_POSITIONS[0, 2:4, 2] = 0.25
MORPH_POSITIONS[1, 4:6, 1] = 0.5
MORPH_NORMALS = np.zeros((2, 6, 3), np.float32)
MORPH_NORMALS[0, 2:4, 0] = 0.5
MESH_MORPH_WEIGHTS = [0.25, 0.0]
NODE_MORPH_WEIGHTS = [0.5, 0.125]
MORPH_KEYS = np.array([[0.0, 1.0], [1.0, 0.5], [0.25, 0.0]])  # per key time, the two targets' weights


def armature_matrix(scale: float, with_rotation: bool) -> np.ndarray:
    q = tf.quat_from_axis_angle([1.0, 0.0, 0.0], np.pi / 2) if with_rotation else np.array([0, 0, 0, 1.0])
    return tf.trs_to_mat4(np.array([0.5, 0.0, -0.25]), q, np.array([scale] * 3))


def make_gltf(folder: Path, name="test.gltf", armature_scale=1.0, armature_rotation=False, use_matrix=False,
              joint_type=5121, weight_type=5126, interleaved=False, buffer_mode="data", external_uri=None,
              interpolation="LINEAR", split_animations=False, morph=False, sparse=False, extra: dict | None = None) -> Path:
    blob = bytearray()
    views, accessors = [], []

    def add(arr: np.ndarray, ctype: int, kind: str, normalized=False, minmax=False, stride=None, view=None, offset=0):
        if view is None:
            while len(blob) % 4:
                blob.append(0)
            views.append({"buffer": 0, "byteOffset": len(blob), "byteLength": arr.nbytes})
            if stride:
                views[-1]["byteStride"] = stride
            blob.extend(arr.tobytes())
            view = len(views) - 1
        acc = {"bufferView": view, "componentType": ctype, "count": int(arr.shape[0]),
               "type": kind}
        if offset:
            acc["byteOffset"] = offset
        if normalized:
            acc["normalized"] = True
        if minmax:
            flat = arr.reshape(arr.shape[0], -1)
            acc["min"] = [float(x) for x in flat.min(0)]
            acc["max"] = [float(x) for x in flat.max(0)]
        accessors.append(acc)
        return len(accessors) - 1

    normals = np.tile(np.array([[0, 0, 1]], dtype=np.float32), (6, 1))
    if interleaved:
        inter = np.concatenate([POSITIONS, normals], axis=1).astype(np.float32)
        while len(blob) % 4:
            blob.append(0)
        views.append({"buffer": 0, "byteOffset": len(blob), "byteLength": inter.nbytes, "byteStride": 24, "target": 34962})
        blob.extend(inter.tobytes())
        v = len(views) - 1
        accessors.append({"bufferView": v, "componentType": 5126, "count": 6, "type": "VEC3",
                          "min": POSITIONS.min(0).tolist(), "max": POSITIONS.max(0).tolist()})
        pos_acc = len(accessors) - 1
        accessors.append({"bufferView": v, "byteOffset": 12, "componentType": 5126, "count": 6, "type": "VEC3"})
        nrm_acc = len(accessors) - 1
    else:
        pos_acc = add(POSITIONS, 5126, "VEC3", minmax=True)
        nrm_acc = add(normals, 5126, "VEC3")
    if sparse:
        # A sparse accessor over zeros that fills in the real positions.
        idx = np.arange(6, dtype=np.uint16)
        iv = add(idx, 5123, "SCALAR")
        vv = add(POSITIONS, 5126, "VEC3")
        accessors.append({"componentType": 5126, "count": 6, "type": "VEC3", "min": POSITIONS.min(0).tolist(),
                          "max": POSITIONS.max(0).tolist(),
                          "sparse": {"count": 6, "indices": {"bufferView": accessors[iv]["bufferView"], "componentType": 5123},
                                     "values": {"bufferView": accessors[vv]["bufferView"]}}})
        pos_acc = len(accessors) - 1
    jdt = {5121: np.uint8, 5123: np.uint16}[joint_type]
    j_acc = add(JOINTS.astype(jdt), joint_type, "VEC4")
    if weight_type == 5126:
        w_acc = add((WEIGHTS * 1.25).astype(np.float32), 5126, "VEC4")  # deliberately not summing to 1
    else:
        info = np.iinfo({5121: np.uint8, 5123: np.uint16}[weight_type])
        w_acc = add(np.round(WEIGHTS * info.max).astype(info.dtype), weight_type, "VEC4", normalized=True)
    indices = np.array([0, 1, 2, 2, 1, 3, 2, 3, 4, 4, 3, 5], dtype=np.uint16)
    i_acc = add(indices, 5123, "SCALAR")

    arm = armature_matrix(armature_scale, armature_rotation)
    glob = [arm @ tf.trs_to_mat4(JOINT_T[0], np.array([0, 0, 0, 1.0]), np.ones(3))]
    for k in (1, 2):
        glob.append(glob[-1] @ tf.trs_to_mat4(JOINT_T[k], np.array([0, 0, 0, 1.0]), np.ones(3)))
    ibm = np.linalg.inv(np.array(glob))
    ibm_acc = add(np.transpose(ibm, (0, 2, 1)).astype(np.float32).reshape(3, 16), 5126, "MAT4")

    t_acc = add(KEY_TIMES.astype(np.float32), 5126, "SCALAR", minmax=True)
    rot = tf.quat_from_axis_angle([0.0, 0.0, 1.0], MID_ANGLES)
    if interpolation == "CUBICSPLINE":
        tangents = np.zeros_like(rot)
        rot_out = np.stack([tangents, rot, tangents], axis=1).reshape(-1, 4)
        mov_out = np.stack([np.zeros_like(ROOT_MOVES), ROOT_MOVES, np.zeros_like(ROOT_MOVES)], axis=1).reshape(-1, 3)
    else:
        rot_out, mov_out = rot, ROOT_MOVES
    r_acc = add(rot_out.astype(np.float32), 5126, "VEC4")
    m_acc = add(mov_out.astype(np.float32), 5126, "VEC3")

    arm_node = {"name": "Armature", "children": [1]}
    if use_matrix:
        arm_node["matrix"] = [float(x) for x in arm.T.reshape(-1)]
    else:
        t, q, s, _ = tf.mat4_decompose(arm)
        arm_node.update(translation=t.tolist(), rotation=q.tolist(), scale=s.tolist())
    nodes = [
        arm_node,
        {"name": "root", "children": [2]},
        {"name": "mid", "translation": JOINT_T[1].tolist(), "children": [3]},
        {"name": "tip", "translation": JOINT_T[2].tolist()},
        {"name": "body", "mesh": 0, "skin": 0},
    ]
    prim = {"attributes": {"POSITION": pos_acc, "NORMAL": nrm_acc, "JOINTS_0": j_acc, "WEIGHTS_0": w_acc}, "indices": i_acc}
    if morph:
        prim["targets"] = [{"POSITION": add(MORPH_POSITIONS[k], 5126, "VEC3", minmax=True), "NORMAL": add(MORPH_NORMALS[k], 5126, "VEC3")}
                           for k in range(2)]
        nodes[4]["weights"] = NODE_MORPH_WEIGHTS
        keys = MORPH_KEYS
        if interpolation == "CUBICSPLINE":
            keys = np.stack([np.zeros_like(keys), keys, np.zeros_like(keys)], axis=1)
        w_out = add(keys.reshape(-1, 1).astype(np.float32), 5126, "SCALAR")
    samplers = [{"input": t_acc, "output": r_acc, "interpolation": interpolation},
                {"input": t_acc, "output": m_acc, "interpolation": interpolation}]
    channels = [{"sampler": 0, "target": {"node": 2, "path": "rotation"}}, {"sampler": 1, "target": {"node": 1, "path": "translation"}}]
    if morph:
        samplers.append({"input": t_acc, "output": w_out, "interpolation": interpolation})
        channels.append({"sampler": 2, "target": {"node": 4, "path": "weights"}})
    if split_animations:
        animations = [{"name": "mid", "samplers": [samplers[0]], "channels": [dict(channels[0], sampler=0)]},
                      {"name": "root", "samplers": [samplers[1]], "channels": [dict(channels[1], sampler=0)]}]
    else:
        animations = [{"name": "wave", "samplers": samplers, "channels": channels}]
    doc = {
        "asset": {"version": "2.0"},
        "scene": 0,
        "scenes": [{"nodes": [0, 4]}],
        "nodes": nodes,
        "meshes": [{"name": "body", "primitives": [prim], **({"weights": MESH_MORPH_WEIGHTS, "extras": {"targetNames": MORPH_NAMES}} if morph else {})}],
        "skins": [{"joints": [1, 2, 3], "inverseBindMatrices": ibm_acc, "skeleton": 1}],
        "animations": animations,
        "accessors": accessors,
        "bufferViews": views,
        "buffers": [{"byteLength": len(blob)}],
    }
    if extra:
        doc.update(extra)
    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    if buffer_mode == "data":
        doc["buffers"][0]["uri"] = "data:application/octet-stream;base64," + base64.b64encode(bytes(blob)).decode()
    else:
        uri = external_uri or "test.bin"
        doc["buffers"][0]["uri"] = uri
        target = (folder / uri)
        target.parent.mkdir(parents=True, exist_ok=True)
        target.write_bytes(bytes(blob))
    path = folder / name
    path.write_text(json.dumps(doc))
    return path


def expected_skinning(key: int, armature_scale=1.0, armature_rotation=False, interpolation="LINEAR") -> np.ndarray:
    """World positions of the 6 vertices at key `key`, by the glTF spec, with plain matrices."""
    arm = armature_matrix(armature_scale, armature_rotation)
    rot = tf.quat_from_axis_angle([0.0, 0.0, 1.0], MID_ANGLES[key])
    root = arm @ tf.trs_to_mat4(ROOT_MOVES[key], np.array([0, 0, 0, 1.0]), np.ones(3))
    mid = root @ tf.trs_to_mat4(JOINT_T[1], rot, np.ones(3))
    tip = mid @ tf.trs_to_mat4(JOINT_T[2], np.array([0, 0, 0, 1.0]), np.ones(3))
    bind = [arm, arm @ tf.trs_to_mat4(JOINT_T[1], np.array([0, 0, 0, 1.0]), np.ones(3))]
    bind.append(bind[1] @ tf.trs_to_mat4(JOINT_T[2], np.array([0, 0, 0, 1.0]), np.ones(3)))
    skin = np.array([root, mid, tip]) @ np.linalg.inv(np.array(bind))
    w = WEIGHTS / WEIGHTS.sum(1, keepdims=True)
    p = np.concatenate([POSITIONS.astype(np.float64), np.ones((6, 1))], 1)
    out = np.zeros((6, 3))
    for k in range(4):
        out += w[:, k, None] * np.einsum("vij,vj->vi", skin[JOINTS[:, k]], p)[:, :3]
    return out


# -- a second skin in the same file (issue 18, point 1: several skins)

OFFSET = tf.trs_to_mat4(np.array([0.2, -0.5, 0.3]), tf.quat_from_axis_angle([0.0, 1.0, 0.0], 0.7), np.ones(3))
EXTRA_POSITIONS = np.array([[-0.15, 1.8, 0.05], [0.15, 1.8, 0.05], [-0.15, 2.1, 0.05], [0.15, 2.1, 0.05]])
EXTRA_WEIGHTS = np.array([[0.6, 0.4, 0, 0], [1, 0, 0, 0], [0.8, 0.2, 0, 0], [0.5, 0.5, 0, 0]])
EXTRA_JOINTS = np.array([[0, 1, 0, 0], [0, 0, 0, 0], [1, 2, 0, 0], [2, 0, 0, 0]])
EXTRA_INDICES = np.array([0, 1, 2, 2, 1, 3], dtype=np.uint16)


def bind_worlds(armature_scale=1.0, armature_rotation=False) -> np.ndarray:
    """World transforms of root, mid and tip at bind time (the rest pose), with plain matrices."""
    arm = armature_matrix(armature_scale, armature_rotation)
    out = [arm @ tf.trs_to_mat4(JOINT_T[0], np.array([0, 0, 0, 1.0]), np.ones(3))]
    for k in (1, 2):
        out.append(out[-1] @ tf.trs_to_mat4(JOINT_T[k], np.array([0, 0, 0, 1.0]), np.ones(3)))
    return np.array(out)


def joint_worlds(key: int, armature_scale=1.0, armature_rotation=False) -> np.ndarray:
    """World transforms of root, mid and tip at clip key `key`, by the glTF spec, with plain matrices."""
    arm = armature_matrix(armature_scale, armature_rotation)
    rot = tf.quat_from_axis_angle([0.0, 0.0, 1.0], MID_ANGLES[key])
    root = arm @ tf.trs_to_mat4(ROOT_MOVES[key], np.array([0, 0, 0, 1.0]), np.ones(3))
    mid = root @ tf.trs_to_mat4(JOINT_T[1], rot, np.ones(3))
    tip = mid @ tf.trs_to_mat4(JOINT_T[2], np.array([0, 0, 0, 1.0]), np.ones(3))
    return np.array([root, mid, tip])


def add_skin(path: Path, mode: str, name: str | None = None, armature_scale=1.0, armature_rotation=False) -> dict:
    """Post-edit a make_gltf file: add a skin, a mesh drawn with it and its node(s); the binary data goes
    in a buffer of its own (a base64 data URI). Call it again for a third skin. Modes:
    - "visor": a skin over [tip, mid] with the main skin's inverse binds (merged, no duplicates);
    - "offset": a skin over [mid, tip, root] whose inverse binds are the main ones times OFFSET, its mesh
      written in that bind space (p' = OFFSET^-1 p), so it skins exactly as EXTRA_POSITIONS in the main
      bind space would (merged, every joint duplicated);
    - "separate": a second chain root2 → mid2 → tip2 under its own armature node 3 m along x, with the
      strip on it (another character: left out).
    Returns what the file holds, for the test's own computation: skin (its index), joints (the chain
    index, 0 root to 2 tip, of each skin joint; None for "separate"), nodes (the joint nodes),
    inverse_bind (row-major float64 of the written float32), positions (float64 of the written float32),
    vertex_joints, weights (normalised), mesh (its name)."""
    path = Path(path)
    doc = json.loads(path.read_text())
    blob = bytearray()
    buffer = len(doc["buffers"])
    nodes, accessors, views = doc["nodes"], doc["accessors"], doc["bufferViews"]
    skin = len(doc["skins"])

    def add(arr: np.ndarray, ctype: int, kind: str) -> int:
        while len(blob) % 4:
            blob.append(0)
        views.append({"buffer": buffer, "byteOffset": len(blob), "byteLength": arr.nbytes})
        blob.extend(arr.tobytes())
        accessors.append({"bufferView": len(views) - 1, "componentType": ctype, "count": int(arr.shape[0]), "type": kind})
        return len(accessors) - 1

    main_ibm = np.linalg.inv(bind_worlds(armature_scale, armature_rotation))
    if mode == "visor":
        chain, pos = [2, 1], EXTRA_POSITIONS
        ibm = main_ibm[chain]
        joint_nodes = [1 + c for c in chain]
    elif mode == "offset":
        chain = [1, 2, 0]
        ibm = main_ibm[chain] @ OFFSET
        p = np.concatenate([EXTRA_POSITIONS, np.ones((4, 1))], 1)
        pos = (np.linalg.inv(OFFSET) @ p.T).T[:, :3]
        joint_nodes = [1 + c for c in chain]
    elif mode == "separate":
        first = len(nodes)
        nodes.append({"name": "Armature2", "translation": [3.0, 0.0, 0.0], "children": [first + 1]})
        nodes.append({"name": "root2", "children": [first + 2]})
        nodes.append({"name": "mid2", "translation": JOINT_T[1].tolist(), "children": [first + 3]})
        nodes.append({"name": "tip2", "translation": JOINT_T[2].tolist()})
        doc["scenes"][0]["nodes"].append(first)
        shift = tf.trs_to_mat4(np.array([3.0, 0.0, 0.0]), np.array([0, 0, 0, 1.0]), np.ones(3))
        ibm = np.linalg.inv(shift @ bind_worlds())
        chain, joint_nodes = None, [first + 1, first + 2, first + 3]
        pos = POSITIONS.astype(np.float64) + [3.0, 0.0, 0.0]
    else:
        raise ValueError(f"unknown mode {mode!r}")
    if mode == "separate":
        vjoints, weights, indices = JOINTS, WEIGHTS, np.array([0, 1, 2, 2, 1, 3, 2, 3, 4, 4, 3, 5], dtype=np.uint16)
    else:
        vjoints, weights, indices = EXTRA_JOINTS.copy(), EXTRA_WEIGHTS, EXTRA_INDICES
        vjoints[vjoints >= len(joint_nodes)] = 0
    pos32 = pos.astype(np.float32)
    ibm32 = np.transpose(ibm, (0, 2, 1)).astype(np.float32).reshape(-1, 16)
    pos_acc = add(pos32, 5126, "VEC3")
    accessors[-1]["min"], accessors[-1]["max"] = pos32.min(0).tolist(), pos32.max(0).tolist()
    nrm_acc = add(np.tile(np.array([[0, 0, 1]], dtype=np.float32), (len(pos), 1)), 5126, "VEC3")
    j_acc = add(vjoints.astype(np.uint8), 5121, "VEC4")
    w_acc = add(weights.astype(np.float32), 5126, "VEC4")
    i_acc = add(indices, 5123, "SCALAR")
    ibm_acc = add(ibm32, 5126, "MAT4")
    mesh_name = f"{mode}{skin}"
    doc["meshes"].append({"name": mesh_name, "primitives": [{"attributes": {"POSITION": pos_acc, "NORMAL": nrm_acc, "JOINTS_0": j_acc,
                                                                         "WEIGHTS_0": w_acc}, "indices": i_acc}]})
    skin_obj = {"joints": joint_nodes, "inverseBindMatrices": ibm_acc}
    if name is not None:
        skin_obj["name"] = name
    doc["skins"].append(skin_obj)
    nodes.append({"name": mesh_name, "mesh": len(doc["meshes"]) - 1, "skin": skin})
    doc["scenes"][0]["nodes"].append(len(nodes) - 1)
    doc["buffers"].append({"byteLength": len(blob),
                           "uri": "data:application/octet-stream;base64," + base64.b64encode(bytes(blob)).decode()})
    path.write_text(json.dumps(doc))
    return {"skin": skin, "joints": chain, "nodes": joint_nodes, "mesh": mesh_name,
            "inverse_bind": ibm32.astype(np.float64).reshape(-1, 4, 4).transpose(0, 2, 1),
            "positions": pos32.astype(np.float64), "vertex_joints": vjoints,
            "weights": weights / weights.sum(1, keepdims=True)}


def expected_extra_skinning(extra: dict, key: int, armature_scale=1.0, armature_rotation=False) -> np.ndarray:
    """World positions of an add_skin mesh ("visor" or "offset") at clip key `key`, by the glTF spec:
    Σ w · world(joint) · inverse_bind(skin, joint) · p, with plain matrices."""
    worlds = joint_worlds(key, armature_scale, armature_rotation)[extra["joints"]]
    skin = worlds @ extra["inverse_bind"]
    p = np.concatenate([extra["positions"], np.ones((len(extra["positions"]), 1))], 1)
    out = np.zeros((len(p), 3))
    for k in range(4):
        out += extra["weights"][:, k, None] * np.einsum("vij,vj->vi", skin[extra["vertex_joints"][:, k]], p)[:, :3]
    return out


# -- modular characters: many pieces on one skeleton (issue 40, point 1: merging, and the cull's extremes)

PART_HALF = 0.035  # half the side of a piece's box, metres
MODULAR_COLOURS = np.array([[0.80, 0.20, 0.15, 1.0], [0.15, 0.55, 0.25, 1.0], [0.20, 0.30, 0.80, 1.0], [0.85, 0.75, 0.20, 1.0],
                            [0.55, 0.25, 0.65, 1.0], [0.90, 0.55, 0.35, 1.0], [0.35, 0.75, 0.80, 1.0], [0.25, 0.20, 0.15, 1.0]])


def modular_gltf(folder: Path, pieces: int = 40, joints: int = 32, materials: int = 6, apart: str | None = None,
                 groups: dict[str, int] | None = None, primitives_per_mesh: int = 1, lods: int = 1,
                 name: str = "modular.gltf") -> Path:
    """Writes a valid skinned glTF (buffers as a data URI) of a modular character: `pieces` skinned
    primitives at each LOD on one skeleton, each a small box on its own joint (spread over the whole
    figure, so a picture shows every piece), and returns its path.

    - `joints`: the skeleton (at least 2): a root at the hips and five chains from it (spine to the head,
      two arms, two legs) sharing the other joints, the figure about 1.8 m tall, standing on y = 0.
    - `materials`: how many distinct flat materials (base colour factors, no texture) the pieces cycle
      through; 0 gives them none. Pieces that differ only so share one draw once merged.
    - `apart`: what keeps pieces from sharing a draw. None: nothing (the common pieces merge into one draw
      a LOD, each variation choice's primitives into one). "texture": each primitive its own material with
      its own 4x4 PNG (the same across its LODs; the importer takes at most 256 images). "morph": each mesh
      its own morph target set (one target, "<piece>.swell", at every LOD of the piece; the "Idle" clip keys
      its weight), so each mesh is its own draw and the primitives of one mesh share theirs.
      With "texture", or "morph" and one primitive a mesh, every primitive is its own draw: `pieces`
      draws a LOD reach the renderer.
    - `groups`: variation groups, group name → number of choices ({"head": 3}: pieces "head_a" ..
      "head_c", written as extras.crowd {"group": "head", "piece": "head_b"}); each choice is one mesh of
      `primitives_per_mesh` primitives, counted in `pieces`; the rest of `pieces` are worn by every agent.
    - `primitives_per_mesh`: primitives each glTF mesh holds (the last common mesh may hold fewer); a
      mesh's primitives are one piece (extras.crowd.piece "part<k>").
    - `lods`: LODs written, each mesh again with extras.crowd.lod k and coarser shapes (LOD0 a box of 12
      triangles, LOD1 a pyramid of 6, coarser a tetrahedron of 4).
    Clips: "Idle" (every joint sways about z, looping; with apart="morph" the targets swell and back) and
    "Walk" (the limbs swing about x)."""
    from io import BytesIO

    from PIL import Image

    groups = dict(groups or {})
    choice_primitives = sum(groups.values()) * primitives_per_mesh
    if joints < 2 or pieces < 1 or choice_primitives > pieces or primitives_per_mesh < 1 or lods < 1 or apart not in (None, "texture", "morph"):
        raise ValueError("modular_gltf: joints >= 2, 1 <= pieces, groups' primitives within pieces, primitives_per_mesh >= 1, "
                         "lods >= 1, apart None, 'texture' or 'morph'")
    blob = bytearray()
    views, accessors = [], []

    def add(arr: np.ndarray, ctype: int, kind: str, minmax=False, target=None) -> int:
        while len(blob) % 4:
            blob.append(0)
        views.append({"buffer": 0, "byteOffset": len(blob), "byteLength": arr.nbytes, **({"target": target} if target else {})})
        blob.extend(np.ascontiguousarray(arr).tobytes())
        acc = {"bufferView": len(views) - 1, "componentType": ctype, "count": int(arr.shape[0]), "type": kind}
        if minmax:
            flat = arr.reshape(len(arr), -1)
            acc["min"], acc["max"] = flat.min(0).tolist(), flat.max(0).tolist()
        accessors.append(acc)
        return len(accessors) - 1

    # The skeleton: joint 0 the root; chain c's joints evenly from its start to its end, the first a child of the root.
    chains = [((0.0, 1.08, 0.0), (0.0, 1.72, 0.0)), ((0.2, 1.45, 0.0), (0.8, 1.45, 0.0)), ((-0.2, 1.45, 0.0), (-0.8, 1.45, 0.0)),
              ((0.14, 0.85, 0.0), (0.14, 0.08, 0.0)), ((-0.14, 0.85, 0.0), (-0.14, 0.08, 0.0))]
    world, parent, chain_of = [np.array([0.0, 0.95, 0.0])], [-1], [-1]
    for c, (start, end) in enumerate(chains):
        n = (joints - 1) // 5 + (1 if c < (joints - 1) % 5 else 0)
        for k in range(n):
            world.append(np.array(start) + (np.array(end) - np.array(start)) * (k / (n - 1) if n > 1 else 0.0))
            parent.append(0 if k == 0 else len(world) - 2)
            chain_of.append(c)
    world = np.array(world)
    nodes = [{"name": "Armature", "children": [1]}]
    for j in range(joints):
        local = world[j] - (world[parent[j]] if parent[j] >= 0 else 0.0)
        node = {"name": "root" if j == 0 else f"joint{j}", "translation": local.tolist()}
        children = [1 + i for i in range(joints) if parent[i] == j]
        if children:
            node["children"] = children
        nodes.append(node)
    ibm = np.tile(np.eye(4), (joints, 1, 1))
    ibm[:, :3, 3] = -world
    ibm_acc = add(np.transpose(ibm, (0, 2, 1)).astype(np.float32).reshape(joints, 16), 5126, "MAT4")

    # Where each primitive sits: spread over the joints, those sharing a joint on a ring about it, across
    # its chain (the arms' rings stand upright), so that no two boxes touch.
    on_joint = [i % joints if pieces >= joints else i * joints // pieces for i in range(pieces)]
    centres = []
    for i in range(pieces):
        j = on_joint[i]
        count = pieces // joints + (1 if j < pieces % joints else 0) if pieces >= joints else 1
        angle = 2 * np.pi * (i // joints) / count
        ring = [0.0, np.cos(angle), np.sin(angle)] if chain_of[j] in (1, 2) else [np.cos(angle), 0.0, np.sin(angle)]
        centres.append(world[j] + (0.075 * np.array(ring) if count > 1 else 0.0))

    images, textures, samplers, mats = [], [], [], []
    if apart == "texture":
        samplers.append({"magFilter": 9728, "minFilter": 9728})
        for i in range(pieces):
            a, b = MODULAR_COLOURS[i % len(MODULAR_COLOURS)], MODULAR_COLOURS[(i * 3 + 1) % len(MODULAR_COLOURS)]
            check = np.where(((np.arange(4)[:, None] + np.arange(4)[None, :] + i) % 2)[..., None] == 0, a, b)
            png = BytesIO()
            Image.fromarray((check * 255).round().astype(np.uint8), "RGBA").save(png, format="PNG")
            data = np.frombuffer(png.getvalue(), np.uint8)
            while len(blob) % 4:
                blob.append(0)
            views.append({"buffer": 0, "byteOffset": len(blob), "byteLength": len(data)})
            blob.extend(data.tobytes())
            images.append({"bufferView": len(views) - 1, "mimeType": "image/png", "name": f"part{i}"})
            textures.append({"source": i, "sampler": 0})
            mats.append({"name": f"textured{i}", "pbrMetallicRoughness": {"baseColorTexture": {"index": i}}})
    else:
        mats = [{"name": f"flat{m}", "pbrMetallicRoughness": {"baseColorFactor": MODULAR_COLOURS[m % len(MODULAR_COLOURS)].tolist()}}
                for m in range(materials)]

    # The meshes: the common pieces (primitives_per_mesh each), then each group's choices.
    units = []  # (piece, group, its primitives' indices)
    common = pieces - choice_primitives
    for u, first in enumerate(range(0, common, primitives_per_mesh)):
        units.append((f"part{u}", "", list(range(first, min(first + primitives_per_mesh, common)))))
    first = common
    for group, choices in groups.items():
        for c in range(choices):
            units.append((f"{group}_{chr(ord('a') + c)}", group, list(range(first, first + primitives_per_mesh))))
            first += primitives_per_mesh
    meshes, mesh_nodes = [], []
    for lod in range(lods):
        for piece, group, parts in units:
            prims = []
            for i in parts:
                pos, nrm, uv, idx = _part_shape(centres[i], lod)
                j = on_joint[i]
                vj = np.tile([j, max(parent[j], 0), 0, 0], (len(pos), 1)).astype(np.uint8)
                vw = np.tile([0.8, 0.2, 0.0, 0.0] if parent[j] >= 0 else [1.0, 0.0, 0.0, 0.0], (len(pos), 1)).astype(np.float32)
                attributes = {"POSITION": add(pos, 5126, "VEC3", minmax=True, target=34962), "NORMAL": add(nrm, 5126, "VEC3", target=34962),
                              "JOINTS_0": add(vj, 5121, "VEC4", target=34962), "WEIGHTS_0": add(vw, 5126, "VEC4", target=34962)}
                prim = {"attributes": attributes, "indices": add(idx, 5123, "SCALAR", target=34963)}
                if apart == "texture":
                    attributes["TEXCOORD_0"] = add(uv, 5126, "VEC2", target=34962)
                    prim["material"] = i
                elif mats:
                    prim["material"] = i % len(mats)
                if apart == "morph":
                    prim["targets"] = [{"POSITION": add(((pos - centres[i]) * 0.5).astype(np.float32), 5126, "VEC3", minmax=True, target=34962)}]
                prims.append(prim)
            crowd = {"piece": piece, "lod": lod, **({"group": group} if group else {})}
            mesh = {"name": f"{piece}_lod{lod}", "primitives": prims, "extras": {"crowd": crowd}}
            if apart == "morph":
                mesh["extras"]["targetNames"] = [f"{piece}.swell"]
                mesh["weights"] = [0.0]
            meshes.append(mesh)
            nodes.append({"name": mesh["name"], "mesh": len(meshes) - 1, "skin": 0})
            mesh_nodes.append(len(nodes) - 1)

    # The clips.
    sway_t = add(np.array([0.0, 0.5, 1.0], np.float32), 5126, "SCALAR", minmax=True)
    walk_t = add(np.array([0.0, 0.25, 0.5, 0.75, 1.0], np.float32), 5126, "SCALAR", minmax=True)
    idle, walk = {"name": "Idle", "samplers": [], "channels": []}, {"name": "Walk", "samplers": [], "channels": []}
    for j in range(joints):
        keys = tf.quat_from_axis_angle([0.0, 0.0, 1.0], np.array([0.0, 0.12 * np.sin(j + 1.0), 0.0]))
        idle["samplers"].append({"input": sway_t, "output": add(keys.astype(np.float32), 5126, "VEC4")})
        idle["channels"].append({"sampler": len(idle["samplers"]) - 1, "target": {"node": 1 + j, "path": "rotation"}})
        if j and parent[j] == 0 and chain_of[j] > 0:  # the first joint of a limb
            swing = 0.4 * (1 if chain_of[j] in (1, 4) else -1)
            keys = tf.quat_from_axis_angle([1.0, 0.0, 0.0], np.array([0.0, swing, 0.0, -swing, 0.0]))
            walk["samplers"].append({"input": walk_t, "output": add(keys.astype(np.float32), 5126, "VEC4")})
            walk["channels"].append({"sampler": len(walk["samplers"]) - 1, "target": {"node": 1 + j, "path": "rotation"}})
    if apart == "morph":
        swell = add(np.array([[0.0], [1.0], [0.0]], np.float32), 5126, "SCALAR")
        idle["samplers"].append({"input": sway_t, "output": swell})
        for n in mesh_nodes:
            idle["channels"].append({"sampler": len(idle["samplers"]) - 1, "target": {"node": n, "path": "weights"}})
    animations = [idle] + ([walk] if walk["channels"] else [])

    doc = {"asset": {"version": "2.0", "generator": "tests/gltf_factory.py modular_gltf"}, "scene": 0,
           "scenes": [{"nodes": [0, *mesh_nodes]}], "nodes": nodes, "meshes": meshes,
           "skins": [{"joints": list(range(1, joints + 1)), "inverseBindMatrices": ibm_acc, "skeleton": 1}],
           "animations": animations, "accessors": accessors, "bufferViews": views}
    for key, value in (("materials", mats), ("textures", textures), ("images", images), ("samplers", samplers)):
        if value:
            doc[key] = value
    doc["buffers"] = [{"byteLength": len(blob), "uri": "data:application/octet-stream;base64," + base64.b64encode(bytes(blob)).decode()}]
    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    path = folder / name
    path.write_text(json.dumps(doc))
    return path


def _part_shape(centre: np.ndarray, lod: int) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """(positions, normals, uvs, uint16 indices) of one piece at `lod`, flat-shaded: a box at LOD0, a
    pyramid at LOD1, a tetrahedron beyond; each triangle's corners take uvs (0, 0), (1, 0), (1, 1)."""
    h = PART_HALF
    corners = np.array([[x, y, z] for x in (-h, h) for y in (-h, h) for z in (-h, h)])
    if lod == 0:
        quads = [(0, 1, 3, 2), (4, 6, 7, 5), (0, 4, 5, 1), (2, 3, 7, 6), (0, 2, 6, 4), (1, 5, 7, 3)]
        faces = [(q[0], q[1], q[2]) for q in quads] + [(q[0], q[2], q[3]) for q in quads]
        points = corners
    elif lod == 1:
        points = np.array([[-h, -h, -h], [h, -h, -h], [h, -h, h], [-h, -h, h], [0.0, h, 0.0]])
        faces = [(0, 1, 2), (0, 2, 3), (0, 4, 1), (1, 4, 2), (2, 4, 3), (3, 4, 0)]
    else:
        points = np.array([[-h, -h, -h], [h, -h, h], [-h, h, h], [h, h, -h]])
        faces = [(0, 1, 2), (0, 3, 1), (0, 2, 3), (1, 3, 2)]
    tri = points[np.array(faces)]  # (T, 3, 3)
    normal = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    outward = np.sign(np.sum(normal * tri.mean(axis=1), axis=1))[:, None]  # (each shape holds its centre) -1: wound inward, flipped
    tri = np.where(outward[..., None] < 0, tri[:, ::-1], tri)
    normal = normal * outward
    normal /= np.linalg.norm(normal, axis=1, keepdims=True)
    positions = (tri.reshape(-1, 3) + centre).astype(np.float32)
    normals = np.repeat(normal, 3, axis=0).astype(np.float32)
    uvs = np.tile([[0.0, 0.0], [1.0, 0.0], [1.0, 1.0]], (len(faces), 1)).astype(np.float32)
    return positions, normals, uvs, np.arange(len(positions), dtype=np.uint16)


MORPH_ONLY_TRANSLATION = np.array([0.3, 0.0, -0.2])  # the mesh node's place
MORPH_ONLY_TURNS = np.array([0.0, 0.6, 1.2])  # radians about Y at KEY_TIMES: the node's own animation


def morph_only_gltf(folder: Path, name: str = "morph_only.gltf", turn: bool = True) -> Path:
    """make_gltf(morph=True) without its skin: the mesh has no JOINTS_0/WEIGHTS_0, its node stands at
    MORPH_ONLY_TRANSLATION, and the one clip keys the morph weights (MORPH_KEYS) and, with `turn`, the
    node's rotation about Y (MORPH_ONLY_TURNS), as vertex-animated files are made."""
    path = make_gltf(folder, name, morph=True)
    doc = json.loads(path.read_text())
    doc.pop("skins")
    body = doc["nodes"][4]
    body.pop("skin")
    body["translation"] = MORPH_ONLY_TRANSLATION.tolist()
    attributes = doc["meshes"][0]["primitives"][0]["attributes"]
    attributes.pop("JOINTS_0")
    attributes.pop("WEIGHTS_0")
    anim = doc["animations"][0]
    weights = next(c for c in anim["channels"] if c["target"]["path"] == "weights")
    anim["channels"] = [dict(weights, sampler=0)]
    anim["samplers"] = [anim["samplers"][weights["sampler"]]]
    if turn:
        add_channel(doc, 4, "rotation", tf.quat_from_axis_angle([0.0, 1.0, 0.0], MORPH_ONLY_TURNS))
    path.write_text(json.dumps(doc))
    return path


def add_channel(doc: dict, node: int, path: str, keys: np.ndarray) -> None:
    """A channel keying `node`'s `path` at KEY_TIMES (one key a row of `keys`, LINEAR) in the first
    animation of a make_gltf document (its buffer a data URI), the keys appended to the buffer."""
    blob = bytearray(base64.b64decode(doc["buffers"][0]["uri"].split(",", 1)[1]))
    values = np.asarray(keys, np.float32)
    while len(blob) % 4:
        blob.append(0)
    doc["bufferViews"].append({"buffer": 0, "byteOffset": len(blob), "byteLength": values.nbytes})
    blob.extend(values.tobytes())
    doc["accessors"].append({"bufferView": len(doc["bufferViews"]) - 1, "componentType": 5126, "count": int(values.shape[0]),
                             "type": {3: "VEC3", 4: "VEC4"}[values.shape[1]]})
    anim = doc["animations"][0]
    times = next(doc["accessors"].index(a) for a in doc["accessors"] if a.get("min") is not None and a["type"] == "SCALAR")
    anim["samplers"].append({"input": times, "output": len(doc["accessors"]) - 1})
    anim["channels"].append({"sampler": len(anim["samplers"]) - 1, "target": {"node": node, "path": path}})
    doc["buffers"][0] = {"byteLength": len(blob), "uri": "data:application/octet-stream;base64," + base64.b64encode(bytes(blob)).decode()}


def glb_parts(path: Path) -> tuple[dict, bytes]:
    """A GLB's JSON and binary chunk."""
    import struct

    data = Path(path).read_bytes()
    n = struct.unpack_from("<I", data, 12)[0]
    return json.loads(data[20:20 + n]), data[20 + n + 8:]


def write_glb(path: Path, doc: dict, blob: bytes) -> Path:
    """A GLB of `doc` (its JSON padded with spaces) and `blob` as they are."""
    import struct

    js = json.dumps(doc).encode()
    js += b" " * (-len(js) % 4)
    body = struct.pack("<I4s", len(js), b"JSON") + js + struct.pack("<I4s", len(blob), b"BIN\x00") + bytes(blob)
    Path(path).write_bytes(b"glTF" + struct.pack("<II", 2, 12 + len(body)) + body)
    return Path(path)


DRACO_POSITION_BITS = 16  # the copies' position quantisation: a vertex within its box's size / 2^16 of the plain file's


def draco_copy(source: Path, target: Path) -> dict:
    """A copy of the GLB `source` with every skinned primitive Draco-compressed (KHR_draco_mesh_compression,
    DracoPy's encoder, vertex order kept), its accessors' plain data no longer referenced. Returns
    {mesh name: the position box's size} for the tolerance."""
    import DracoPy

    doc, blob = glb_parts(source)
    blob = bytearray(blob)
    dtypes = {5120: np.int8, 5121: np.uint8, 5122: np.int16, 5123: np.uint16, 5125: np.uint32, 5126: np.float32}
    sizes = {"SCALAR": 1, "VEC2": 2, "VEC3": 3, "VEC4": 4}

    def raw(index):
        acc = doc["accessors"][index]
        view = doc["bufferViews"][acc["bufferView"]]
        n = acc["count"] * sizes[acc["type"]]
        return np.frombuffer(bytes(blob), dtypes[acc["componentType"]], n, view.get("byteOffset", 0) + acc.get("byteOffset", 0)).reshape(acc["count"], -1)

    boxes = {}
    for mesh in doc["meshes"]:
        for prim in mesh["primitives"]:
            attributes = prim["attributes"]
            if "JOINTS_0" not in attributes:
                continue
            points = raw(attributes["POSITION"]).astype(np.float64)
            faces = raw(prim["indices"]).reshape(-1, 3).astype(np.int64)
            boxes[mesh.get("name")] = float(np.max(points.max(0) - points.min(0)))
            generic = {semantic: k for k, semantic in enumerate(s for s in attributes if s not in ("POSITION", "NORMAL"))}
            encoded = DracoPy.encode(points, faces, quantization_bits=DRACO_POSITION_BITS, preserve_order=True,
                                     normals=raw(attributes["NORMAL"]).astype(np.float64) if "NORMAL" in attributes else None,
                                     generic_attributes={k: raw(attributes[s]) for s, k in generic.items()})
            decoded = DracoPy.decode(encoded)
            ids = {"POSITION": next(a["unique_id"] for a in decoded.attributes if a["attribute_type"] == 0)}
            if "NORMAL" in attributes:
                ids["NORMAL"] = next(a["unique_id"] for a in decoded.attributes if a["attribute_type"] == 1)
            ids.update(generic)
            while len(blob) % 4:
                blob.append(0)
            doc["bufferViews"].append({"buffer": 0, "byteOffset": len(blob), "byteLength": len(encoded)})
            blob.extend(encoded)
            prim.setdefault("extensions", {})["KHR_draco_mesh_compression"] = {"bufferView": len(doc["bufferViews"]) - 1, "attributes": ids}
            for index in [*(attributes[s] for s in ids), prim["indices"]]:
                doc["accessors"][index].pop("bufferView", None)
                doc["accessors"][index].pop("byteOffset", None)
    for key in ("extensionsUsed", "extensionsRequired"):
        doc[key] = sorted(set(doc.get(key, [])) | {"KHR_draco_mesh_compression"})
    while len(blob) % 4:
        blob.append(0)
    doc["buffers"][0]["byteLength"] = len(blob)
    write_glb(target, doc, blob)
    return boxes


def clipless_gltf(folder: Path, name: str = "body.gltf") -> Path:
    """make_gltf's skinned character with no animations: a body whose clips come from elsewhere."""
    path = make_gltf(folder, name)
    doc = json.loads(path.read_text())
    doc.pop("animations")
    path.write_text(json.dumps(doc))
    return path


def library_gltf(folder: Path, name: str = "library.gltf", mid_length: float | None = None) -> Path:
    """make_gltf's rig and clip without its skin or mesh (as Mixamo's animations come without the
    character): the nodes and the animation alone. `mid_length`: the "mid" joint's rest offset made this
    long, with translation keys on it, as a rig of other proportions would be."""
    path = make_gltf(folder, name)
    doc = json.loads(path.read_text())
    for key in ("skins", "meshes"):
        doc.pop(key)
    doc["nodes"][4] = {"name": "empty"}
    if mid_length is not None:
        doc["nodes"][2]["translation"] = [0.0, float(mid_length), 0.0]
        add_channel(doc, 2, "translation", np.tile([0.0, float(mid_length), 0.0], (3, 1)))
    path.write_text(json.dumps(doc))
    return path
