"""Figures of frames: rollout grids and counterfactual steering strips, and the PNG writer every figure uses.

Separate from :mod:`orbis2.eval.report.report` (the tables, claims and the figures of the records) so that evaluation
stages draw their figures without importing the report.
"""

from __future__ import annotations

from pathlib import Path
from typing import Sequence

import numpy as np

from orbis2.io import atomic_file


def pyplot():
    """matplotlib.pyplot on the file-only Agg backend (imported when a figure is made)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def save_figure(fig, path: str | Path) -> None:
    """``fig`` as a PNG at ``path``, written atomically; the figure is closed either way."""
    plt = pyplot()
    try:
        with atomic_file(Path(path)) as tmp:
            fig.savefig(tmp, format="png", dpi=120, bbox_inches="tight")
    finally:
        plt.close(fig)


def _check_frames(frames: np.ndarray, what: str) -> np.ndarray:
    frames = np.asarray(frames)
    if frames.dtype != np.uint8 or frames.ndim != 4 or frames.shape[-1] != 3:
        raise ValueError(f"{what} must be uint8 [T, H, W, 3], got {frames.dtype} {frames.shape}")
    return frames


def _frame_rows(frames: Sequence[np.ndarray], labels: Sequence[str], times: Sequence[float]) -> list[np.ndarray]:
    """Checked uint8 frame rows, one frame per time column."""
    rows = [_check_frames(f, f"frames of {label}") for f, label in zip(frames, labels)]
    for f, label in zip(rows, labels):
        if len(f) != len(times):
            raise ValueError(f"{label} has {len(f)} frames for {len(times)} time columns")
    return rows


def _draw_frame_rows(axes, rows: list[np.ndarray], labels: Sequence[str], times: Sequence[float],
                     as_columns: bool = False) -> None:
    """Frames into the first ``len(times)`` columns, times as column titles, labels as row titles; ``as_columns``:
    each video down a column instead (labels as column titles, times as row titles)."""
    for r, (f, label) in enumerate(zip(rows, labels)):
        for c, t in enumerate(times):
            ax = axes[c][r] if as_columns else axes[r][c]
            ax.imshow(f[c])
            ax.set_xticks([])
            ax.set_yticks([])
            title, side = (label, f"{t:g} s") if as_columns else (f"{t:g} s", label)
            if (c if as_columns else r) == 0:
                ax.set_title(title, fontsize=8)
            if (r if as_columns else c) == 0:
                ax.set_ylabel(side, fontsize=8)


def save_rollout_grid(
    frames: Sequence[np.ndarray], labels: Sequence[str], times: Sequence[float], path: str | Path
) -> None:
    """Appendix grid: one row of frames per model, one column per time (frames[i] is uint8 [T, H, W, 3])."""
    if len(frames) != len(labels) or not frames:
        raise ValueError(f"need one label per model row, got {len(frames)} rows and {len(labels)} labels")
    rows = _frame_rows(frames, labels, times)
    plt = pyplot()
    h, w = rows[0].shape[1:3]
    fig, axes = plt.subplots(len(rows), len(times), figsize=(1.8 * len(times) * w / h, 1.8 * len(rows)), squeeze=False)
    _draw_frame_rows(axes, rows, labels, times)
    save_figure(fig, path)


def save_frame_columns(
    frames: Sequence[np.ndarray], labels: Sequence[str], times: Sequence[float], path: str | Path
) -> None:
    """A grid with one column per video (``labels`` as column titles) and one row per time (frames[i] is uint8
    [T, H, W, 3]): many videos of one clip side by side, read across."""
    if len(frames) != len(labels) or not frames:
        raise ValueError(f"need one label per video column, got {len(frames)} columns and {len(labels)} labels")
    columns = _frame_rows(frames, labels, times)
    plt = pyplot()
    h, w = columns[0].shape[1:3]
    fig, axes = plt.subplots(len(times), len(columns), figsize=(1.9 * len(columns) * w / h, 1.9 * len(times)),
                             squeeze=False, gridspec_kw={"wspace": 0.04, "hspace": 0.04})
    _draw_frame_rows(axes, columns, labels, times, as_columns=True)
    save_figure(fig, path)


def save_steering_strip(
    frames: Sequence[np.ndarray],
    modes: Sequence[str],
    times: Sequence[float],
    commanded: Sequence[np.ndarray],
    path: str | Path,
    estimated: Sequence[np.ndarray] | None = None,
) -> None:
    """Counterfactual steering figure: per mode a row of frames and a top-down plot of its trajectory.

    ``commanded[i]`` (and ``estimated[i]``, the odometry of the generated video)
    are [K, 2] positions in metres, x forward and y to the left.
    """
    if not (len(frames) == len(modes) == len(commanded)) or not frames:
        raise ValueError("need one frame row, mode name and commanded trajectory per mode")
    if estimated is not None and len(estimated) != len(modes):
        raise ValueError("need one estimated trajectory per mode")
    rows = _frame_rows(frames, modes, times)
    plt = pyplot()
    h, w = rows[0].shape[1:3]
    fig, axes = plt.subplots(
        len(rows),
        len(times) + 1,
        figsize=(1.8 * (len(times) * w / h + 1), 1.8 * len(rows)),
        squeeze=False,
        gridspec_kw={"width_ratios": [w / h] * len(times) + [1]},
    )
    _draw_frame_rows(axes, rows, modes, times)
    for r in range(len(rows)):
        ax = axes[r][-1]
        plan = np.asarray(commanded[r], dtype=float)
        # top-down view: forward is up, left is left
        ax.plot(-plan[:, 1], plan[:, 0], color="tab:blue", label="commanded")
        if estimated is not None:
            est = np.asarray(estimated[r], dtype=float)
            ax.plot(-est[:, 1], est[:, 0], color="tab:orange", linestyle="--", label="estimated")
        ax.set_aspect("equal", adjustable="datalim")
        ax.tick_params(labelsize=6)
        if r == 0:
            ax.set_title("trajectory (m)", fontsize=8)
            ax.legend(fontsize=6)
    save_figure(fig, path)
