"""A car's odometry in the plane: the body-frame move between two poses, and a pose moved.

Odometry measures how a car moved, never where it is: the displacement ``(dx, dy)`` in
the body frame at the move's start and the yaw change ``dyaw`` (what wheel speeds and an
IMU integrate). Poses are ``(x, y, yaw)`` in metres and radians.
"""

from __future__ import annotations

import math

import numpy as np

from saferace.track.frenet import wrap_angle


def odometry_step(pose_from: np.ndarray, pose_to: np.ndarray) -> np.ndarray:
    """``(dx, dy, dyaw)``: the move from ``pose_from`` to ``pose_to`` in the body frame at
    its start."""
    x0, y0, yaw0 = (float(v) for v in pose_from)
    x1, y1, yaw1 = (float(v) for v in pose_to)
    cos, sin = math.cos(yaw0), math.sin(yaw0)
    dx, dy = x1 - x0, y1 - y0
    dyaw = wrap_angle(yaw1 - yaw0)
    return np.array([cos * dx + sin * dy, -sin * dx + cos * dy, dyaw])


def moved_by(pose: np.ndarray, step: np.ndarray) -> np.ndarray:
    """``pose`` after the body-frame ``step`` (:func:`odometry_step`'s inverse)."""
    x, y, yaw = (float(v) for v in pose)
    dx, dy, dyaw = (float(v) for v in step)
    cos, sin = math.cos(yaw), math.sin(yaw)
    return np.array([x + cos * dx - sin * dy, y + sin * dx + cos * dy, wrap_angle(yaw + dyaw)])
