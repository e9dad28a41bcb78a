"""Ego-motion integration: poses from per-step speed and yaw rate (exact unicycle arcs).

Shared by the town (which renders from these poses), the importer, the CLI, visual
odometry and the steering evaluation, none of which should need the town's renderer to get it.
"""

from __future__ import annotations

import numpy as np

from orbis2.errors import OrbisError


def integrate_odometry(speed, yaw_rate, fps, x0=0.0, y0=0.0, yaw0=0.0):
    """Poses from per-step controls, exact unicycle arcs (see the module docstring).

    Pose 0 is (x0, y0, yaw0); pose k+1 follows pose k by driving speed[k] / fps metres along a
    circular arc turning by yaw_rate[k] / fps radians (a straight line when yaw_rate is 0).
    Returns (x, y, yaw), each of len(speed).
    """
    v = np.asarray(speed, np.float64)
    w = np.asarray(yaw_rate, np.float64)
    n, dt = len(v), 1.0 / fps
    dyaw = w * dt
    yaw = yaw0 + np.concatenate([[0.0], np.cumsum(dyaw)])[:n]
    # Chord of the arc: length v dt sinc(dyaw / 2), direction yaw + dyaw / 2 (exact, stable at 0).
    chord = v * dt * np.sinc(dyaw / (2 * np.pi))
    x = x0 + np.concatenate([[0.0], np.cumsum(chord * np.cos(yaw + dyaw / 2))])[:n]
    y = y0 + np.concatenate([[0.0], np.cumsum(chord * np.sin(yaw + dyaw / 2))])[:n]
    return x, y, yaw


def integrate_controls(speed, yaw_rate, dt: float) -> np.ndarray:
    """Planar positions [T+1, 2] reached by driving the controls from the origin, heading +x.

    Each step drives ``speed[k] * dt`` metres along a circular arc that turns by
    ``yaw_rate[k] * dt`` radians, the same exact integration the town uses to place its camera, so
    the reference trajectory of a rendered episode has no integration error. Point k is the
    position at t_k = k * dt; a video of T frames is compared with the first T points.
    """
    v = np.asarray(speed, np.float64).reshape(-1)
    w = np.asarray(yaw_rate, np.float64).reshape(-1)
    if v.shape != w.shape:
        raise OrbisError(f"speed and yaw_rate differ in length ({len(v)} vs {len(w)})")
    if not dt > 0:
        raise OrbisError(f"time step must be positive, got {dt}")
    # Pose k + 1 needs control k only: a trailing dummy control gives all T + 1 poses.
    x, y, _ = integrate_odometry(np.append(v, 0.0), np.append(w, 0.0), 1.0 / dt)
    return np.stack([x, y], 1)
