"""Float64 quaternion, dual-quaternion and matrix helpers, vectorised over leading axes.

Conventions, shared with glTF and the shaders:
- quaternions are (x, y, z, w);
- matrices are 4x4 row-major numpy arrays acting on column vectors (``M @ v``);
- a transform built from TRS is ``T @ R @ S`` (glTF's order);
- a dual quaternion is a pair (real, dual) of quaternions with ``dual = 0.5 * (t, 0) * real``.
"""

from __future__ import annotations

import numpy as np

EPS = 1e-12


def quat_identity(shape=()) -> np.ndarray:
    q = np.zeros(tuple(shape) + (4,))
    q[..., 3] = 1.0
    return q


def quat_mul(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Hamilton product a*b (apply b first, then a)."""
    ax, ay, az, aw = np.moveaxis(np.asarray(a, dtype=np.float64), -1, 0)
    bx, by, bz, bw = np.moveaxis(np.asarray(b, dtype=np.float64), -1, 0)
    return np.stack(
        [
            aw * bx + ax * bw + ay * bz - az * by,
            aw * by - ax * bz + ay * bw + az * bx,
            aw * bz + ax * by - ay * bx + az * bw,
            aw * bw - ax * bx - ay * by - az * bz,
        ],
        axis=-1,
    )


def quat_conj(q: np.ndarray) -> np.ndarray:
    out = np.array(q, dtype=np.float64, copy=True)
    out[..., :3] *= -1.0
    return out


def quat_normalize(q: np.ndarray) -> np.ndarray:
    q = np.asarray(q, dtype=np.float64)
    n = np.linalg.norm(q, axis=-1, keepdims=True)
    return q / np.maximum(n, EPS)


def quat_rotate(q: np.ndarray, v: np.ndarray) -> np.ndarray:
    """Rotate vectors v (..., 3) by unit quaternions q (..., 4)."""
    q = np.asarray(q, dtype=np.float64)
    v = np.asarray(v, dtype=np.float64)
    u = q[..., :3]
    w = q[..., 3:4]
    t = 2.0 * np.cross(u, v)
    return v + w * t + np.cross(u, t)


def quat_from_axis_angle(axis, angle) -> np.ndarray:
    axis = np.asarray(axis, dtype=np.float64)
    angle = np.asarray(angle, dtype=np.float64)
    axis = axis / np.maximum(np.linalg.norm(axis, axis=-1, keepdims=True), EPS)
    half = 0.5 * angle[..., None]
    return np.concatenate([axis * np.sin(half), np.cos(half)], axis=-1)


def quat_from_euler_xyz(x, y, z) -> np.ndarray:
    """Rotation about X, then Y, then Z (intrinsic order Z*Y*X applied to column vectors)."""
    qx = quat_from_axis_angle([1.0, 0.0, 0.0], np.asarray(x, dtype=np.float64))
    qy = quat_from_axis_angle([0.0, 1.0, 0.0], np.asarray(y, dtype=np.float64))
    qz = quat_from_axis_angle([0.0, 0.0, 1.0], np.asarray(z, dtype=np.float64))
    return quat_mul(qz, quat_mul(qy, qx))


def quat_to_mat3(q: np.ndarray) -> np.ndarray:
    q = quat_normalize(q)
    x, y, z, w = np.moveaxis(q, -1, 0)
    m = np.empty(q.shape[:-1] + (3, 3))
    m[..., 0, 0] = 1 - 2 * (y * y + z * z)
    m[..., 0, 1] = 2 * (x * y - z * w)
    m[..., 0, 2] = 2 * (x * z + y * w)
    m[..., 1, 0] = 2 * (x * y + z * w)
    m[..., 1, 1] = 1 - 2 * (x * x + z * z)
    m[..., 1, 2] = 2 * (y * z - x * w)
    m[..., 2, 0] = 2 * (x * z - y * w)
    m[..., 2, 1] = 2 * (y * z + x * w)
    m[..., 2, 2] = 1 - 2 * (x * x + y * y)
    return m


def mat3_to_quat(m: np.ndarray) -> np.ndarray:
    """Rotation matrix to unit quaternion (Shepperd's method: pick the largest diagonal term)."""
    m = np.asarray(m, dtype=np.float64)
    shape = m.shape[:-2]
    m = m.reshape(-1, 3, 3)
    q = np.empty((m.shape[0], 4))
    tr = m[:, 0, 0] + m[:, 1, 1] + m[:, 2, 2]
    diag = np.stack([m[:, 0, 0], m[:, 1, 1], m[:, 2, 2], tr], axis=-1)
    case = np.argmax(diag, axis=-1)
    for c in range(4):
        sel = case == c
        if not np.any(sel):
            continue
        a = m[sel]
        if c == 3:
            s = np.sqrt(np.maximum(1.0 + tr[sel], EPS)) * 2.0
            q[sel] = np.stack(
                [(a[:, 2, 1] - a[:, 1, 2]) / s, (a[:, 0, 2] - a[:, 2, 0]) / s, (a[:, 1, 0] - a[:, 0, 1]) / s, 0.25 * s],
                axis=-1,
            )
        else:
            i, j, k = c, (c + 1) % 3, (c + 2) % 3
            s = np.sqrt(np.maximum(1.0 + a[:, i, i] - a[:, j, j] - a[:, k, k], EPS)) * 2.0
            out = np.empty((a.shape[0], 4))
            out[:, i] = 0.25 * s
            out[:, j] = (a[:, j, i] + a[:, i, j]) / s
            out[:, k] = (a[:, k, i] + a[:, i, k]) / s
            out[:, 3] = (a[:, k, j] - a[:, j, k]) / s
            q[sel] = out
    q = quat_normalize(q)
    # A canonical sign (w >= 0) keeps decompositions reproducible.
    q *= np.where(q[:, 3:4] < 0.0, -1.0, 1.0)
    return q.reshape(shape + (4,))


def quat_slerp(a: np.ndarray, b: np.ndarray, t: np.ndarray) -> np.ndarray:
    """Shortest-arc spherical interpolation, as glTF's LINEAR rotation interpolation requires."""
    a = np.asarray(a, dtype=np.float64)
    b = np.asarray(b, dtype=np.float64)
    t = np.asarray(t, dtype=np.float64)[..., None]
    d = np.sum(a * b, axis=-1, keepdims=True)
    b = np.where(d < 0.0, -b, b)
    d = np.abs(d)
    theta = np.arccos(np.clip(d, -1.0, 1.0))
    sin_theta = np.sin(theta)
    near = sin_theta < 1e-9
    safe = np.where(near, 1.0, sin_theta)
    wa = np.where(near, 1.0 - t, np.sin((1.0 - t) * theta) / safe)
    wb = np.where(near, t, np.sin(t * theta) / safe)
    return quat_normalize(wa * a + wb * b)


def trs_to_mat4(t: np.ndarray, q: np.ndarray, s: np.ndarray) -> np.ndarray:
    t = np.asarray(t, dtype=np.float64)
    s = np.asarray(s, dtype=np.float64)
    r = quat_to_mat3(q)
    m = np.zeros(r.shape[:-2] + (4, 4))
    m[..., :3, :3] = r * s[..., None, :]
    m[..., :3, 3] = t
    m[..., 3, 3] = 1.0
    return m


def mat4_decompose(m: np.ndarray):
    """Split affine matrices into (t, q, s, shear), where shear is the largest residual of ``T R S`` against m.

    Negative determinants put the reflection into the x scale.
    """
    m = np.asarray(m, dtype=np.float64)
    t = m[..., :3, 3].copy()
    a = m[..., :3, :3]
    s = np.linalg.norm(a, axis=-2)
    det = np.linalg.det(a)
    s[..., 0] = np.where(det < 0.0, -s[..., 0], s[..., 0])
    r = a / np.where(np.abs(s) < EPS, 1.0, s)[..., None, :]
    q = mat3_to_quat(r)
    rebuilt = trs_to_mat4(t, q, s)
    shear = np.max(np.abs(rebuilt - m), axis=(-2, -1)) if m.ndim > 2 else float(np.max(np.abs(rebuilt - m)))
    return t, q, s, shear


def mat4_inverse_affine(m: np.ndarray) -> np.ndarray:
    return np.linalg.inv(np.asarray(m, dtype=np.float64))


# ---------------------------------------------------------------------------------------------
# Dual quaternions


def dq_from_rt(q: np.ndarray, t: np.ndarray):
    """Unit dual quaternion of 'rotate by q, then translate by t'."""
    q = np.asarray(q, dtype=np.float64)
    tq = np.concatenate([np.asarray(t, dtype=np.float64), np.zeros(np.shape(t)[:-1] + (1,))], axis=-1)
    return q, 0.5 * quat_mul(tq, q)


def dq_normalize(real: np.ndarray, dual: np.ndarray):
    """Project onto unit dual quaternions: divide by |real| and remove the dual part's component along real."""
    n = np.linalg.norm(real, axis=-1, keepdims=True)
    n = np.maximum(n, EPS)
    r = real / n
    d = dual / n
    d = d - r * np.sum(r * d, axis=-1, keepdims=True)
    return r, d


def dq_to_rt(real: np.ndarray, dual: np.ndarray):
    r, d = dq_normalize(real, dual)
    t = 2.0 * quat_mul(d, quat_conj(r))[..., :3]
    return r, t


def dq_mul(a_real, a_dual, b_real, b_dual):
    """(a * b): apply b first, then a."""
    return quat_mul(a_real, b_real), quat_mul(a_real, b_dual) + quat_mul(a_dual, b_real)


def dq_to_mat4(real: np.ndarray, dual: np.ndarray, scale=None) -> np.ndarray:
    """Matrix of a (normalised) dual quaternion, optionally times a uniform scale applied first."""
    q, t = dq_to_rt(real, dual)
    s = np.ones(q.shape[:-1] + (3,)) if scale is None else np.repeat(np.asarray(scale, dtype=np.float64)[..., None], 3, -1)
    return trs_to_mat4(t, q, s)


def align_quat_track(q: np.ndarray, axis: int = 0) -> np.ndarray:
    """Flip signs along `axis` so that every key has a non-negative dot product with its predecessor."""
    q = np.moveaxis(np.array(q, dtype=np.float64, copy=True), axis, 0)
    for k in range(1, q.shape[0]):
        flip = np.sum(q[k] * q[k - 1], axis=-1, keepdims=True) < 0.0
        q[k] = np.where(flip, -q[k], q[k])
    return np.moveaxis(q, 0, axis)
