"""Steering scores of any model's rollouts that come with their commanded trajectories (``orbis2 evaluate``).

Kept apart from :mod:`orbis2.eval.protocols.evaluate`, which the ``eval_fvd`` stages import: the
steering instrument's code is no input of the FVD stages.
"""

from __future__ import annotations

from collections.abc import Callable
from itertools import islice

import numpy as np

from orbis2.data.importer import read_odometry_csv
from orbis2.data.video import iter_frames
from orbis2.eval.evaluate_records import EvaluateRecord, SteeringScores
from orbis2.eval.metrics.odometry import camera_intrinsics
from orbis2.eval.metrics.stats import mean_interval
from orbis2.eval.protocols.evaluate import EvaluateError, Pair, Protocol
from orbis2.eval.protocols.steering import score_videos


def steering_record(pairs: list[Pair], fps: float, window: slice, offset: int, clusters: list[str],
                    proto: Protocol, instrument: Callable, instrument_name: str, hfov_deg: float) -> SteeringScores:
    """Steering ADE (metres, after scale alignment) and the signed turn response (degrees, the commanded turn's
    direction positive) of each rollout's first ``window``, read by ``instrument``
    (:mod:`orbis2.eval.protocols.steering`, the code of the ``eval_steering`` stage), with clip-bootstrap
    intervals."""
    missing = [p for p in pairs if p.trajectory is None]
    if missing:
        raise EvaluateError(f"{missing[0].generated}: no trajectory (and {len(missing) - 1} more); give every "
                            f"rollout one (<stem>.csv next to it, or the manifest's trajectory column) or none")
    times = np.arange(window.stop) / fps
    controls, videos = [], []
    for pair in pairs:
        odo = read_odometry_csv(pair.trajectory)
        if odo["timestamp"][0] > 1e-6 or odo["timestamp"][-1] < times[-1] - 1e-6:
            raise EvaluateError(f"{pair.trajectory}: covers {odo['timestamp'][0]:g}-{odo['timestamp'][-1]:g} s, "
                                f"but the scored window needs 0-{times[-1]:g} s from the first generated frame")
        controls.append((np.interp(times, odo["timestamp"], odo["speed"]),
                         np.interp(times, odo["timestamp"], odo["yaw_rate"])))
        frames = list(islice(iter_frames(pair.generated), offset, offset + window.stop))
        videos.append(np.stack(frames))
    first = videos[0]
    scores = score_videos(videos, controls, instrument, camera_intrinsics(first.shape[2], first.shape[1], hfov_deg),
                          fps)

    def interval(values: np.ndarray) -> dict:
        return mean_interval(values, clusters, proto.bootstrap_reps, seed=proto.seed).to_dict()

    return SteeringScores.model_validate(
        {"instrument": instrument_name, "hfov_deg": hfov_deg, "seconds": window.stop / fps,
         "ade_m": interval(scores["ade"]), "turn_deg": interval(scores["turn_deg"]),
         "commanded_turn_deg": interval(scores["commanded_turn_deg"])})


def add_steering(record: EvaluateRecord, pairs: list[Pair], proto: Protocol, generated_has_context: bool,
                 instrument: Callable, instrument_name: str, hfov_deg: float) -> EvaluateRecord:
    """``record`` with its ``steering`` scores (:func:`steering_record` over the record's FVD window) when the
    rollouts have trajectories; else ``record`` as it is."""
    if not any(p.trajectory for p in pairs):
        return record
    card = record.protocol
    steering = steering_record(pairs, card.fps, slice(0, card.window_frames),
                               card.context_frames if generated_has_context else 0,
                               [p.clip for p in pairs], proto, instrument, instrument_name, hfov_deg)
    return record.model_copy(update={"steering": steering})
