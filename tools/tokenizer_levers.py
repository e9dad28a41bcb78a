"""One lever of the detail tokenizer: train it with some settings changed and score it as its stage does.

    python tools/tokenizer_levers.py base                                   # the profile's settings
    python tools/tokenizer_levers.py lr1e3 --set train.lr=0.001
    python tools/tokenizer_levers.py lr1e3_mse --set train.lr=0.001 --set mse_weight=1.0 --against base
    python tools/tokenizer_levers.py wide --model decoder_channels=32 --against base
    python tools/tokenizer_levers.py percept --perceptual 0.25 --against base
    python tools/tokenizer_levers.py percept_half_res --perceptual 0.75 --perceptual-taps conv_1,conv_2 --against base

Trains on the existing shards (``data/shards``) with the shared training loop in
``data/runs/tokenizer_levers/<name>/`` (resumable), then measures what the ``tokenizer_detail`` stage
reports: val PSNR through the continuous latent (what the predictors' latents decode like) and
through the codebook, SSIM, and the reconstruction FID, plus training seconds per step. ``--set``
changes a key of the ``tokenizer_detail`` section (``train.<key>`` for its training settings),
``--model`` a field of the tokenizer's size preset; values are read as YAML. ``--perceptual W`` adds W times
an LPIPS-style distance on the Inception FID network's maps named by ``--perceptual-taps``
(``InceptionPerceptual``; the paper's LPIPS weights are not available offline) to the reconstruction
terms. A training folder refuses settings other than those it was started with. Each run appends one
JSON row to ``--out`` (default ``reports/tokenizer_levers.jsonl``) with the per-frame continuous
PSNRs and their clips; ``--against NAME`` adds the paired difference to that earlier row with a
clip-bootstrap interval. Time nothing beside another torch process: the seconds are the machine's.
The lever table in docs/pipeline.md ("The detail tokenizer") comes from this procedure.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import math
import time
from pathlib import Path

import torch
import yaml

from orbis2.accel import conv_layout
from orbis2.assets import asset_path
from orbis2.config.params import load_config
from orbis2.data.shards import load_manifest
from orbis2.eval.metrics.stats import paired_difference
from orbis2.losses import feature_distance, psnr
from orbis2.models.discriminator import build_discriminator
from orbis2.models.sizes import tokenizer_config
from orbis2.models.teachers import PERCEPTUAL_TAPS, InceptionPerceptual
from orbis2.models.tokenizer import build_detail_tokenizer
from orbis2.tasks.tokenizers import DetailGAN, DetailTokenizerTask, _final_model, frame_batches, reconstruction_fid
from orbis2.train import train


def assignments(pairs: list[str]) -> dict:
    """``key=value`` pairs -> {key: YAML value}."""
    out = {}
    for pair in pairs:
        key, sep, value = pair.partition("=")
        if not sep:
            raise SystemExit(f"{pair!r}: expected key=value")
        out[key] = yaml.safe_load(value)
    return out


class LeverTask(DetailTokenizerTask):
    """The stage's task with the tokenizer (and its discriminator) built at ``sizes`` instead of the preset's."""

    def __init__(self, cfg, shards, out_dir, sizes):
        super().__init__(cfg, shards, out_dir)
        self.sizes = sizes

    def build_model(self) -> DetailGAN:
        return DetailGAN(build_detail_tokenizer(self.sizes), build_discriminator(self.sizes))


class PerceptualLeverTask(LeverTask):
    """The lever task with ``weight`` x the perceptual distance among the reconstruction terms (as LPIPS is in
    taming's nll, so the adaptive GAN weight balances against it too)."""

    def __init__(self, cfg, shards, out_dir, sizes, network: InceptionPerceptual, weight: float):
        super().__init__(cfg, shards, out_dir, sizes)
        self.network, self.weight = network, weight

    def reconstruction_loss(self, recon, images):
        rec, metrics = super().reconstruction_loss(recon, images)
        with torch.no_grad():
            target = self.network(images)
        distance = feature_distance(self.network(recon), target)
        return rec + self.weight * distance, {**metrics, "perceptual": distance.detach()}


def changed_section(section, settings: dict):
    """``section`` with ``settings`` applied (``train.<key>`` for its training settings); unknown keys stop."""
    train_keys = {k.removeprefix("train."): v for k, v in settings.items() if k.startswith("train.")}
    own = {k: v for k, v in settings.items() if not k.startswith("train.")}
    try:
        return dataclasses.replace(section, **own, train=dataclasses.replace(section.train, **train_keys))
    except TypeError as err:
        raise SystemExit(f"--set: {err}") from err


@torch.no_grad()
def frame_psnrs(tokenizer, shards: Path, count: int, batch_size: int, seed: int) -> list[float]:
    """Continuous-path PSNR of each of the stage's ``count`` val frames."""
    return [float(v) for images in frame_batches(shards, "val", count, batch_size, seed)
            for v in psnr(tokenizer.decode(tokenizer.encode(images)), images, "none")]


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("name", help="the row's name (and its training folder)")
    parser.add_argument("--set", action="append", default=[], metavar="KEY=VALUE",
                        help="a tokenizer_detail setting (train.<key> for training)")
    parser.add_argument("--model", action="append", default=[], metavar="FIELD=VALUE",
                        help="a field of the tokenizer size preset (e.g. decoder_channels=32)")
    parser.add_argument("--perceptual", type=float, default=0.0, metavar="W",
                        help="weight of the Inception perceptual distance among the reconstruction terms")
    parser.add_argument("--perceptual-taps", default=",".join(PERCEPTUAL_TAPS), metavar="LAYERS",
                        help="the Inception layers the perceptual distance compares, comma-separated")
    parser.add_argument("--against", help="an earlier row's name: the paired PSNR difference to it")
    parser.add_argument("--profile", default=None, help="params.yaml's profile unless given")
    parser.add_argument("--shards", type=Path, default=Path("data/shards"))
    parser.add_argument("--assets", type=Path, default=Path("data/assets"))
    parser.add_argument("--out", type=Path, default=Path("reports/tokenizer_levers.jsonl"))
    args = parser.parse_args()

    cfg = load_config("params.yaml", args.profile)
    section = changed_section(cfg.tokenizer_detail, assignments(args.set))
    try:
        sizes = tokenizer_config(section.preset, **{**section.model, **assignments(args.model)})
    except Exception as err:  # the preset's own checks name the field
        raise SystemExit(f"--model: {err}") from err
    inception = asset_path(args.assets, "inception_v3")
    work = Path("data/runs/tokenizer_levers") / args.name
    taps = tuple(args.perceptual_taps.split(","))
    settings = {"set": assignments(args.set), "model": assignments(args.model), "perceptual": args.perceptual,
                **({"perceptual_taps": list(taps)} if args.perceptual else {})}
    record = work / "lever.json"
    if record.is_file() and json.loads(record.read_text()) != settings:
        raise SystemExit(f"{work}: started with {record.read_text()}, not {json.dumps(settings)}; "
                         f"choose another name or delete the folder")
    work.mkdir(parents=True, exist_ok=True)
    record.write_text(json.dumps(settings))
    task = (PerceptualLeverTask(section, args.shards, work, sizes, conv_layout(InceptionPerceptual(inception, taps)),
                                args.perceptual)
            if args.perceptual else LeverTask(section, args.shards, work, sizes))
    start = time.perf_counter()
    result = train(task, section.train, work)
    seconds = time.perf_counter() - start
    model = _final_model(task, result.model_path)
    metrics = task.evaluate(model, result.step)
    tc = section.train
    fid = reconstruction_fid(model.tokenizer, inception,
                             frame_batches(args.shards, "val", section.fid_images, tc.batch_size, tc.seed))
    per_frame = frame_psnrs(model.tokenizer, args.shards, section.eval_images, tc.batch_size, tc.seed)
    # the stage's val frames: ceil(count / clips) consecutive frames from each clip in turn
    per_clip = math.ceil(section.eval_images / load_manifest(args.shards)["splits"]["val"]["samples"])
    clips = [i // per_clip for i in range(len(per_frame))]
    row = {"name": args.name, "profile": cfg.profile, **settings,
           "steps": result.step, "train_s": round(seconds, 1), "step_s": round(seconds / max(1, result.step), 3),
           "decoder_parameters": sum(p.numel() for p in model.tokenizer.decoder.parameters()),
           "rfid": fid, "frames": len(per_frame), "clips": len(set(clips)), **metrics,
           "psnr_per_frame": per_frame, "clip_of_frame": clips}
    if args.against:
        rows = {r["name"]: r for r in map(json.loads, args.out.read_text().splitlines())} if args.out.is_file() else {}
        if args.against not in rows:
            raise SystemExit(f"--against {args.against}: no such row in {args.out}")
        base = rows[args.against]
        if base["clip_of_frame"] != clips:
            raise SystemExit(f"--against {args.against}: measured on other frames; run both on the same shards")
        row["psnr_gain_db"] = paired_difference(per_frame, base["psnr_per_frame"], clips).to_dict()
    args.out.parent.mkdir(parents=True, exist_ok=True)
    with args.out.open("a") as f:
        f.write(json.dumps(row) + "\n")
    gain = row.get("psnr_gain_db")
    print(f"{args.name}: {result.step} steps, {row['step_s']} s/step, PSNR {metrics['val_psnr_continuous']:.2f} dB "
          f"continuous, {metrics['val_psnr']:.2f} dB through the codebook, SSIM {metrics['val_ssim']:.3f}, "
          f"rFID {fid:.1f}" + (f"; vs {args.against}: {gain['estimate']:+.2f} dB [{gain['low']:+.2f}, "
                               f"{gain['high']:+.2f}]" if gain else ""))


if __name__ == "__main__":
    main()
