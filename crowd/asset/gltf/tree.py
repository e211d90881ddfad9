"""The node tree: each node's parent, the joints, the nearest joint above a node, the transforms of the
non-joint nodes between joints, and the constant similarity (a `Fold`) such nodes apply above a joint.

Space: skinned vertices stay in the mesh's bind space (glTF ignores a skinned mesh node's transform).
Non-joint nodes above and between joints are folded into the joints' local transforms (an animated one
is made a joint instead: crowd.asset.gltf.skins.animated_ancestors), and a constant
uniform scale above the root joint (0.01 and 100 are common) is factored out of the whole skeleton by
scaling joint translations (crowd.asset.gltf.skins), so joint transforms come out rigid and in the
file's scene units. Every walk here is linear in the number of nodes.
"""

from __future__ import annotations

import numpy as np

from ... import transforms as tf
from .reader import Reader, is_whole, show

MAX_NODES = 1 << 16


class Tree:
    """The node hierarchy: parents, the joints, and each node's nearest joint above, all in linear time."""

    def __init__(self, r: Reader):
        self.r = r
        nodes = r.array("nodes")
        if len(nodes) > MAX_NODES:
            r.fail(f"{len(nodes):,} nodes, more than the {MAX_NODES:,} allowed")
        self.nodes = [r.item("nodes", i) for i in range(len(nodes))]
        parent: dict[int, int] = {}
        for i, n in enumerate(self.nodes):
            for c in r.list(n, "children", r.node_where(i)):
                if not is_whole(c) or not 0 <= c < len(nodes):
                    r.fail(f"node {i} has child {show(c)} out of range")
                if c in parent:
                    r.fail(f"node {c} has two parents")
                parent[c] = i
        self.parent = parent
        done: set[int] = set()  # nodes whose chain up is known to end at a root
        for i in range(len(nodes)):
            path, on_path, k = [], set(), i
            while k is not None and k not in done:
                if k in on_path:
                    r.fail(f"node hierarchy has a cycle through node {i}")
                on_path.add(k)
                path.append(k)
                k = parent.get(k)
            done.update(path)
        self.joints: set[int] = set()
        self._above: dict[int, int | None] = {}
        self._run: dict[int, np.ndarray] = {}

    def joint_above(self, node: int) -> int | None:
        """The nearest joint strictly above `node`, or None."""
        return _nearest_joint_above(self.parent, self.joints, self._above, node)

    def run_matrix(self, node: int) -> np.ndarray:
        """For a non-joint node: the product of the locals from the top of its run of non-joint nodes
        (just below a joint, or a root) down to it, itself included; memoised, so linear in all."""
        chain, k = [], node
        while k not in self._run:
            chain.append(k)
            p = self.parent.get(k)
            if p is None or p in self.joints:
                base = None
                break
            k = p
        else:
            base = self._run[k]
        for k in reversed(chain):
            base = self.r.local(k) if base is None else base @ self.r.local(k)
            self._run[k] = base
        return self._run[node]

    def between(self, node: int) -> np.ndarray | None:
        """Product of the locals strictly between `node` and its nearest joint above (or the root);
        None when there is none."""
        p = self.parent.get(node)
        return None if p is None or p in self.joints else self.run_matrix(p)


def _memoised_walk(node: int, memo: dict, step) -> object:
    """Where a chain of steps from `node` ends, remembered for every node on the way, so that walks
    over a whole tree stay linear. `step(k)` is (the next node, None) to go on, or (None, the end)."""
    chain, k = [], node
    while k not in memo:
        chain.append(k)
        nxt, end = step(k)
        if nxt is None:
            break
        k = nxt
    else:
        end = memo[k]
    for k in chain:
        memo[k] = end
    return end


def _nearest_joint_above(parent: dict[int, int], joints: set[int], memo: dict, node: int) -> int | None:
    """The nearest node of `joints` strictly above `node` (None: it has none), memoised in `memo`."""
    def step(k):
        p = parent.get(k)
        return (None, p) if p is None or p in joints else (p, None)

    return _memoised_walk(node, memo, step)


def joint_tops(tree: Tree, joints: set[int]) -> dict[int, int]:
    """For each joint: the top joint of its tree in the forest of `joints` (parent = the nearest joint
    above). Linear in the nodes walked; tree.joints and its memo are left alone."""
    above: dict[int, int | None] = {}
    top: dict[int, int] = {}

    def step(k):
        a = _nearest_joint_above(tree.parent, joints, above, k)
        return (None, k) if a is None else (a, None)

    for j in joints:
        _memoised_walk(j, top, step)
    return top


def _is_uniform(s: np.ndarray, tol: float = 1e-5) -> bool:
    return float(np.max(np.abs(s - s[0]))) <= tol * max(1.0, abs(float(s[0])))


class Fold:
    """A constant similarity P (rigid Q and uniform scale sp) applied on the left of a joint's local TRS."""

    def __init__(self, matrix: np.ndarray):
        t, q, s, shear = tf.mat4_decompose(matrix)
        self.ok = _is_uniform(s) and shear < 1e-5 and s[0] > 0
        self.t, self.q, self.s = t, q, float(s[0])
        self.identity = np.allclose(matrix, np.eye(4), atol=1e-12)

    def translation(self, t, tangent=False):
        out = self.s * tf.quat_rotate(self.q, t)
        return out if tangent else out + self.t

    def rotation(self, q):
        return tf.quat_mul(self.q, q)  # linear in q, so it also maps CUBICSPLINE tangents

    def scale(self, s):
        return self.s * np.asarray(s)


def _trs_fields(node):
    t = np.array(node.translation if node.translation is not None else [0, 0, 0], dtype=np.float64)
    q = np.array(node.rotation if node.rotation is not None else [0, 0, 0, 1], dtype=np.float64)
    s = np.array(node.scale if node.scale is not None else [1, 1, 1], dtype=np.float64)
    return t, tf.quat_normalize(q), s


def node_local_matrix(node) -> np.ndarray:
    """A pygltflib node's local transform as a float64 4x4 (its matrix, or its TRS with glTF's defaults).
    For files this project wrote or already imported (bench/peers_panda.py); the importer checks its own."""
    if node.matrix is not None and len(node.matrix) == 16:
        return np.array(node.matrix, dtype=np.float64).reshape(4, 4).T  # glTF matrices are column-major
    return tf.trs_to_mat4(*_trs_fields(node))

