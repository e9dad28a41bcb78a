"""Score any model's rollouts under one written-down protocol: FVD, chunked FVD, FVD-slope, reference rows.

One code path for every FVD the project reports: :func:`score_rollouts` takes the
I3D features of the real and generated frames of each window and returns the
records; the ``eval_fvd_<system>`` stage feeds it the frames its rollouts decode,
``orbis2 evaluate`` (:mod:`orbis2.eval.protocols.evaluate_videos`) the frames of video files another
model wrote. Each record carries its :class:`Protocol` card (frames, rate,
windows, context, resize, clips and videos, the I3D weights' checksum, seeds), so
a number can be reproduced from what is printed beside it.

Two protocols:

- ``orbis2``: the windows of the profile's ``evaluation`` section (``seconds``,
  ``long_seconds``, ``chunk_seconds``), clip bootstrap with its ``seed`` and
  ``fvd_bootstrap_reps``.
- ``paper``: the paper's Sec. 4.3: FVD over 6-s rollouts, chunked FVD over
  consecutive 4-s windows of 16-s rollouts (4 chunks, FVD-slope over them).
  The paper does not say how many frames of a window I3D sees, at what frame
  rate, how frames are resized or cropped, which I3D weights or how many
  context frames; we choose 16 evenly spaced frames per window (both ends
  included), the rollouts' own rate, a plain bilinear resize to 224x224 without
  crop, the Kinetics-400 Inception-I3D of the reference implementation, and the
  context the caller states. The paper's clip counts (800 nuPlan, 400
  nuPlan-turns sequences) are a property of the data, recorded, not imposed.
"""

from __future__ import annotations

import csv
import math
from collections.abc import Callable, Sequence
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any

import numpy as np

from orbis2.data.video import VIDEO_SUFFIXES, iter_frames, probe, resample_stride
from orbis2.errors import OrbisError
from orbis2.eval.evaluate_records import EvaluateRecord
from orbis2.eval.metrics.fvd import CLIP_FRAMES, I3D_SIZE, chunk_windows, even_frame_indices, i3d_features
from orbis2.eval.metrics.stats import fvd_slope_interval
from orbis2.eval.protocols.references import fvd_with_interval, real_floor

Features = Callable[[slice], np.ndarray]  # I3D features [N, 400] of the videos' frames in a window
I3D_FEATURES = 400  # Kinetics-400 logits: below this many videos the covariance is rank-deficient


class EvaluateError(OrbisError):
    """The videos or manifest cannot be scored; the message names the file and the fix."""


@dataclass(frozen=True)
class Protocol:
    """How FVD is measured: windows in seconds from the first generated frame, the bootstrap, the floor."""

    name: str
    seconds: float  # the FVD window
    long_seconds: float  # span of the chunked FVD (used when the videos are at least this long)
    chunk_seconds: float
    bootstrap_reps: int
    seed: int
    floor_splits: int

    def short(self, fps: float) -> slice:
        return slice(0, round(self.seconds * fps))

    def chunks(self, fps: float) -> tuple[list[slice], slice]:
        """The consecutive chunk windows of the long span and the span they cover."""
        windows = chunk_windows(round(self.long_seconds * fps), fps, self.chunk_seconds)
        return windows, slice(0, windows[-1].stop)

    def card(self, fps: float, context_frames: int, clips: int, videos: int, i3d_sha256: str,
             source_resolution: Sequence[int]) -> dict[str, Any]:
        """Everything needed to reproduce a table's numbers, printed beside them."""
        return {"protocol": self.name, "fps": fps, "seconds": self.seconds, "window_frames": round(self.seconds * fps),
                "long_seconds": self.long_seconds, "chunk_seconds": self.chunk_seconds,
                "i3d_frames": CLIP_FRAMES, "frame_selection": "evenly spaced over each window, both ends included",
                "stride": round(self.seconds * fps - 1) / (CLIP_FRAMES - 1),
                "context_frames": context_frames, "resize": f"bilinear to {I3D_SIZE}x{I3D_SIZE}, no crop",
                "source_resolution": list(source_resolution), "clips": clips, "videos": videos,
                "i3d": "Inception-I3D, Kinetics-400 logits", "i3d_sha256": i3d_sha256,
                "bootstrap_reps": self.bootstrap_reps, "bootstrap_seed": self.seed,
                "floor_splits": self.floor_splits}


def protocol(name: str, ev) -> Protocol:
    """The named protocol; ``ev`` (an EvaluationConfig) gives ours its windows and both their bootstrap."""
    common = {"bootstrap_reps": ev.fvd_bootstrap_reps, "seed": ev.seed, "floor_splits": ev.floor_splits}
    if name == "orbis2":
        return Protocol("orbis2", ev.seconds, ev.long_seconds, ev.chunk_seconds, **common)
    if name == "paper":
        return Protocol("paper", 6.0, 16.0, 4.0, **common)
    raise EvaluateError(f"unknown protocol {name!r}; choose orbis2 or paper")


def i3d_picks(window: slice) -> np.ndarray:
    """Positions of the CLIP_FRAMES (16) frames of ``window`` that I3D sees (evenly spaced, both ends included)."""
    return window.start + np.asarray(even_frame_indices(window.stop - window.start))


def windows_of(proto: Protocol, fps: float, n_frames: int) -> tuple[slice, list[slice], slice | None]:
    """(FVD window, chunk windows, their span): chunks only when the videos cover ``long_seconds``."""
    short = proto.short(fps)
    if n_frames < short.stop:
        raise EvaluateError(f"the rollouts have {n_frames} generated frames, but protocol {proto.name} scores "
                            f"{proto.seconds:g} s = {short.stop} frames at {fps:g} fps; pass longer rollouts")
    if n_frames >= round(proto.long_seconds * fps):
        chunks, whole = proto.chunks(fps)
        return short, chunks, whole
    return short, [], None


def refuse_short_ones(pairs: list[Pair], lengths: list[int], proto: Protocol, fps: float) -> None:
    """Every rollout is scored over the same windows, those of the shortest, so one short rollout would change
    them for all (a 20-frame one among 35-frame ones dropped the chunked FVD and the FVD-slope of every rollout):
    refuse it, naming it, when it changes what the longest rollouts are scored on."""
    first_window = proto.short(fps).stop
    if max(lengths) < first_window:
        return  # none is long enough: windows_of says so for all of them
    full = windows_of(proto, fps, max(lengths))
    short = [(pair.generated, n) for pair, n in zip(pairs, lengths)
             if n < first_window or windows_of(proto, fps, n) != full]
    if not short:
        return
    needed = round(proto.long_seconds * fps) if full[1] else first_window
    named = ", ".join(f"{path} ({n} frames)" for path, n in short[:3])
    more = f" and {len(short) - 3} more" if len(short) > 3 else ""
    raise EvaluateError(f"{named}{more}: shorter than the {needed} generated frames the other rollouts are scored "
                        f"on ({'FVD, chunked FVD and FVD-slope' if full[1] else 'FVD'}); all are scored on the "
                        f"windows of the shortest, so leave the short one(s) out or pass rollouts of one length")


def chunked_record(split: str, windows: list[slice], whole: slice, real: Features, fake: Features,
                   clusters: list[str], fps: float, proto: Protocol) -> dict[str, Any]:
    """Chunked FVD over consecutive ``chunk_seconds`` windows, FVD over ``whole`` (their span), and the FVD-slope,
    each with a clip-bootstrap interval (all chunks on the same resamples)."""
    reals, fakes = [real(w) for w in windows], [fake(w) for w in windows]
    chunks, slope, slope_draws = fvd_slope_interval(reals, fakes, clusters, proto.bootstrap_reps, seed=proto.seed)
    full = fvd_with_interval(real(whole), fake(whole), clusters, proto.bootstrap_reps, proto.seed)
    return {"split": split, "seconds": len(windows) * proto.chunk_seconds, "chunk_seconds": proto.chunk_seconds,
            "videos": len(clusters), "clips": slope.clusters, "seed": proto.seed,
            "chunks": [{"start_s": w.start / fps, "end_s": w.stop / fps, "fvd": c.estimate,
                        "low": c.low, "high": c.high} for w, c in zip(windows, chunks)],
            "fvd_long": full["fvd"], "fvd_long_low": full["low"], "fvd_long_high": full["high"],
            "fvd_slope": slope.estimate, "fvd_slope_low": slope.low, "fvd_slope_high": slope.high,
            "bootstrap_reps": proto.bootstrap_reps, "bootstrap_seed": proto.seed,
            "fvd_slope_draws": [float(d) for d in slope_draws]}


def score_rollouts(split: str, real: Features, fake: Features, clusters: list[str], fps: float, proto: Protocol,
                   short: slice, chunks: list[slice], whole: slice | None) -> dict[str, Any]:
    """``{"fvd": ...}`` over ``short``, plus ``"chunked"`` when ``chunks`` are given: the records every FVD table
    reports, from the features of the real and generated frames of each window."""
    out: dict[str, Any] = {"fvd": {**fvd_with_interval(real(short), fake(short), clusters, proto.bootstrap_reps,
                                                       proto.seed),
                                   "frames": CLIP_FRAMES, "seconds": proto.seconds, "resolution": [I3D_SIZE, I3D_SIZE],
                                   "seed": proto.seed}}
    if chunks:
        out["chunked"] = chunked_record(split, chunks, whole, real, fake, clusters, fps, proto)
    return out


def sample_size_warnings(fvd: dict[str, Any], references: dict[str, dict[str, Any]]) -> list[str]:
    """What the sample cannot resolve: rank-deficient covariances, and reported gaps inside the interval."""
    warnings = []
    videos, clips = fvd["videos"], fvd["clips"]
    if videos <= I3D_FEATURES:
        warnings.append(f"{videos} videos <= {I3D_FEATURES} I3D features: the covariances are rank-deficient, so FVD "
                        f"is biased upwards and only comparable between systems scored on the same clips")
    half_width = (fvd["high"] - fvd["low"]) / 2
    for name, row in references.items():
        if row.get("fvd") is None:
            continue
        gap = abs(fvd["fvd"] - row["fvd"])
        if gap < half_width:
            warnings.append(f"the gap to {name} ({gap:.1f}) is below the interval's half-width ({half_width:.1f}) "
                            f"at {clips} clips: this sample cannot tell them apart")
    return warnings


# --------------------------------------------------------------------------- videos on disk


@dataclass(frozen=True)
class Pair:
    """One rollout: the generated video, the real video it continues, and its clip (what the bootstrap resamples)."""

    name: str
    generated: Path
    real: Path
    clip: str
    context_frames: int | None = None  # from a manifest's optional column
    trajectory: Path | None = None  # commanded (speed, yaw rate) CSV, times from the first generated frame


def pairs_from_folders(generated: Path, real: Path) -> list[Pair]:
    """Videos of two folders matched by file stem; each is its own clip."""
    for folder in (generated, real):
        if not folder.is_dir():
            raise EvaluateError(f"{folder}: no such folder; pass the folder holding the videos")
    gen = {p.stem: p for p in sorted(generated.iterdir()) if p.suffix.lower() in VIDEO_SUFFIXES}
    ref = {p.stem: p for p in sorted(real.iterdir()) if p.suffix.lower() in VIDEO_SUFFIXES}
    if not gen:
        raise EvaluateError(f"{generated}: holds no video ({', '.join(VIDEO_SUFFIXES)}); pass the generated videos")
    missing = sorted(set(gen) - set(ref))
    if missing:
        raise EvaluateError(f"{real}: no real video named {missing[0]!r} (and {len(missing) - 1} more) for the "
                            f"generated ones; name each real video like the rollout that continues it")
    return [Pair(stem, gen[stem], ref[stem], stem, trajectory=gen[stem].with_suffix(".csv")
                 if gen[stem].with_suffix(".csv").is_file() else None) for stem in sorted(gen)]


def pairs_from_manifest(manifest: Path) -> list[Pair]:
    """Rows ``name, generated, real[, clip][, context_frames][, trajectory]`` (paths relative to the manifest); rows
    of one clip resample together."""
    if not manifest.is_file():
        raise EvaluateError(f"{manifest}: manifest not found; pass a CSV with columns name, generated, real[, clip]")
    with manifest.open(newline="") as f:
        reader = csv.DictReader(f)
        missing = {"name", "generated", "real"} - set(reader.fieldnames or [])
        if missing:
            raise EvaluateError(f"{manifest}: missing column(s) {sorted(missing)}; the header must hold name, "
                                f"generated, real and optionally clip")
        rows = list(reader)
    pairs = []
    for line, row in enumerate(rows, start=2):
        paths = [manifest.parent / row[k] for k in ("generated", "real")]
        for path in paths:
            if not path.is_file():
                raise EvaluateError(f"{manifest}, line {line}: {path} does not exist; fix the path (relative to "
                                    f"the manifest's folder)")
        context = row.get("context_frames")
        if context is not None and not context.strip().isdigit():
            raise EvaluateError(f"{manifest}, line {line}: context_frames {context!r} is not a whole number")
        trajectory = manifest.parent / row["trajectory"] if row.get("trajectory") else None
        if trajectory is not None and not trajectory.is_file():
            raise EvaluateError(f"{manifest}, line {line}: {trajectory} does not exist; fix the path (relative to "
                                f"the manifest's folder)")
        pairs.append(Pair(row["name"], *paths, row.get("clip") or row["name"], int(context) if context else None,
                          trajectory))
    if len({p.name for p in pairs}) != len(pairs):
        raise EvaluateError(f"{manifest}: names repeat; give every rollout its own name")
    return pairs


class PickedVideos:
    """The frames of each video at the given positions (only those are kept in memory)."""

    def __init__(self, paths: list[Path], offset: int, positions: np.ndarray, stride: Callable[[Path], int],
                 what: str):
        self.position = {int(p): i for i, p in enumerate(positions)}
        wanted = {offset + int(p) for p in positions}
        needed = offset + int(positions.max()) + 1
        videos = []
        for path in paths:
            kept = {i: frame for i, frame in enumerate(iter_frames(path, stride(path))) if i in wanted}
            if len(kept) < len(wanted):
                count = sum(1 for _ in iter_frames(path, stride(path)))
                raise EvaluateError(f"{path}: {count} frames, but the protocol needs {needed} {what}; pass "
                                    f"longer videos or a shorter protocol")
            videos.append(np.stack([kept[offset + int(p)] for p in positions]))
        shapes = {v.shape for v in videos}
        if len(shapes) > 1:
            raise EvaluateError(f"videos in {paths[0].parent} differ in size {sorted(shapes)}; resize them alike")
        self.frames = np.stack(videos)

    def clip(self, window: slice) -> np.ndarray:
        return self.frames[:, [self.position[int(p)] for p in i3d_picks(window)]]


def frame_count(path: Path) -> int:
    """Frames in a video: the container's count, or decoded and counted where it reports none."""
    return probe(path).frames or sum(1 for _ in iter_frames(path))


def pairing_check(first_generated: np.ndarray, last_context: np.ndarray, clusters: Sequence[str]) -> dict[str, Any]:
    """How many rollouts start closest to their own clip: FVD compares sets, so it cannot see shuffled pairs.

    A continuation's first frame follows the last context frame of its own real video;
    the check counts the rollouts whose first frame is nearest (mean absolute difference on
    a 4x subsampled grid) to the last context frame of a real video of their own clip
    (several starts in one clip look alike). With correct pairs and a model that continues
    its context nearly all are; with shuffled pairs about one clip's share are.
    """
    a = first_generated[:, ::4, ::4].reshape(len(first_generated), -1).astype(np.float32)
    b = last_context[:, ::4, ::4].reshape(len(last_context), -1).astype(np.float32)
    distance = np.stack([np.abs(row - b).mean(axis=1) for row in a])  # [generated, real]
    labels = np.asarray([str(c) for c in clusters])
    matched = int(np.sum(labels[distance.argmin(axis=1)] == labels))
    return {"matched": matched, "videos": len(a), "fraction": matched / len(a),
            "definition": "rollouts whose first frame is nearest to the last context frame of their own clip"}


def context_frames(pairs: list[Pair], given: int | None, where: Path | None) -> int:
    """The stated context length: ``given``, else the manifest's one value of ``context_frames``."""
    stated = {p.context_frames for p in pairs} - {None}
    if given is not None:
        return given
    if len(stated) == 1:
        return stated.pop()
    raise EvaluateError(f"{where or 'the videos'}: " + ("rows state different context_frames; score them apart"
                        if stated else "pass --context-frames (or a context_frames column in the manifest)"))


def evaluate_pairs(pairs: list[Pair], context_frames: int, proto: Protocol, i3d, i3d_sha256: str,
                   generated_has_context: bool = False, split: str = "videos") -> EvaluateRecord:
    """Score rollouts on disk: the generated videos' frame rate sets the windows; the real videos (the same rate or
    an integer multiple) hold ``context_frames`` context frames, then the continuation.

    Returns the record: the FVD and chunked records of :func:`score_rollouts`, the real-vs-real floor
    and the repeat-last row (the real last context frame held still), the warnings and the card
    (steering scores are added by :mod:`orbis2.eval.protocols.evaluate_steering`).
    """
    if context_frames < 1:
        raise EvaluateError(f"--context-frames {context_frames}: a rollout continues at least one real frame")
    if len(pairs) < 2:
        raise EvaluateError(f"{len(pairs)} rollout(s): FVD needs at least 2 videos (and 2 clips for an interval)")
    first = probe(pairs[0].generated)
    fps = first.fps
    for pair in pairs:
        info = probe(pair.generated)
        if not math.isclose(info.fps, fps, rel_tol=1e-3):
            raise EvaluateError(f"{pair.generated}: {info.fps:g} fps, but {pairs[0].generated} has {fps:g}; "
                                f"write every rollout at one rate")
    lengths = [frame_count(p.generated) - (context_frames if generated_has_context else 0) for p in pairs]
    refuse_short_ones(pairs, lengths, proto, fps)
    short, chunks, whole = windows_of(proto, fps, min(lengths))
    picks = np.unique(np.concatenate([i3d_picks(w) for w in [short, *chunks, *([whole] if whole else [])]]))
    real_stride = {p.real: resample_stride(probe(p.real).fps, round(fps), 1e-3, p.real) for p in pairs}
    clusters = [p.clip for p in pairs]

    gen = PickedVideos([p.generated for p in pairs], context_frames if generated_has_context else 0, picks,
                       lambda _: 1, "generated frames")
    real = PickedVideos([p.real for p in pairs], context_frames, picks, real_stride.__getitem__,
                        f"frames ({context_frames} context + the continuation)")
    last = PickedVideos([p.real for p in pairs], context_frames - 1, np.array([0]), real_stride.__getitem__,
                        "context frames")
    if gen.frames.shape[2:] != real.frames.shape[2:]:
        raise EvaluateError(f"generated videos are {gen.frames.shape[3]}x{gen.frames.shape[2]}, real ones "
                            f"{real.frames.shape[3]}x{real.frames.shape[2]}; write both at one resolution")
    features: dict[tuple[str, int, int], np.ndarray] = {}

    def cached(kind: str, videos: PickedVideos) -> Features:
        def get(window: slice) -> np.ndarray:
            key = (kind, window.start, window.stop)
            if key not in features:
                features[key] = i3d_features(videos.clip(window), i3d)
            return features[key]
        return get

    out = score_rollouts(split, cached("real", real), cached("fake", gen), clusters, fps, proto, short, chunks, whole)
    real_short = cached("real", real)(short)
    still = last.frames[:, [0] * CLIP_FRAMES]
    clips = len(set(clusters))
    references = {"real_floor": real_floor(real_short, clusters, proto.floor_splits, proto.seed) if clips >= 4 else
                  {"fvd": None, "clips": clips, "reason": "needs at least 4 clips (2 per half)"},
                  "repeat_last": fvd_with_interval(real_short, i3d_features(still, i3d), clusters,
                                                   proto.bootstrap_reps, proto.seed)}
    out["references"] = references
    out["pairing"] = pairing_check(gen.clip(short)[:, 0], last.frames[:, 0], clusters)
    out["warnings"] = sample_size_warnings(out["fvd"], references)
    if not chunks:
        out["warnings"].append(f"the rollouts are shorter than {proto.long_seconds:g} s: no chunked FVD or FVD-slope")
    if out["pairing"]["fraction"] < 0.5:
        out["warnings"].insert(0, f"only {out['pairing']['matched']} of {len(pairs)} rollouts start nearest to their "
                                  f"own real video: the pairs look shuffled (check the names or the manifest), or "
                                  f"the rollouts do not continue their context")
    out["protocol"] = proto.card(fps, context_frames, clips, len(pairs), i3d_sha256, gen.frames.shape[2:4])
    out["videos"] = [{**asdict(p), "generated": str(p.generated), "real": str(p.real),
                      "trajectory": None if p.trajectory is None else str(p.trajectory)} for p in pairs]
    return EvaluateRecord.model_validate(out)


def format_table(record: EvaluateRecord) -> str:
    """The figures with their intervals, the reference rows, the warnings and the protocol card, as text."""
    fvd = record.fvd
    lines = [f"FVD ({fvd.seconds:g} s)   {fvd.fvd:.1f} [{fvd.low:.1f}, {fvd.high:.1f}]  "
             f"({fvd.videos} videos, {fvd.clips} clips)"]
    for name, row in reference_rows(record):
        value = f"n/a ({row.reason})" if row.fvd is None else f"{row.fvd:.1f} [{row.low:.1f}, {row.high:.1f}]"
        lines.append(f"  {name:<14}{value}")
    if record.chunked is not None:
        ch = record.chunked
        lines.append("chunked FVD   " + "  ".join(f"{c.start_s:g}-{c.end_s:g} s {c.fvd:.1f} [{c.low:.1f}, {c.high:.1f}]"
                                                  for c in ch.chunks))
        lines.append(f"FVD-slope     {ch.fvd_slope:.1f} [{ch.fvd_slope_low:.1f}, {ch.fvd_slope_high:.1f}]")
    if record.steering is not None:
        st = record.steering
        ade, turn = st.ade_m, st.turn_deg
        lines.append(f"steering ({st.instrument})  ADE {ade.estimate:.2f} m [{ade.low:.2f}, {ade.high:.2f}], turn "
                     f"{turn.estimate:.1f} deg [{turn.low:.1f}, {turn.high:.1f}] of "
                     f"{st.commanded_turn_deg.estimate:.1f} commanded")
    lines += [f"warning: {w}" for w in record.warnings]
    lines.append("protocol: " + ", ".join(f"{k}={v}" for k, v in record.protocol.model_dump().items()))
    return "\n".join(lines)


def reference_rows(record: EvaluateRecord) -> list[tuple[str, Any]]:
    """The record's reference rows by name, in the order they are written (real floor, repeat-last)."""
    refs = record.references
    rows = [(name, getattr(refs, name)) for name in type(refs).model_fields]
    return [(name, row) for name, row in rows if row is not None]
