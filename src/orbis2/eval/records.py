"""The evaluation records: one typed model per kind, written by the evaluation stages and read strictly by the report.

Each ``eval_*`` stage builds its record (:class:`FvdRecord`, :class:`ProbeRecord`, :class:`SteeringRecord`,
:class:`SpeedRecord`, :class:`ConditioningRecord`; ``orbis2 evaluate``'s in :mod:`orbis2.eval.evaluate_records`) and
writes it with :func:`write_record`; the report reads them back (:mod:`orbis2.eval.report.evals`) into
an ``Evals`` and by attribute (``evals.steering_record().modes[mode].ade_low``). Reading is strict: a
missing key, an unknown key or a value of the wrong type stops with an ``OrbisError`` naming the file, the key
and the stage that writes it, so a renamed key fails when its record is read, not in the last table of a long
run, and no table is padded with guesses.

A record re-writes byte for byte: numbers keep the type they were written with (an int stays an int where a
float is allowed), and a key the stage writes only sometimes (``chunked``, ``per_block``, ...) is a field
that defaults to None and is left out of the file when None. Keys that are data (split names, steering modes,
instruments, systems) are ``dict`` keys; a lookup the report needs goes through ``Evals.entry``, which names
the file when the key is absent.
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any, TypeVar

from pydantic import BaseModel, ConfigDict, Field, ValidationError

from orbis2.errors import OrbisError
from orbis2.io import write_json
from orbis2.registry import registry

PROBE_TARGETS = tuple(registry().probe_targets)  # registry.yaml: every probe target
EVAL_KINDS = ("steering", "speed", "conditioning")  # one file each, beside the per-system and per-target ones

Num = int | float  # a JSON number as written: an int stays an int, so a record re-writes byte for byte


class Record(BaseModel):
    """Every field required unless it defaults, no unknown key, no coercion (a stage passes lists, ints and
    floats as it writes them): a value of a type its file would not hold fails where the record is built."""

    model_config = ConfigDict(extra="forbid", strict=True)


def _is_none(value: Any) -> bool:
    return value is None


def sometimes() -> Any:
    """A key the stage writes only in some runs: None when absent, and left out of the file when None."""
    return Field(default=None, exclude_if=_is_none)


class Nfe(Record):
    top: int
    bottom: int


class Interval(Record):
    """:class:`orbis2.eval.metrics.stats.Interval` as stored (a paired difference or a mean with its bootstrap)."""

    estimate: Num
    low: Num
    high: Num
    level: Num
    clusters: int
    units: int
    reps: int
    seed: int


class Bootstrapped(Record):
    """An FVD with its clip-bootstrap interval and draws
    (:func:`orbis2.eval.protocols.references.fvd_with_interval`)."""

    fvd: Num
    low: Num
    high: Num
    clips: int
    videos: int
    bootstrap_reps: int
    bootstrap_seed: int
    draws: list[Num]


class SplitFvd(Bootstrapped):
    """A split's FVD over ``seconds`` of rollout (:func:`orbis2.eval.protocols.evaluate.score_rollouts`)."""

    frames: int
    seconds: Num
    resolution: list[int]
    seed: int
    source_resolution: list[int] | None = sometimes()  # eval_fvd's frames; `orbis2 evaluate` states it in its card


class RealFloor(Record):
    """Real vs real on disjoint halves of the clips; ``fvd`` None (with the reason) on fewer than 4 clips."""

    fvd: Num | None
    clips: int
    reason: str | None = sometimes()
    low: Num | None = sometimes()
    high: Num | None = sometimes()
    videos_per_half: int | None = sometimes()
    half_splits: int | None = sometimes()
    seed: int | None = sometimes()
    definition: str | None = sometimes()


class References(Record):
    """The reference rows of a split (:mod:`orbis2.eval.protocols.references`); `orbis2 evaluate` has no
    reconstruction."""

    real_floor: RealFloor
    repeat_last: Bootstrapped
    reconstruction: Bootstrapped | None = sometimes()


class ProtocolCard(Record):
    """Everything needed to reproduce a table's FVDs (:meth:`orbis2.eval.protocols.evaluate.Protocol.card`)."""

    protocol: str
    fps: Num
    seconds: Num
    window_frames: int
    long_seconds: Num
    chunk_seconds: Num
    i3d_frames: int
    frame_selection: str
    stride: Num
    context_frames: int
    resize: str
    source_resolution: list[int]
    clips: int
    videos: int
    i3d: str
    i3d_sha256: str
    bootstrap_reps: int
    bootstrap_seed: int
    floor_splits: int


class Chunk(Record):
    start_s: Num
    end_s: Num
    fvd: Num
    low: Num
    high: Num


class Chunked(Record):
    """Chunked FVD, FVD over the long span and the FVD-slope (:func:`orbis2.eval.protocols.evaluate.chunked_record`)."""

    split: str
    seconds: Num
    chunk_seconds: Num
    videos: int
    clips: int
    seed: int
    chunks: list[Chunk]
    fvd_long: Num
    fvd_long_low: Num
    fvd_long_high: Num
    fvd_slope: Num
    fvd_slope_low: Num
    fvd_slope_high: Num
    bootstrap_reps: int
    bootstrap_seed: int
    fvd_slope_draws: list[Num]


class FirstFrame(Record):
    """The first generated frame's PSNR (dB) against the real frame, the tokenizer's reconstruction's, and the gap
    (reconstruction minus generated, paired per rollout): what the predictor adds to the tokenizer's blur."""

    generated_psnr: Interval
    reconstruction_psnr: Interval
    gap_db: Interval


class FvdRecord(Record):
    """``fvd_<system>.json``: per split of ``evaluation.fvd_splits`` its FVD, reference rows and protocol card;
    the long split's chunked FVD."""

    model: str
    label: str
    parameters: int
    latent_channels: int
    predictors: list[str]
    nfe: Nfe
    starts_per_clip: int
    fvd_material: Num
    fvd: dict[str, SplitFvd]
    references: dict[str, References]
    protocol: dict[str, ProtocolCard]
    chunked: Chunked | None = sometimes()
    first_frame: dict[str, FirstFrame] | None = sometimes()  # per split; records made before it have none


class SegmentationProbe(Record):
    miou: Num
    iou: dict[str, Num]
    classes: list[int]
    val_loss: Num
    train_frames: int
    test_frames: int
    epochs: int


class DepthProbe(Record):
    rmse: Num
    val_loss: Num
    train_frames: int
    test_frames: int
    scored_frames: int
    epochs: int


class ProbeData(Record):
    """The data set each task was probed on; a task no data set labels is left out."""

    segmentation: str | None = sometimes()
    depth: str | None = sometimes()


class BlockProbe(Record):
    block: int
    miou: Num
    rmse: Num


class ProbeRecord(Record):
    """``probe_<target>.json``: linear probes of one representation; a task without labels is None
    (:func:`orbis2.eval.protocols.probe.probe_on_features`). ``block`` is None for a tokenizer or the teacher."""

    target: str
    label: str
    block: int | None
    segmentation: SegmentationProbe | None
    depth: DepthProbe | None
    data: ProbeData
    per_block: list[BlockProbe] | None = sometimes()


class InstrumentCells(Record):
    """One mode's figures by one instrument (:func:`orbis2.eval.protocols.steering.mode_record`)."""

    ade: Num
    ade_low: Num
    ade_high: Num
    turn_deg: Num
    turn_low: Num
    turn_high: Num
    path_length: Num


class SteeringMode(InstrumentCells):
    """The main instrument's figures on top, every instrument's below."""

    samples: int
    speed_scale: Num
    yaw_rate_scale: Num
    commanded_turn_deg: Num
    instruments: dict[str, InstrumentCells]


class TurnStep(Interval):
    commanded: Num


class PathRatio(Record):
    estimate: Num
    low: Num
    high: Num
    commanded: Num
    clusters: int
    note: str


class SteeringResponses(Record):
    """One instrument's scale-free responses (:func:`orbis2.eval.protocols.steering.steering_responses`): the turn ones
    need the yaw-rate modes, the path ratio the speed modes."""

    turn_response_deg: Interval | None = sometimes()
    commanded_turn_response_deg: Num | None = sometimes()
    turn_by_mode_deg: dict[str, Num] | None = sometimes()
    turn_steps_deg: dict[str, TurnStep] | None = sometimes()
    path_ratio: PathRatio | None = sometimes()


class Material(Record):
    turn_deg: Num
    path_ratio: Num


class OdometrySanity(Record):
    """An instrument on the real videos and on shuffled ones
    (:func:`orbis2.eval.protocols.steering.odometry_sanity`)."""

    real_ade: Num
    real_low: Num
    real_high: Num
    shuffled_ade: Num
    shuffled_low: Num
    shuffled_high: Num
    videos: int


class TurnCells(Record):
    turn_deg: Num
    low: Num
    high: Num
    commanded_turn_deg: Num


class TurnReading(Record):
    """A reading of the turn alone (:func:`orbis2.eval.protocols.steering.turn_record`)."""

    modes: dict[str, TurnCells]
    turn_steps_deg: dict[str, TurnStep]
    turn_response_deg: Interval | None = sometimes()
    commanded_turn_response_deg: Num | None = sometimes()


class TruthHorizon(Record):
    """Generated against true frames at one horizon (:func:`orbis2.eval.protocols.truth.horizon_cells`)."""

    seconds: Num
    frame: int
    latent_mse: Interval
    psnr: Interval


class InstrumentOnTruth(Record):
    """The instrument's turn read from the true videos (:func:`orbis2.eval.protocols.truth.instrument_calibration`);
    ``relative_error`` is None where the command does not turn."""

    turn_deg: Interval
    commanded_turn_deg: Num
    relative_error: Interval | None = sometimes()


class TruthMode(Record):
    """One steering mode scored against its true counterfactual: per-frame errors by horizon, FVD of the generated
    against the true videos, the instrument on the truth, and how many true paths hit traffic or left the road."""

    samples: int
    horizons: list[TruthHorizon]
    fvd: Bootstrapped
    instrument: InstrumentOnTruth
    collision: int
    off_road: int


class TruthMargin(Record):
    margin: Interval
    own: Num
    others: Num
    verdict: str


class TruthClaim(Record):
    """:func:`orbis2.eval.protocols.truth.truth_claim` on the rollouts' latent MSE to each command's truth."""

    material: Num
    verdict: str
    modes: dict[str, TruthMargin]
    pairs: dict[str, dict[str, Num]]


class TruthReading(Record):
    """The steering rollouts against the town's true counterfactuals (the ``truth`` stage)."""

    instrument: str
    modes: dict[str, TruthMode]
    claim: TruthClaim


class SteeringRecord(Record):
    """``steering.json``: per steering mode ADE and turn by each instrument, responses, sanity checks, and the
    latent and image readings of the turn; ``truth`` where the data has true counterfactuals (the town)."""

    split: str
    seconds: Num
    samples: int
    clips: int
    seed: int
    inverse_dynamics: str
    instruments: list[str]
    nfe: Nfe
    modes: dict[str, SteeringMode]
    responses: dict[str, SteeringResponses]
    material: Material
    odometry_sanity: OdometrySanity
    sanity: dict[str, OdometrySanity]
    latent_turn: TurnReading
    image_turn: TurnReading
    truth: TruthReading | None = sometimes()


class SpeedRun(Record):
    fps: Num
    peak_memory_mb: Num
    parameters: int
    frames: int
    memory_kind: str
    bottom_nfe: int
    top_nfe: int | None  # None for a flat system
    frames_per_step: int


class SpeedRecord(Record):
    """``speed.json`` / ``speed_all.json``: frames per second and peak memory per timed run."""

    device: str
    memory_kind: str
    batch: int
    seconds: Num
    nfe: Nfe
    models: dict[str, SpeedRun]
    precision: str
    compile: bool
    kv_cache: bool


class VariantRow(Record):
    """A predictor's error with one conditioning input replaced; the reference row (the true input) has no
    clip count or per-seed verdicts."""

    model: str
    metric: str
    variant: str
    error: Num
    effect: Num
    low: Num
    high: Num
    verdict: str
    windows: int
    clips: int | None = sometimes()
    seed_verdicts: list[str] | None = sometimes()


class BaselineRow(Record):
    model: str
    horizon_s: Num
    baseline: str
    model_mse: Num
    baseline_mse: Num
    effect: Num
    low: Num
    high: Num
    verdict: str
    windows: int
    clips: int


class EnergyShares(Record):
    varying_share: Num
    within_clip_share: Num
    repeat_last_relative: Num
    repeat_last_mse: Num
    variation_mse: Num
    frames: int


class ProbeFit(Record):
    r2: Num
    low: Num
    high: Num
    shuffled_r2: Num


class EgoMotionProbe(Record):
    train_pairs: int
    val_pairs: int
    speed: ProbeFit
    yaw_rate: ProbeFit
    penalty: dict[str, Num]
    train_cv_r2: dict[str, dict[str, Num]]
    features: str


class LatentStatistics(Record):
    """Energy shares per latent set and the ego-motion probe
    (:func:`orbis2.eval.protocols.conditioning.latent_statistics`)."""

    step_frames: int
    step_s: Num
    abstract: EnergyShares
    detail: EnergyShares
    ego_motion_probe: EgoMotionProbe


class ResponseStep(Record):
    relative: Num
    low: Num
    high: Num
    verdict: str


class LatentResponse(Record):
    relative: Num
    low: Num
    high: Num
    readout_difference: Num
    real_difference: Num
    windows: int
    clips: int
    verdict: str
    steps: dict[str, ResponseStep] | None = sometimes()  # with the original mode
    ordered: bool | None = sometimes()


class SteeringResponse(Record):
    """The steered predictor's latents under scaled steering
    (:func:`orbis2.eval.protocols.conditioning.latent_steering_response`); a response is None where its motion
    has no modes or windows."""

    model: str
    windows: int
    material: Num
    gain: dict[str, Num]
    modes: dict[str, dict[str, Num | None]]
    responses: dict[str, LatentResponse | None]


class ConditioningRecord(Record):
    """``conditioning.json`` / ``conditioning_all.json``: variant errors, one-step baselines, latent statistics and
    (with a steered predictor in the scope) its response inside the model."""

    split: str
    windows: int
    clips: int
    draws: int
    seeds: list[int]
    threshold: Num
    bootstrap_reps: int
    variants: list[VariantRow]
    baselines: list[BaselineRow]
    latents: LatentStatistics
    steering_response: SteeringResponse | None = sometimes()


class CompressionRow(Record):
    """Compressed or full abstract latents; a null metric is one its inputs did not measure."""

    variant: str
    latent_dim: int
    fvd_long: Num | None
    fvd_slope: Num | None
    miou: Num | None
    rmse: Num | None
    fvd_long_n: int | None = sometimes()
    fvd_slope_n: int | None = sometimes()
    miou_n: int | None = sometimes()
    rmse_n: int | None = sometimes()


class CompressionRecord(Record):
    rows: list[CompressionRow]


class GuidanceSelection(Record):
    """``selection.json`` of tools/select_guidance.py (:func:`orbis2.eval.protocols.steering.choose_guidance`);
    written in field order by :meth:`text`, not sorted like the stages' records."""

    chosen: Num
    resolved: bool
    instrument: str
    material_deg: Num
    smaller_step_low_deg: dict[str, Num]  # by scale, written as a float ("2.0")
    split: str

    def text(self) -> str:
        return json.dumps(to_json(self), indent=2) + "\n"


R = TypeVar("R", bound=Record)


def to_json(record: Record) -> dict[str, Any]:
    """The record as the JSON object its stage writes (keys left out where :func:`sometimes` says so)."""
    return record.model_dump()


def write_record(path: str | Path, record: Record) -> None:
    """The record at ``path``, atomically, formatted as every record is (:func:`orbis2.io.write_json`)."""
    write_json(Path(path), to_json(record))


def from_json(cls: type[R], path: str | Path, stage: str | None = None) -> R:
    """The record of type ``cls`` in ``path``; anything else stops with an error naming the file, each key
    and the stage that writes it (``stage``, e.g. ``eval_fvd_hierarchical``)."""
    path = Path(path)
    rerun = f"re-run {stage}" if stage else "re-run the stage that writes it"
    try:
        data = json.loads(path.read_text())
    except (OSError, json.JSONDecodeError) as err:
        raise OrbisError(f"cannot read {path}: {err}; {rerun}") from err
    if not isinstance(data, dict):
        raise OrbisError(f"{path} holds {type(data).__name__}, expected a JSON object; {rerun}")
    try:
        return cls.model_validate(data)
    except ValidationError as err:
        problems = []
        for e in err.errors():
            what = {"missing": "missing key", "extra_forbidden": "unknown key"}.get(e["type"], e["msg"])
            problems.append(f"{'.'.join(map(str, e['loc'])) or '(top level)'}: {what}")
        written = f" (written by stage {stage})" if stage else ""
        raise OrbisError(f"{path}{written} is not a {cls.__name__}: {'; '.join(problems)}; {rerun}") from None
