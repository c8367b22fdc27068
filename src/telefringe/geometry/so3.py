"""Rotations: the rotation-vector (Rodrigues) map, its inverse and left Jacobian, the
nearest rotation to a matrix, and the chordal mean of rotations.

Conventions: a rotation vector (3,) is the axis times the angle in radians; matrices are
(3, 3) proper rotations; ``R_a_b`` maps vectors of frame b into frame a.
"""

from __future__ import annotations

import numpy as np

__all__ = [
    "rotation_from_rotvec",
    "rotvec_from_rotation",
    "skew",
    "left_jacobian",
    "project_to_rotation",
    "chordal_mean",
]


def rotation_from_rotvec(rotvec) -> np.ndarray:
    """Rodrigues: rotation vector (3,) in radians -> rotation matrix (3, 3).

    Raises ``ValueError`` if ``rotvec`` is not 3 finite numbers.
    """
    r = np.asarray(rotvec, dtype=float)
    if r.size != 3 or not np.all(np.isfinite(r)):
        raise ValueError(f"rotvec must be 3 finite numbers (radians), got {rotvec!r}")
    r = r.reshape(3)
    theta = float(np.linalg.norm(r))
    K = np.array([[0.0, -r[2], r[1]], [r[2], 0.0, -r[0]], [-r[1], r[0], 0.0]])
    if theta < 1e-12:
        return np.eye(3) + K
    K = K / theta
    return np.eye(3) + np.sin(theta) * K + (1.0 - np.cos(theta)) * (K @ K)


def rotvec_from_rotation(R) -> np.ndarray:
    """Inverse Rodrigues: rotation matrix (3, 3) -> rotation vector (3,) in radians.

    The angle (the vector's norm) is in [0, pi]. Accurate to rounding error at every
    angle, including near 0 and pi (the angle comes from ``atan2(sin, cos)``; near pi the
    axis comes from the symmetric part of ``R``). At exactly pi the sign of the axis is
    arbitrary (both give the same rotation). Raises ``ValueError`` if ``R`` is not a
    proper rotation.
    """
    R = np.asarray(R, dtype=float)
    if R.shape != (3, 3) or not np.all(np.isfinite(R)):
        raise ValueError("R must be a finite (3, 3) array")
    if not np.allclose(R @ R.T, np.eye(3), rtol=0.0, atol=1e-6) or np.linalg.det(R) < 0:
        raise ValueError("R is not a proper rotation (R R^T != I or det < 0)")
    w = np.array([R[2, 1] - R[1, 2], R[0, 2] - R[2, 0], R[1, 0] - R[0, 1]])  # 2 sin(t) axis
    sin_t = 0.5 * float(np.linalg.norm(w))
    cos_t = 0.5 * (float(np.trace(R)) - 1.0)
    theta = float(np.arctan2(sin_t, cos_t))
    if cos_t > -0.7:
        # w is well conditioned here (sin_t / theta >= 0.55); theta / sin(theta) -> 1 at 0
        return (0.5 if sin_t == 0.0 else theta / (2.0 * sin_t)) * w
    # near pi: the symmetric part is cos(t) I + (1 - cos(t)) a a^T
    aaT = (0.5 * (R + R.T) - cos_t * np.eye(3)) / (1.0 - cos_t)
    i = int(np.argmax(np.diag(aaT)))
    axis = aaT[:, i] / np.sqrt(aaT[i, i])
    axis /= np.linalg.norm(axis)
    if np.dot(axis, w) < 0:
        axis = -axis
    return theta * axis


def skew(v: np.ndarray) -> np.ndarray:
    """(..., 3) -> (..., 3, 3) cross-product matrices."""
    v = np.asarray(v, dtype=float)
    z = np.zeros(v.shape[:-1])
    return np.stack([np.stack([z, -v[..., 2], v[..., 1]], -1),
                     np.stack([v[..., 2], z, -v[..., 0]], -1),
                     np.stack([-v[..., 1], v[..., 0], z], -1)], -2)


def left_jacobian(w: np.ndarray) -> np.ndarray:
    """Left Jacobian of SO(3) at rotation vector ``w`` (3,): d(R(w) x)/dw = -[R x]_x J_l."""
    th = float(np.linalg.norm(w))
    K = skew(w)
    if th < 1e-6:
        return np.eye(3) + 0.5 * K + (K @ K) / 6.0
    return (np.eye(3) + (1.0 - np.cos(th)) / th**2 * K
            + (th - np.sin(th)) / th**3 * (K @ K))


def project_to_rotation(M: np.ndarray) -> np.ndarray:
    """Nearest proper rotation (Frobenius) to a 3 x 3 matrix."""
    U, _, Vt = np.linalg.svd(M)
    S = np.diag([1.0, 1.0, np.sign(np.linalg.det(U @ Vt)) or 1.0])
    return U @ S @ Vt



def chordal_mean(Rs) -> np.ndarray:
    """Chordal L2 mean of rotations ``Rs`` (n, 3, 3): the rotation nearest their sum."""
    return project_to_rotation(np.sum(np.asarray(Rs), axis=0))
