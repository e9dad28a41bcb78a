"""Ego-motion integration: poses from per-step speed and yaw rate (exact unicycle arcs).

Shared by the town (which renders from these poses), the importer, the CLI and
visual odometry, none of which should need the town's renderer to get it.
"""

from __future__ import annotations

import numpy as np


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
