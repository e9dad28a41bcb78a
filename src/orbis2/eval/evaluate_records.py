"""The record of ``orbis2 evaluate`` and of the ``evaluate_<name>`` stage (``fvd.json``), typed like
:mod:`orbis2.eval.records`' and built from the same parts as the ``eval_fvd`` stages' records.

:func:`orbis2.eval.protocols.evaluate.evaluate_pairs` builds an :class:`EvaluateRecord`,
:func:`orbis2.eval.protocols.evaluate_steering.add_steering` adds its :class:`SteeringScores`, and the command
and the stage write it with :func:`orbis2.eval.records.write_record`; anything reading a written one
goes through :func:`orbis2.eval.records.from_json`. Strict like every record: an unknown key, a missing
one or a value of the wrong type fails where the record is built or read.
"""

from __future__ import annotations

from orbis2.eval.records import Chunked, Interval, Num, ProtocolCard, Record, References, SplitFvd, sometimes


class Pairing(Record):
    """How many rollouts start closest to their own clip (:func:`orbis2.eval.protocols.evaluate.pairing_check`)."""

    matched: int
    videos: int
    fraction: Num
    definition: str


class RolloutVideo(Record):
    """One scored rollout as :class:`orbis2.eval.protocols.evaluate.Pair` names it; paths as given."""

    name: str
    generated: str
    real: str
    clip: str
    context_frames: int | None
    trajectory: str | None


class SteeringScores(Record):
    """Steering ADE and the signed turn of rollouts with trajectories
    (:func:`orbis2.eval.protocols.evaluate_steering.steering_record`)."""

    instrument: str
    hfov_deg: Num
    seconds: Num
    ade_m: Interval
    turn_deg: Interval
    commanded_turn_deg: Interval


class EvaluateRecord(Record):
    """``orbis2 evaluate --out`` and ``reports/evaluate/<name>/fvd.json``: the FVD with its interval, the chunked
    FVD when the rollouts are long enough, the reference rows, the pairing check, the warnings, the protocol
    card, the videos and, for rollouts with trajectories, the steering scores."""

    fvd: SplitFvd
    chunked: Chunked | None = sometimes()
    references: References
    pairing: Pairing
    warnings: list[str]
    protocol: ProtocolCard
    videos: list[RolloutVideo]
    steering: SteeringScores | None = sometimes()
