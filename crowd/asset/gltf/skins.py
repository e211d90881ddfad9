"""The skeleton: the skins that draw meshes, merged where they form one joint tree, their joints sorted
parents-first, with rest transforms (non-joint nodes folded in, a uniform scale above the root joints
factored out) and inverse binds.

Several skins. The main skin is the one most mesh nodes draw with (ties: the lowest index). Another skin
whose joints all hang, in the joint forest of the joints of every skin drawing a mesh, in a tree that
holds a joint of the main skin (a visor over the head joints, a second hand skin over the arm) is merged
into one skeleton on the union of the joints (the main skin's first, in its order; then the others' new
ones), with one warning. A joint takes the inverse bind of the first skin that lists it; a skin that
lists it with another inverse bind draws through a duplicate joint, "name@skinK": a child of that joint
at identity rest, without channels, with that skin's inverse bind, so world @ inverse bind is exactly
what glTF means. A skin on another joint tree is another character: left out, one warning.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ... import transforms as tf
from ..model import Skeleton
from .reader import FLOAT_TYPES, Reader, check_matrices, is_whole
from .tree import Fold, Tree, joint_tops

MAX_JOINTS = 1 << 16  # SkinnedMesh.joints is uint16


@dataclass
class Rig:
    """The skeleton of the merged skins, and how the file's nodes and skins map onto its joints."""

    skeleton: Skeleton
    joint_index: dict[int, int]  # joint node -> its joint in the skeleton
    skin_maps: dict[int, np.ndarray]  # merged skin k -> the skeleton joint of each of its joints
    folds: list[Fold | None]  # per joint: the non-joint nodes above it, folded into its local transform
    factor: float  # the uniform scale factored out above the root joints


def skin_of_nodes(r: Reader) -> dict[int, int] | None:
    """A file without a skin (the classic vertex-animated birds and horses, morph test files): one skin is
    made whose joints are the nodes that draw meshes, each mesh weighted wholly to its own node, with
    identity inverse binds (the bind pose is where the nodes stand), so its node animation and morph
    weights play as any character's. Returns node -> its joint in that skin, or None where the file has
    a skin (which is then used as it is)."""
    if r.array("skins"):
        return None
    nodes = r.array("nodes")
    drawn = [i for i, n in enumerate(nodes) if isinstance(n, dict) and n.get("mesh") is not None]
    if not drawn:
        r.fail("no skin and no node draws a mesh: nothing to draw")
    r.doc["skins"] = [{"name": "nodes", "joints": drawn}]
    for i in drawn:
        nodes[i]["skin"] = 0
    r.warnings.append(f"no skin: the {len(drawn)} node{'s' if len(drawn) > 1 else ''} drawing meshes made the skeleton "
                      "(node animation and morph weights play; each mesh moves with its node)")
    return {node: k for k, node in enumerate(drawn)}


def read_skeleton(r: Reader, tree: Tree) -> Rig:
    """The skeleton of the skins that draw meshes (tree.joints becomes its joint nodes)."""
    nodes = tree.nodes
    warn = r.warnings

    skins = r.array("skins")
    if not skins:
        r.fail("no skin: this importer needs a skinned character")
    skin_use: dict[int, int] = {}
    for i, n in enumerate(nodes):
        where = r.node_where(i)
        mesh, skin = r.index(n, "mesh", "meshes", where), r.index(n, "skin", "skins", where)
        if mesh is not None and skin is not None:
            skin_use[skin] = skin_use.get(skin, 0) + 1
    if not skin_use:
        r.fail("no node draws a mesh with a skin")
    skin_index = max(skin_use, key=lambda k: (skin_use[k], -k))
    # Every skin that draws a mesh is checked; those that hang in the main skin's joint trees are merged.
    skin_joints = {skin_index: _skin_joints(r, skin_index)}
    for k in sorted(skin_use):
        if k != skin_index:
            skin_joints[k] = _skin_joints(r, k)
    merged = _mergeable_skins(r, tree, skin_index, skin_joints, warn)
    # The union: the main skin's joints in its order, then the other skins' new joints in skin order.
    src_joints = list(skin_joints[skin_index])
    listed = set(src_joints)
    for k in merged[1:]:
        for j in skin_joints[k]:
            if j not in listed:
                listed.add(j)
                src_joints.append(j)
    skinned = len(src_joints)  # (the joints after these are animated nodes above them: no skin lists them)
    for node in animated_ancestors(r, tree, listed):
        listed.add(node)
        src_joints.append(node)
    if len(src_joints) > MAX_JOINTS:
        r.fail(f"skins {', '.join(map(str, merged))} have {len(src_joints):,} joints together, more than the {MAX_JOINTS:,} a vertex can address")
    tree.joints = listed
    joint_parent = tree.joint_above

    # Parents-first order, stable in the union's order.
    position = {j: i for i, j in enumerate(src_joints)}
    depth: dict[int, int] = {}
    for j in src_joints:
        chain, k = [], j
        while k is not None and k not in depth:
            chain.append(k)
            k = joint_parent(k)
        d = -1 if k is None else depth[k]
        for k in reversed(chain):
            d += 1
            depth[k] = d
    order = sorted(src_joints, key=lambda j: (depth[j], position[j]))
    new_index = {node: i for i, node in enumerate(order)}
    jc = len(order)
    names, seen = [], set()
    for i, node in enumerate(order):
        name = nodes[node].get("name")
        name = name if isinstance(name, str) and name else f"joint{i}"
        while name in seen:  # the first repeat gets ".i"; a name that still clashes gets it again
            name = f"{name}.{i}"
        seen.add(name)
        names.append(name)
    parent_list = [new_index[joint_parent(n)] if joint_parent(n) is not None else -1 for n in order]

    rest_t = np.zeros((jc, 3))
    rest_q = np.zeros((jc, 4))
    rest_s = np.zeros((jc, 3))
    folds: list[Fold | None] = []
    for i, node in enumerate(order):
        t, q, s, shear = r.trs(node)
        if shear > 1e-5:
            warn.append(f"joint {names[i]!r} matrix has shear {shear:.2g}; approximated by TRS")
        above = tree.between(node)
        fold = None if above is None else Fold(above)
        if fold is None or fold.identity:
            folds.append(None)
        else:
            if not fold.ok:
                r.fail(f"non-uniform scale or shear on a non-joint node above joint {names[i]!r} is not supported")
            t, q, s = fold.translation(t), fold.rotation(q), fold.scale(s)
            folds.append(fold)
        rest_t[i], rest_q[i], rest_s[i] = t, q, s

    # Inverse binds: each joint takes the first merged skin's (the main skin's first) that lists it. A
    # skin that lists a joint with another inverse bind draws through a duplicate joint: a child of that
    # joint at identity rest, so its world transform is the joint's and world @ ibm is what glTF means.
    ibm_file = np.empty((jc, 4, 4))
    assigned = np.zeros(jc, dtype=bool)
    skin_maps: dict[int, np.ndarray] = {}
    dup_of: list[int] = []
    dup_ibm: list[np.ndarray] = []
    ibm_file[[new_index[j] for j in src_joints[skinned:]]] = np.eye(4)  # (no vertex is weighted to them)
    assigned[[new_index[j] for j in src_joints[skinned:]]] = True
    for k in merged:
        ibm_k = _skin_inverse_binds(r, k, len(skin_joints[k]))
        idx = np.array([new_index[j] for j in skin_joints[k]], dtype=np.int64)
        fresh = ~assigned[idx]
        ibm_file[idx[fresh]] = ibm_k[fresh]
        assigned[idx[fresh]] = True
        held = ibm_file[idx]
        size = np.maximum(1.0, np.maximum(np.abs(held).max(axis=(1, 2)), np.abs(ibm_k).max(axis=(1, 2))))
        differ = np.flatnonzero(np.abs(held - ibm_k).max(axis=(1, 2)) > 1e-6 * size)
        if jc + len(dup_of) + len(differ) > MAX_JOINTS:
            r.fail(f"skins {', '.join(map(str, merged))} need more than the {MAX_JOINTS:,} joints a vertex can address "
                   "(duplicates for differing inverse binds included)")
        mapping = idx.copy()
        for p in differ:
            o = int(idx[p])
            mapping[p] = jc + len(dup_of)
            name = f"{names[o]}@skin{k}"
            while name in seen:
                name = f"{name}.{mapping[p]}"
            seen.add(name)
            names.append(name)
            dup_of.append(o)
            dup_ibm.append(ibm_k[p])
        skin_maps[k] = mapping
    if len(merged) > 1:
        warn.append(f"merged skins {', '.join(map(str, merged))} into one skeleton ({jc + len(dup_of)} joints; "
                    f"{len(dup_of)} duplicated for differing inverse binds)")
    if dup_of:
        n = len(dup_of)
        parent_list += dup_of
        rest_t = np.concatenate([rest_t, np.zeros((n, 3))])
        rest_q = np.concatenate([rest_q, np.tile([0.0, 0.0, 0.0, 1.0], (n, 1))])
        rest_s = np.concatenate([rest_s, np.ones((n, 3))])
        folds += [None] * n
        ibm_file = np.concatenate([ibm_file, np.array(dup_ibm)])
        jc += n
    parents = np.array(parent_list, dtype=np.int32)

    # Factor a constant uniform scale above the root joint(s) out of the skeleton: child translations
    # are multiplied by it and the inverse binds absorb it, so joint transforms stay rigid.
    # A root made of an animated node above the skin's joints (animated_ancestors) counts its own uniform
    # scale too (an armature's 0.01), as it counted when it was folded in above them.
    roots = [i for i in range(jc) if parents[i] < 0]
    added = {new_index[j] for j in src_joints[skinned:]}
    root_scales = {round(float(rest_s[i][0]), 9) if i in added and _uniform(rest_s[i]) else (round(folds[i].s, 9) if folds[i] else 1.0)
                   for i in roots}
    factor = root_scales.pop() if len(root_scales) == 1 else 1.0
    if factor != 1.0:
        for i in roots:
            rest_s[i] /= factor
        for i in range(jc):
            if parents[i] >= 0:
                rest_t[i] *= factor

    ibm = np.diag([factor, factor, factor, 1.0]) @ ibm_file
    if not np.all(np.isfinite(ibm)):
        r.fail("inverseBindMatrices hold NaN or Inf")

    skeleton = Skeleton(tuple(names), parents, rest_t, tf.quat_normalize(rest_q), rest_s, ibm).validate()
    return Rig(skeleton, new_index, skin_maps, folds, factor)


def animated_ancestors(r: Reader, tree: Tree, joints: set[int]) -> list[int]:
    """The nodes above `joints` (the skins' joint nodes) that are not joints themselves and that some
    animation moves (a translation, rotation or scale channel), in node order: folded at rest, their
    motion would be lost, so they become joints of the skeleton. Channels are read leniently here; the
    clips check them."""
    moved = set()
    for anim in r.array("animations"):
        for ch in (anim.get("channels") if isinstance(anim, dict) else None) or []:
            target = ch.get("target") if isinstance(ch, dict) else None
            if isinstance(target, dict) and target.get("path") in ("translation", "rotation", "scale") and is_whole(target.get("node")):
                moved.add(int(target["node"]))
    out, seen = set(), set()
    for j in joints:
        k = tree.parent.get(j)
        while k is not None and k not in seen:
            seen.add(k)
            if k in moved and k not in joints:
                out.add(k)
            k = tree.parent.get(k)
    return sorted(out)


def _uniform(s: np.ndarray, tol: float = 1e-5) -> bool:
    return float(np.max(np.abs(s - s[0]))) <= tol * max(1.0, abs(float(s[0]))) and s[0] > 0


def _skin_label(r: Reader, k: int, joints: int) -> str:
    """'skin 1 ('Bob', 20 joints)' for messages."""
    name = r.item("skins", k).get("name")
    return f"skin {k} ({name!r}, {joints} joints)" if isinstance(name, str) and name else f"skin {k} ({joints} joints)"


def _skin_joints(r: Reader, k: int) -> list[int]:
    """Skin k's joint nodes, checked: some, at most MAX_JOINTS, each a node, none twice."""
    skin = r.item("skins", k)
    joints = r.list(skin, "joints", f"skin {k}")
    if not joints:
        r.fail(f"skin {k} has no joints")
    if len(joints) > MAX_JOINTS:
        r.fail(f"skin {k} has {len(joints):,} joints, more than the {MAX_JOINTS:,} a vertex can address")
    for j in joints:
        r.item("nodes", j, "joint node")
    if len(set(joints)) != len(joints):
        r.fail(f"skin {k} lists a joint twice")
    return joints


def _mergeable_skins(r: Reader, tree: Tree, main: int, skin_joints: dict[int, list[int]], warn: list[str]) -> list[int]:
    """The skins that form one skeleton with the main skin, main first: those all of whose joints lie,
    in the joint forest of the joints of every skin drawing a mesh, in a tree that holds a joint of the
    main skin. The others are other characters (or do not fit one skeleton): left out, one warning each."""
    others = sorted(k for k in skin_joints if k != main)
    if not others:
        return [main]
    top = joint_tops(tree, set().union(*skin_joints.values()))
    main_tops = {top[j] for j in skin_joints[main]}
    merged = [main]
    for k in others:
        joints = skin_joints[k]
        outside = sum(top[j] not in main_tops for j in joints)
        if not outside:
            merged.append(k)
        elif outside == len(joints):
            warn.append(f"{_skin_label(r, k, len(joints))} shares no joint tree with skin {main}: it is another character; left out")
        else:
            warn.append(f"{_skin_label(r, k, len(joints))} has {outside} joints outside skin {main}'s joint trees: "
                        "it does not fit one skeleton with it; left out")
    return merged


def _skin_inverse_binds(r: Reader, k: int, joint_count: int) -> np.ndarray:
    """Skin k's inverse bind matrices as float64 (joint_count, 4, 4), row-major, checked (identity without them)."""
    skin = r.item("skins", k)
    ibm_index = r.index(skin, "inverseBindMatrices", "accessors", f"skin {k}")
    if ibm_index is None:
        return np.tile(np.eye(4), (joint_count, 1, 1))
    raw = r.accessor(ibm_index, "inverseBindMatrices", ("MAT4",), FLOAT_TYPES)
    if raw.shape[0] < joint_count:
        r.fail(f"skin {k}: inverseBindMatrices has {raw.shape[0]} matrices for {joint_count} joints")
    ibm = raw[:joint_count].astype(np.float64).reshape(-1, 4, 4).transpose(0, 2, 1)
    check_matrices(r, ibm, f"accessor {ibm_index} (inverseBindMatrices)")
    return ibm

