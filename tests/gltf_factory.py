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
