"""The ``orbis2`` command: use trained models.

``orbis2 rollout`` reads the context from any video, rolls the hierarchical
model forward and writes an mp4 and a GIF; ``orbis2 play`` drives it live in the
browser (:mod:`orbis2.play`). ``orbis2 evaluate`` scores any model's rollouts
against the real videos they continue, through the code the
``eval_fvd`` stages run (:mod:`orbis2.eval.protocols.evaluate`). ``orbis2 convert``
turns nuPlan, PhysicalAI-AV, BDD100K or OpenDV-YouTube into the import layout
(:mod:`orbis2.data.datasets`); ``orbis2 import-weights`` converts the authors' released
weights into our files (:mod:`orbis2.models.official`). User-fixable problems (short video,
bad trajectory CSV, missing or mismatched checkpoints) print one message naming
the file and the fix and exit with status 2.

This module only turns options into library calls (the trained models' loading,
checks and outputs are :mod:`orbis2.inference`'s, shared with ``orbis2 play``);
no library module imports it.
"""

from __future__ import annotations

import argparse
import math
import sys
import time
from pathlib import Path

import numpy as np
import torch
from tqdm import tqdm

from orbis2.accel import cast_for_inference, inference_autocast, set_tf32
from orbis2.data.datasets import DatasetError, bdd100k, nuplan, opendv, physicalai_av
from orbis2.data.parts import part_name
from orbis2.data.video import PLAYABLE_SUFFIXES
from orbis2.errors import OrbisError
from orbis2.eval.metrics.inverse_dynamics import WEIGHTS_FILE
from orbis2.eval.protocols.evaluate import format_table, pairs_from_folders, pairs_from_manifest
from orbis2.eval.protocols.evaluate_videos import evaluate_videos
from orbis2.eval.records import write_record
from orbis2.inference import (
    DEFAULT_ABSTRACT_TF,
    DEFAULT_ACTION,
    abstract_predictor_path,
    compile_models,
    compose,
    consistency_grid,
    decode_latents,
    load_checkpoints,
    load_steering,
    read_context,
    sampler_settings,
    steering_until,
    write_outputs,
)
from orbis2.kinematics import integrate_odometry
from orbis2.latents import encode_frames
from orbis2.registry import layout_path
from orbis2.rollout import (
    cascaded_rollout,
    first_context_end,
    rollout_schedule,
    steering_offsets,
    steering_sequences,
)
from orbis2.run_profile import resolve_profile
from orbis2.stage import freeze_imports
from orbis2.tasks.official import unconverted_steering

# --------------------------------------------------------------------------- rollout command


def rollout_command(args: argparse.Namespace) -> str:
    check_numbers(args)
    cfg, which = resolve_profile(args.params, args.profile, [
        args.detail_tokenizer, args.abstract_tokenizer, abstract_predictor_path(args.abstract_predictor),
        args.detail_predictor])
    print(f"orbis2 rollout: {which}", file=sys.stderr)
    data = cfg.data
    steps = max(1, math.ceil(args.seconds * data.abstract_hz))
    context_end = first_context_end(data)
    schedule = rollout_schedule(data, context_end, steps)
    frames = read_context(args.video, cfg, context_end + 1)
    odometry, odometry_path = load_steering(args.trajectory, args.video)
    if odometry is not None:
        steering_until(odometry, odometry_path, schedule[-1].detail_target[-1] / data.fps, args.hold_last)

    detail_tok, abstract_tok, abstract_path, abstract_pred, detail_pred = load_checkpoints(
        args.detail_tokenizer, args.abstract_tokenizer, args.abstract_predictor, args.detail_predictor, args.device,
        cfg, args.params)
    device = next(detail_pred.model.parameters()).device

    steering = path = None
    if odometry is not None:
        if abstract_pred.model.steering is None:
            raise OrbisError(f"{abstract_path}: this abstract predictor is not steered but {odometry_path} gives a "
                             f"trajectory; train the action stage or drop --trajectory")
        if unconverted_steering(abstract_pred.meta, abstract_path):
            raise OrbisError(unconverted_steering(abstract_pred.meta, abstract_path))
        if "steering" not in abstract_pred.meta:
            raise OrbisError(f"{abstract_path}: a steered predictor without its steering scale in the file; "
                             f"re-train it with the action stage (python stages/predictor.py action)")
        offsets = steering_offsets(abstract_pred.meta["steering"], data.fps, abstract_path)
        last = needed = schedule[-1].detail_target[-1]
        if offsets is not None:  # the authors' steering also reads the commands after the predicted frame
            needed = max(last, schedule[-1].abstract_context[-1] + max(offsets))
            steering_until(odometry, odometry_path, needed / data.fps, args.hold_last)
        t = np.arange(needed + 1) / data.fps
        speed = np.interp(t, odometry["timestamp"], odometry["speed"]) * args.speed_scale
        yaw_rate = np.interp(t, odometry["timestamp"], odometry["yaw_rate"]) * args.yaw_rate_scale
        steering = steering_sequences(schedule, speed, yaw_rate, abstract_pred.meta["steering"]["scale"], offsets)
        steering = steering[None].to(device)
        x, y, _ = integrate_odometry(speed[context_end:last + 1], yaw_rate[context_end:last + 1], data.fps)
        path = (x, y)

    first = schedule[0]
    detail_ctx = detail_tok.normalize(encode_frames(detail_tok, frames[list(first.detail_context)]))
    abstract_ctx = abstract_tok.normalize(encode_frames(abstract_tok, frames[list(first.abstract_context)]))
    generator = torch.Generator(device=device).manual_seed(args.seed)
    if device.type == "cuda":
        set_tf32(True)
    for predictor in (abstract_pred, detail_pred):  # bf16 weights cast once on CUDA (a no-op on the CPU)
        cast_for_inference(predictor.model, device, args.precision)
    if args.compile:
        compile_models(abstract_pred, detail_pred, detail_tok)
    abstract_nfe, detail_nfe, guidance, line = sampler_settings(args.abstract_nfe, args.detail_nfe,
                                                                args.steering_guidance, cfg, detail_pred,
                                                                steering is not None)
    grid = consistency_grid(abstract_pred, abstract_path, args.abstract_nfe)
    if grid is not None:
        line += f"; the abstract predictor is consistency-distilled: {len(grid)} steps at {grid}"
    for name, predictor in (("abstract", abstract_pred), ("detail", detail_pred)):
        if predictor.meta.get("sampling", {}).get("method", "").startswith("heun"):
            line += f"; the authors sample the {name} predictor with Heun steps, this rollout with Euler steps"
    print(f"orbis2 rollout: {line}", file=sys.stderr)
    with tqdm(total=steps, desc="rollout", unit="step") as bar, inference_autocast(device, args.precision):
        details, _ = cascaded_rollout(
            abstract_pred.model, detail_pred.model, detail_ctx[None].to(device), abstract_ctx[None].to(device),
            steps, generator, abstract_nfe=abstract_nfe, detail_nfe=detail_nfe,
            abstract_hz=data.abstract_hz, detail_hz=data.detail_hz, steering=steering,
            on_step=lambda _: bar.update(1), kv_cache=not args.no_kv_cache, steering_guidance=guidance,
            abstract_grid=grid)

    context_frames = frames[list(first.detail_context)]
    video = np.concatenate([context_frames, decode_latents(detail_tok, details[0], device, args.precision)])
    indices = np.array(list(first.detail_context) + [i for s in schedule for i in s.detail_target])
    real = None
    if args.side_by_side:
        real = np.zeros_like(video)
        available = indices < len(frames)
        real[available] = frames[indices[available]]
    out = compose(video, real, path, np.clip(indices - context_end, 0, None))
    gif = write_outputs(args.out, out, data.detail_hz)
    mode = "unconditional" if steering is None else f"steered by {odometry_path}"
    return f"wrote {args.out} and {gif}: {len(out)} frames at {data.detail_hz} Hz, {steps} steps, {mode}"


def check_numbers(args: argparse.Namespace) -> None:
    """Numbers argparse accepts but a rollout cannot use (NaN, infinity, zero or negative lengths, no steps,
    negative guidance)."""
    for flag, value in (("--seconds", args.seconds), ("--speed-scale", args.speed_scale),
                        ("--yaw-rate-scale", args.yaw_rate_scale)):
        if not math.isfinite(value):
            raise OrbisError(f"{flag} {value}: not a finite number")
    if args.seconds <= 0:
        raise OrbisError(f"--seconds {args.seconds:g}: the rollout length must be > 0")
    if args.out.suffix.lower() not in PLAYABLE_SUFFIXES:
        raise OrbisError(f"--out {args.out}: the video is written as VP9, in .mp4 or .webm; change the suffix")
    check_sampler(args)


def check_sampler(args: argparse.Namespace) -> None:
    """Sampler options a rollout cannot use (None: the evaluation's, :func:`~orbis2.inference.sampler_settings`)."""
    guidance = args.steering_guidance
    if guidance is not None and not math.isfinite(guidance):
        raise OrbisError(f"--steering-guidance {guidance}: not a finite number")
    if guidance is not None and guidance < 0:
        raise OrbisError(f"--steering-guidance {guidance:g}: must be >= 0 (1: no guidance)")
    for flag, value in (("--abstract-nfe", args.abstract_nfe), ("--detail-nfe", args.detail_nfe)):
        if value is not None and value < 1:
            raise OrbisError(f"{flag} {value}: needs at least 1 function evaluation per sample")


def add_sampler_options(p: argparse.ArgumentParser) -> None:
    """The sampler's options of ``orbis2 rollout`` and ``orbis2 play`` (:func:`~orbis2.inference.sampler_settings`)."""
    g = p.add_argument_group("sampler", "default: the sampler the run's evaluation used (params.yaml's evaluation "
                                        "section of the profile: the paper's 15 / 30 steps at gpu and paper)")
    g.add_argument("--abstract-nfe", type=int, default=None, help="Euler steps per abstract latent")
    g.add_argument("--detail-nfe", type=int, default=None,
                   help="Euler steps per detail window (a distilled detail predictor's own steps come first)")
    g.add_argument("--steering-guidance", type=float, default=None,
                   help="classifier-free guidance on the steering (1: none, the paper's sampler)")


def add_rollout_parser(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("rollout", help="roll the hierarchical world model forward from a video's context")
    p.add_argument("--video", type=Path, required=True, help="context video (any rate that is a multiple of data.fps)")
    p.add_argument("--trajectory", type=Path, default=None,
                   help="CSV with columns timestamp, speed, yaw_rate, or an episode's .parquet "
                        "(default: <video>.csv or <video>.parquet if present)")
    p.add_argument("--hold-last", action="store_true",
                   help="a trajectory shorter than the rollout keeps its last speed and yaw rate (default: error)")
    p.add_argument("--speed-scale", type=float, default=1.0, help="multiply the speeds (counterfactuals)")
    p.add_argument("--yaw-rate-scale", type=float, default=1.0, help="multiply the yaw rates (counterfactuals)")
    p.add_argument("--seconds", type=float, default=16.0, help="rollout length in seconds")
    p.add_argument("--out", type=Path, required=True, help="output video (.mp4 or .webm; VP9) and a GIF with its stem")
    p.add_argument("--detail-tokenizer", type=Path, default=layout_path("tokenizer", "detail") / "tokenizer.pt")
    p.add_argument("--abstract-tokenizer", type=Path, default=layout_path("tokenizer", "abstract") / "tokenizer.pt")
    p.add_argument("--abstract-predictor", type=Path, default=None,
                   help=f"default: {DEFAULT_ACTION}, else {DEFAULT_ABSTRACT_TF}")
    p.add_argument("--detail-predictor", type=Path, default=layout_path("predictor", "detail") / "predictor.pt")
    p.add_argument("--params", type=Path, default=Path("params.yaml"))
    p.add_argument("--profile", default=None,
                   help="smoke | default | gpu | paper (default: the one the files it reads were made with)")
    p.add_argument("--side-by-side", action="store_true", help="show the real continuation on the left")
    p.add_argument("--device", default=None, help="default: cuda if available, else cpu")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--precision", choices=("bf16", "fp32"), default="bf16",
                   help="bf16 autocast on CUDA (default) or fp32; the CPU always runs fp32")
    add_sampler_options(p)
    p.add_argument("--compile", action="store_true",
                   help="torch.compile the predictors and the decoder (compiles once per rollout shape; about 1.2x "
                        "on the CPU after a minute of compiling, more on CUDA)")
    p.add_argument("--no-kv-cache", action="store_true",
                   help="recompute the abstract predictor's context at every Euler step (for comparison)")
    p.set_defaults(run=rollout_command)


def evaluate_command(args: argparse.Namespace) -> str:
    """Score a folder (or manifest) of rollouts; write the record as JSON and return the table."""
    if args.manifest is not None:
        if args.generated is not None or args.real is not None:
            raise OrbisError("--manifest names the videos itself; drop --generated and --real")
        pairs = pairs_from_manifest(args.manifest)
    elif args.generated is None or args.real is None:
        raise OrbisError("pass --generated and --real folders (matched by file name), or --manifest")
    else:
        pairs = pairs_from_folders(args.generated, args.real)
    cfg, which = resolve_profile(args.params, args.profile, [pairs[0].real, pairs[0].generated])
    print(f"orbis2 evaluate: {which}", file=sys.stderr)
    record = evaluate_videos(pairs, cfg, context=args.context_frames,
                             where=args.manifest, protocol_name=args.protocol,
                             generated_has_context=args.generated_has_context, split=args.split, i3d=args.i3d,
                             instrument=args.instrument, instrument_weights=args.instrument_weights,
                             hfov_deg=args.hfov_deg, device=args.device)
    if args.out is not None:
        write_record(args.out, record)
    return format_table(record)


def add_evaluate_parser(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("evaluate", help="score any model's rollouts: FVD, chunked FVD, FVD-slope, reference rows")
    p.add_argument("--generated", type=Path, default=None, help="folder of generated videos (the continuations)")
    p.add_argument("--real", type=Path, default=None,
                   help="folder of the real videos they continue, same file stems: context frames, then the truth")
    p.add_argument("--manifest", type=Path, default=None,
                   help="CSV with columns name, generated, real and optionally clip (rows of one clip resample "
                        "together) and context_frames, paths relative to the CSV; instead of --generated/--real")
    p.add_argument("--context-frames", type=int, default=None,
                   help="frames at the start of each real video the model was given as context (default: the "
                        "manifest's context_frames column)")
    p.add_argument("--generated-has-context", action="store_true",
                   help="the generated videos start with the same context frames (they are skipped)")
    p.add_argument("--protocol", choices=("orbis2", "paper"), default="orbis2",
                   help="orbis2: the profile's evaluation windows; paper: 6-s FVD, 4 x 4-s chunks (default: orbis2)")
    p.add_argument("--instrument", choices=("learned", "opencv"), default="learned",
                   help="reads the trajectory of rollouts that have one: the inverse_dynamics stage's network "
                        "(default) or OpenCV visual odometry")
    p.add_argument("--instrument-weights", type=Path, default=layout_path("inverse_dynamics") / WEIGHTS_FILE,
                   help="the learned instrument's weights (default: %(default)s)")
    p.add_argument("--hfov-deg", type=float, default=None,
                   help="horizontal field of view of the rollouts' camera (default: the town camera's)")
    p.add_argument("--split", default="videos", help="name of this set in the record (default: videos)")
    p.add_argument("--out", type=Path, default=None, help="write the record (FVDs, intervals, card) as JSON")
    p.add_argument("--i3d", type=Path, default=None, help="I3D weights (default: assets.dir/i3d_kinetics400.pt)")
    p.add_argument("--params", type=Path, default=Path("params.yaml"))
    p.add_argument("--profile", default=None,
                   help="smoke | default | gpu | paper (default: the one the files it reads were made with)")
    p.add_argument("--device", default=None, help="default: cuda if available, else cpu")
    p.set_defaults(run=evaluate_command)


def convert_command(args: argparse.Namespace) -> str:
    """Turn a dataset tree into the import layout under ``--out``; bad items are skipped and reported. With
    ``--parts N --part I`` part I only (one job of N side by side); without ``--part`` every part not yet done, then
    the report of all of them (orbis2.data.datasets.convert_items)."""
    start = time.perf_counter()
    if args.parts < 1 or (args.part is not None and not 0 <= args.part < args.parts):
        raise DatasetError(f"--part {args.part} --parts {args.parts}: parts must be >= 1 and 0 <= part < parts")
    parts = {"parts": args.parts, "part": args.part}
    if args.dataset == "nuplan":
        report = nuplan.convert(args.db, args.sensor_root, args.out, args.split, args.channel, args.clip_seconds,
                                args.turns_deg, args.strict, **parts)
    elif args.dataset == "physicalai-av":
        report = physicalai_av.convert(args.root, args.out, args.split, args.camera, args.include_invalid,
                                       args.strict, **parts)
    elif args.dataset == "bdd100k":
        report = bdd100k.convert(args.root, args.out, args.allow_missing_info, args.max_fix_delay, args.strict,
                                 **parts)
    else:
        report = opendv.convert(args.meta, args.videos, args.out, args.limit, args.strict, **parts)
    if args.part is not None:
        return (f"part {part_name(args.part, args.parts)}: {report.summary()} -> {args.out} in "
                f"{time.perf_counter() - start:.1f} s; the report: the same command without --part")
    path = report.write()
    if not report.converted:
        raise DatasetError(f"{report.summary()}: nothing usable was converted; see {path} for each item's problem "
                           f"and fix")
    return (f"{report.summary()} -> {args.out} in {time.perf_counter() - start:.1f} s; report: {path}; next: "
            f"python stages/import.py --videos {args.out}")


def add_convert_parser(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("convert", help="turn nuPlan, PhysicalAI-AV, BDD100K or OpenDV-YouTube into the import layout")
    datasets = p.add_subparsers(dest="dataset", required=True)
    n = datasets.add_parser("nuplan", help="front camera + ego poses of nuPlan log databases")
    n.add_argument("--db", type=Path, required=True, help="a log .db, or a folder of them (nuplan-v1.1/splits/<s>)")
    n.add_argument("--sensor-root", type=Path, required=True, nargs="+", action="extend",
                   help="nuplan-v1.1/sensor_blobs; several folders (one per unpacked camera archive) may be given")
    n.add_argument("--split", default="val", help="import split to write (default: val)")
    n.add_argument("--channel", default="CAM_F0", help="camera channel (default: CAM_F0, the front camera)")
    n.add_argument("--clip-seconds", type=float, default=20.0, help="cut logs into clips this long (default: 20)")
    n.add_argument("--turns-deg", type=float, default=None,
                   help="keep only clips whose heading changes by at least this many degrees (nuPlan-turns)")
    a = datasets.add_parser("physicalai-av", help="front camera + egomotion of PhysicalAI-Autonomous-Vehicles")
    a.add_argument("--root", type=Path, required=True, help="dataset root (features.csv, clip_index.parquet, chunks)")
    a.add_argument("--split", default=None,
                   help="put every clip into this import split (default: each clip's split in clip_index.parquet, "
                        "test -> heldout)")
    a.add_argument("--include-invalid", action="store_true",
                   help="convert clips whose clip_is_valid is false too (default: skip and report them)")
    a.add_argument("--camera", default="camera_front_wide_120fov", help="camera feature (default: %(default)s)")
    b = datasets.add_parser("bdd100k", help="BDD100K videos with their info (GPS/IMU) files")
    b.add_argument("--root", type=Path, required=True, help="the bdd100k folder holding videos/ and info/")
    b.add_argument("--allow-missing-info", action="store_true", help="link videos without info, without odometry")
    b.add_argument("--max-fix-delay", type=float, default=bdd100k.MAX_FIX_DELAY,
                   help="bridge a first GPS fix up to this many seconds after the first frame (default: %(default)s)")
    o = datasets.add_parser("opendv", help="OpenDV-YouTube videos, without odometry (unconditional)")
    o.add_argument("--meta", type=Path, required=True, help="meta/OpenDV-YouTube.json")
    o.add_argument("--videos", type=Path, required=True, help="download root (<youtuber>/<videoid>.mp4)")
    o.add_argument("--limit", type=int, default=None, help="convert at most this many videos")
    for parser in (n, a, b, o):
        parser.add_argument("--out", type=Path, default=Path("data/videos"),
                            help="import folder to write into (default: data/videos)")
        parser.add_argument("--strict", action="store_true",
                            help="stop at the first bad item (default: skip it, list it in the report, go on)")
        parser.add_argument("--parts", type=int, default=1,
                            help="split the items into this many parts, one job each (default: 1)")
        parser.add_argument("--part", type=int, default=None, metavar="I",
                            help="convert part I (0-based) only; then the command without --part writes the report")
    p.set_defaults(run=convert_command)


# --------------------------------------------------------------------------- play command


def play_command(args: argparse.Namespace) -> str:
    from orbis2.play import play_command as serve  # the web server's imports, for this command only

    check_sampler(args)
    if args.threads is not None and args.threads < 1:
        raise OrbisError(f"--threads {args.threads}: needs at least 1")
    return serve(args)


def add_play_parser(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("play", help="drive the world model live in the browser (docs/play.md)")
    p.add_argument("--host", default="127.0.0.1", help="address to listen on (default: this machine only)")
    p.add_argument("--port", type=int, default=8765, help="port to listen on (0: a free one)")
    p.add_argument("--video", type=Path, action="append", default=[],
                   help="also offer this video as a scene (odometry beside it: <stem>.csv); repeatable")
    p.add_argument("--record-dir", type=Path, default=Path("recordings"), help="where recordings are written")
    p.add_argument("--detail-tokenizer", type=Path, default=layout_path("tokenizer", "detail") / "tokenizer.pt")
    p.add_argument("--abstract-tokenizer", type=Path, default=layout_path("tokenizer", "abstract") / "tokenizer.pt")
    p.add_argument("--abstract-predictor", type=Path, default=None, help=f"default: {DEFAULT_ACTION}")
    p.add_argument("--detail-predictor", type=Path, default=layout_path("predictor", "detail") / "predictor.pt")
    p.add_argument("--params", type=Path, default=Path("params.yaml"))
    p.add_argument("--profile", default=None, help="smoke | default | gpu | paper (default: the file's `profile`)")
    p.add_argument("--device", default=None, help="default: cuda if available, else cpu")
    p.add_argument("--seed", type=int, default=0, help="the seed of every drive (and of its recording's replay)")
    p.add_argument("--precision", choices=("bf16", "fp32"), default="bf16",
                   help="bf16 autocast on CUDA (default) or fp32; the CPU always runs fp32")
    p.add_argument("--compile", action="store_true",
                   help="torch.compile the predictors and the decoder during the warm-up (a minute on the CPU the "
                        "first time, then from the compile cache; about 1.2x on the CPU)")
    p.add_argument("--threads", type=int, default=None,
                   help="torch threads on the CPU (default: the cores less one, which the browser and the true "
                        "view use)")
    add_sampler_options(p)
    p.set_defaults(run=play_command)


# --------------------------------------------------------------------------- import-weights command


def import_weights_command(args: argparse.Namespace) -> str:
    """Convert the authors' released networks into our checkpoint files (docs/official-weights.md)."""
    from orbis2.models.official import import_release

    start = time.perf_counter()
    manifest = import_release(args.folder, args.out, "additive" if args.authors_causal_mask else "hard")
    written = ", ".join(sorted(manifest["written"]))
    return (f"imported {len(manifest['files'])} files of {args.folder} -> {args.out} ({written}) in "
            f"{time.perf_counter() - start:.1f} s; manifest: {args.out / 'manifest.json'}")


def add_import_weights_parser(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("import-weights", help="convert the authors' released Orbis 2 weights into our files")
    p.add_argument("folder", type=Path, help="the downloaded release (hf download sud0301/orbis2 --local-dir F)")
    p.add_argument("--out", type=Path, default=Path("data/official"), help="where to write (default: %(default)s)")
    p.add_argument("--authors-causal-mask", action="store_true",
                   help="keep their abstract predictor's temporal mask, which adds +1 to the allowed scores and lets "
                        "the future leak in (their outputs exactly); default: our hard causal mask")
    p.set_defaults(run=import_weights_command)


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(prog="orbis2", description=__doc__.splitlines()[0])
    sub = parser.add_subparsers(dest="command", required=True)
    add_rollout_parser(sub)
    add_evaluate_parser(sub)
    add_convert_parser(sub)
    add_play_parser(sub)
    add_import_weights_parser(sub)
    args = parser.parse_args(argv)
    freeze_imports()
    try:
        print(args.run(args))
    except OrbisError as err:
        print(f"orbis2 {args.command}: error: {err}", file=sys.stderr)
        sys.exit(2)


if __name__ == "__main__":
    main()
