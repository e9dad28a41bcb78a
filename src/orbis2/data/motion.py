"""Ego-motion statistics of a driving dataset: how fast it drives and how often it turns.

A world model can only learn to follow steering if its data turns often and both ways; these
figures are what the `town` stage reports (and what tests pin) about its world.
"""

from __future__ import annotations

import numpy as np

TURN_THRESHOLD = 0.05  # rad/s: |yaw rate| above this counts as turning
MOVING_THRESHOLD = 1.0  # m/s
SPEED_BINS = np.arange(0.0, 16.0, 2.0)  # m/s, last bin open
YAW_BINS = np.array([-np.inf, -0.5, -0.2, -0.05, 0.05, 0.2, 0.5, np.inf])  # rad/s


def motion_statistics(speed: np.ndarray, yaw_rate: np.ndarray, on_bend: np.ndarray | None = None) -> dict[str, float]:
    """Per-frame shares and means over concatenated (speed, yaw_rate) samples.

    ``turning`` = share of frames with |yaw rate| > TURN_THRESHOLD, split into ``left`` (counter-
    clockwise) and ``right``; ``left_right_ratio`` is left / right (1 = balanced). Histograms
    are shares per bin (speed bins of 2 m/s; yaw-rate bins edged at +-0.05, 0.2, 0.5 rad/s).
    ``turning_yaw_rate_median`` and ``_p99``: |yaw rate| over the turning frames (0 without any),
    how graded the turns are, i.e. which steering counterfactuals stay inside the data.
    With ``on_bend`` (per frame: the ego is on a road curve, not at a junction): ``bend`` = share
    of frames on a curve, ``bend_turning`` = share turning there, ``bend_yaw_rate_median`` = the
    median |yaw rate| of those frames (0 without any).
    """
    v = np.asarray(speed, np.float64)
    w = np.asarray(yaw_rate, np.float64)
    if v.shape != w.shape or v.size == 0:
        raise ValueError(f"speed and yaw_rate must be non-empty and of one shape, got {v.shape} and {w.shape}")
    left, right = float(np.mean(w > TURN_THRESHOLD)), float(np.mean(w < -TURN_THRESHOLD))
    moving = v > MOVING_THRESHOLD
    out = {
        "frames": float(v.size),
        "speed_mean": float(v.mean()),
        "speed_moving_mean": float(v[moving].mean()) if moving.any() else 0.0,
        "stopped": float(np.mean(v < 0.5)),
        "turning": left + right,
        "left": left,
        "right": right,
        "left_right_ratio": left / right if right > 0 else float("inf"),
        "abs_yaw_rate_mean": float(np.abs(w).mean()),
    }
    turning = np.abs(w[np.abs(w) > TURN_THRESHOLD])
    out["turning_yaw_rate_median"] = float(np.median(turning)) if turning.size else 0.0
    out["turning_yaw_rate_p99"] = float(np.percentile(turning, 99)) if turning.size else 0.0
    if on_bend is not None:
        bend = np.asarray(on_bend, bool)
        if bend.shape != v.shape:
            raise ValueError(f"on_bend must have the shape of speed {v.shape}, got {bend.shape}")
        bend_turning = bend & (np.abs(w) > TURN_THRESHOLD)
        out["bend"] = float(bend.mean())
        out["bend_turning"] = float(bend_turning.mean())
        out["bend_yaw_rate_median"] = float(np.median(np.abs(w[bend_turning]))) if bend_turning.any() else 0.0
    speed_hist = np.histogram(np.minimum(v, SPEED_BINS[-1] + 1.0), np.append(SPEED_BINS, np.inf))[0] / v.size
    yaw_hist = np.histogram(w, YAW_BINS)[0] / w.size
    out.update({f"speed_hist_{lo:g}": float(h) for lo, h in zip(SPEED_BINS, speed_hist)})
    out.update({f"yaw_hist_{lo:g}_{hi:g}": float(h) for lo, hi, h in zip(YAW_BINS[:-1], YAW_BINS[1:], yaw_hist)})
    return out
