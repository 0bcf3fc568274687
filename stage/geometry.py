"""Rotations and rigid transforms: the one home for them in stage.

Used by the calibration methods, the simulator (sensor poses, the body's
kinematics) and the importers. Conventions: Kinect-style spaces, metres,
y up. A 4x4 matrix ``M`` maps points of one space into another
(``apply(M, p) = p @ M[:3,:3].T + M[:3,3]``). Angles in radians unless a
name says ``_deg``.
"""

from __future__ import annotations

import math

import numpy as np


# math.cos, not np.cos: these take one angle, and the simulator builds them for every
# sensor and body 30 times a second, where numpy's per-call overhead shows
def rot_x(a: float) -> np.ndarray:
    """(3, 3) rotation about x by ``a`` radians (pitch for a Kinect: y up, z forward)."""
    c, s = math.cos(a), math.sin(a)
    return np.array([[1.0, 0.0, 0.0], [0.0, c, -s], [0.0, s, c]])


def rot_y(a: float) -> np.ndarray:
    """(3, 3) rotation about y, the vertical axis, by ``a`` radians (yaw; 0 keeps +z)."""
    c, s = math.cos(a), math.sin(a)
    return np.array([[c, 0.0, s], [0.0, 1.0, 0.0], [-s, 0.0, c]])


def rot_z(a: float) -> np.ndarray:
    """(3, 3) rotation about z, the optical axis, by ``a`` radians (roll)."""
    c, s = math.cos(a), math.sin(a)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


def axis_rotations(axis: str, angles: np.ndarray) -> np.ndarray:
    """(...,) angles in radians -> (..., 3, 3) rotations about ``axis`` ('x', 'y' or 'z').

    The vectorised ``rot_x``/``rot_y``/``rot_z`` (a BVH file's channels, a GA population).
    """
    a = np.asarray(angles, dtype=float)
    c, s = np.cos(a), np.sin(a)
    one, zero = np.ones_like(a), np.zeros_like(a)
    if axis == "x":
        rows = [[one, zero, zero], [zero, c, -s], [zero, s, c]]
    elif axis == "y":
        rows = [[c, zero, s], [zero, one, zero], [-s, zero, c]]
    elif axis == "z":
        rows = [[c, -s, zero], [s, c, zero], [zero, zero, one]]
    else:
        raise ValueError(f"axis must be 'x', 'y' or 'z', not {axis!r}")
    return np.stack([np.stack(r, axis=-1) for r in rows], axis=-2)


def euler_matrices(angles: np.ndarray) -> np.ndarray:
    """(P, 3) (yaw, pitch, roll) -> (P, 3, 3) rotations ``Ry(yaw) @ Rx(pitch) @ Rz(roll)``.

    Vectorised over P (the GA evaluates a whole population at once).
    """
    angles = np.asarray(angles, dtype=float)
    cy, sy = np.cos(angles[:, 0]), np.sin(angles[:, 0])
    cp, sp = np.cos(angles[:, 1]), np.sin(angles[:, 1])
    cr, sr = np.cos(angles[:, 2]), np.sin(angles[:, 2])
    out = np.empty((len(angles), 3, 3))
    out[:, 0, 0] = cy * cr + sy * sp * sr
    out[:, 0, 1] = -cy * sr + sy * sp * cr
    out[:, 0, 2] = sy * cp
    out[:, 1, 0] = cp * sr
    out[:, 1, 1] = cp * cr
    out[:, 1, 2] = -sp
    out[:, 2, 0] = -sy * cr + cy * sp * sr
    out[:, 2, 1] = sy * sr + cy * sp * cr
    out[:, 2, 2] = cy * cp
    return out


def yaw_matrices(yaw: np.ndarray) -> np.ndarray:
    """(P,) yaw angles -> (P, 3, 3) rotations about y."""
    return axis_rotations("y", yaw)


def matrix(rotation: np.ndarray, translation: np.ndarray) -> np.ndarray:
    """(3, 3) and (3,) -> (4, 4) homogeneous transform."""
    m = np.eye(4)
    m[:3, :3] = rotation
    m[:3, 3] = translation
    return m


def apply(m: np.ndarray, points: np.ndarray) -> np.ndarray:
    """Apply a 4x4 transform to (..., 3) points."""
    return points @ m[:3, :3].T + m[:3, 3]


def invert(m: np.ndarray) -> np.ndarray:
    """Inverse of a 4x4 transform (exact for rigid ones, general otherwise)."""
    r = m[:3, :3]
    if np.allclose(r @ r.T, np.eye(3), atol=1e-9):
        return matrix(r.T, -r.T @ m[:3, 3])
    return np.linalg.inv(m)


def nearest_rotation(a: np.ndarray) -> np.ndarray:
    """The rotation closest to a 3x3 matrix (polar decomposition by SVD)."""
    u, _, vt = np.linalg.svd(a)
    d = np.sign(np.linalg.det(u @ vt)) or 1.0
    return u @ np.diag([1.0, 1.0, d]) @ vt


def rotation_angle_deg(a: np.ndarray, b: np.ndarray) -> float:
    """Angle (degrees) of the rotation taking ``b``'s rotation part to ``a``'s.

    Affine parts are first projected on the nearest rotation, so an affine
    estimate (the regression) is judged by its rotation.
    """
    ra, rb = nearest_rotation(a[:3, :3]), nearest_rotation(b[:3, :3])
    cos = (np.trace(ra @ rb.T) - 1.0) / 2.0
    return float(np.degrees(np.arccos(np.clip(cos, -1.0, 1.0))))


def transform_error(estimate: np.ndarray, truth: np.ndarray, points: np.ndarray | None = None,
                    ) -> dict[str, float]:
    """How far an estimated transform is from the true one.

    Returns rotation error (degrees), translation error (mm: distance between
    the two translation vectors) and, when ``points`` (..., 3) of the source
    space are given, the RMS (mm) over them of the distance between where the
    estimate and the truth put each point: the error a performer would see.
    """
    out = {"rot_deg": rotation_angle_deg(estimate, truth),
           "trans_mm": float(np.linalg.norm(estimate[:3, 3] - truth[:3, 3]) * 1000.0)}
    if points is not None:
        pts = np.asarray(points, dtype=float).reshape(-1, 3)
        d = apply(estimate, pts) - apply(truth, pts)
        out["rms_mm"] = float(np.sqrt((d ** 2).sum(axis=1).mean()) * 1000.0)
    return out


def level_matrix(plane: np.ndarray) -> np.ndarray:
    """4x4 that levels a sensor's space with its floor plane (seed 004, step 1).

    ``plane`` (4,): a x + b y + c z + d = 0 in the sensor's space, normal
    pointing up (Kinect's FloorClipPlane: d is the sensor's height). The
    result rotates the normal onto +y (the smallest such rotation, so yaw is
    left alone) and lifts the space by d, so the floor becomes y = 0.
    """
    n = np.asarray(plane[:3], dtype=float)
    norm = float(np.linalg.norm(n))
    if norm < 1e-9:
        raise ValueError("floor plane has no normal")
    n = n / norm
    d = float(plane[3]) / norm
    up = np.array([0.0, 1.0, 0.0])
    v = np.cross(n, up)
    s, c = float(np.linalg.norm(v)), float(n @ up)
    if s < 1e-12:
        r = np.eye(3) if c > 0 else rot_x(np.pi)
    else:
        k = v / s
        kx = np.array([[0, -k[2], k[1]], [k[2], 0, -k[0]], [-k[1], k[0], 0]])
        r = np.eye(3) + s * kx + (1 - c) * (kx @ kx)  # Rodrigues
    return matrix(r, np.array([0.0, d, 0.0]))


def transform_plane(plane: np.ndarray, m: np.ndarray) -> np.ndarray:
    """A plane (4,) given in space A, expressed in space B, for ``m``: A -> B."""
    out = np.asarray(plane, dtype=float) @ invert(m)
    return out / np.linalg.norm(out[:3])


def wrap_angle(a: np.ndarray) -> np.ndarray:
    """Angles wrapped into [-pi, pi)."""
    return (np.asarray(a) + np.pi) % (2 * np.pi) - np.pi
