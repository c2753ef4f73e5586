"""SE(2) helpers on plain numpy arrays.

A pose is ``(x, y, theta)``; a batch of poses is an ``(N, 3)`` array. Frames follow
Cartographer's vocabulary: ``local_pose`` (tracking frame in the local SLAM frame),
``global_pose`` (tracking frame in the optimized map frame), ``submap_pose`` (submap origin
in the local or global frame).
"""
from __future__ import annotations

import math

import numpy as np


def wrap(a):
    """Wrap angles to [-pi, pi)."""
    return (np.asarray(a) + np.pi) % (2.0 * np.pi) - np.pi


def _wrap1(a: float) -> float:
    return (a + math.pi) % (2.0 * math.pi) - math.pi


def compose(a, b) -> np.ndarray:
    """a ∘ b for poses (3,) or batches (N, 3) (broadcasting)."""
    a = np.asarray(a, dtype=float)
    b = np.asarray(b, dtype=float)
    if a.ndim == 1 and b.ndim == 1:
        c, s = math.cos(a[2]), math.sin(a[2])
        return np.array([a[0] + c * b[0] - s * b[1], a[1] + s * b[0] + c * b[1], _wrap1(a[2] + b[2])])
    c, s = np.cos(a[..., 2]), np.sin(a[..., 2])
    x = a[..., 0] + c * b[..., 0] - s * b[..., 1]
    y = a[..., 1] + s * b[..., 0] + c * b[..., 1]
    return np.stack([x, y, wrap(a[..., 2] + b[..., 2])], axis=-1)


def inverse(a) -> np.ndarray:
    a = np.asarray(a, dtype=float)
    if a.ndim == 1:
        c, s = math.cos(a[2]), math.sin(a[2])
        return np.array([-(c * a[0] + s * a[1]), s * a[0] - c * a[1], _wrap1(-a[2])])
    c, s = np.cos(a[..., 2]), np.sin(a[..., 2])
    x = -(c * a[..., 0] + s * a[..., 1])
    y = s * a[..., 0] - c * a[..., 1]
    return np.stack([x, y, wrap(-a[..., 2])], axis=-1)


def between(a, b) -> np.ndarray:
    """a⁻¹ ∘ b: pose of b in the frame of a."""
    if np.ndim(a) == 1 and np.ndim(b) == 1:  # the per-scan case, without temporaries
        c, s = math.cos(a[2]), math.sin(a[2])
        dx, dy = b[0] - a[0], b[1] - a[1]
        return np.array([c * dx + s * dy, c * dy - s * dx, _wrap1(b[2] - a[2])], dtype=float)
    return compose(inverse(a), b)


def transform_points(pose, points: np.ndarray) -> np.ndarray:
    """Apply a pose (3,) to points (N, 2)."""
    c, s = math.cos(pose[2]), math.sin(pose[2])
    out = np.empty_like(points, dtype=float)
    out[:, 0] = pose[0] + c * points[:, 0] - s * points[:, 1]
    out[:, 1] = pose[1] + s * points[:, 0] + c * points[:, 1]
    return out


def yaw_to_quaternion(theta):
    """(qx, qy, qz, qw) of a rotation about +z."""
    theta = np.asarray(theta, dtype=float)
    z = np.zeros_like(theta)
    return np.stack([z, z, np.sin(theta / 2), np.cos(theta / 2)], axis=-1)


def quaternion_to_yaw(qx, qy, qz, qw):
    return np.arctan2(2.0 * (qw * qz + qx * qy), 1.0 - 2.0 * (qy * qy + qz * qz))


def interpolate_pose(t, t0, p0, t1, p1) -> np.ndarray:
    """Linear interpolation of a pose between two stamped poses (angle along the short way)."""
    if t1 == t0:
        return np.asarray(p0, dtype=float).copy()
    a = (t - t0) / (t1 - t0)
    p0 = np.asarray(p0, dtype=float)
    p1 = np.asarray(p1, dtype=float)
    d = wrap(p1[2] - p0[2])
    return np.array([p0[0] + a * (p1[0] - p0[0]), p0[1] + a * (p1[1] - p0[1]), wrap(p0[2] + a * d)])
