"""What the sampler contributes to a rollout's blur: the hierarchy rolled out from the same starts and noise with
other Euler steps, scored frame by frame against the real frames and the tokenizer's reconstruction of them.

    python tools/sampler_sweep.py                                    # the profile's evaluation sampler alone
    python tools/sampler_sweep.py --setting detail12:bottom_nfe=12 --setting top15:top_nfe=15

Run in a project whose main job has finished (its latent cache, tokenizers and predictors). Each setting
(``NAME:key=value,...``; keys ``top_nfe``, ``bottom_nfe``) rolls out ``--seconds`` from the evaluation's
starts of ``--split`` (``evaluation.starts_per_clip`` per clip, its seed, so every setting draws the same
noise) and reports, per horizon in ``--horizons`` (seconds after the last context frame; 0.1 is the first
generated frame), the mean PSNR of the generated frame against the real one, the tokenizer's own
reconstruction's PSNR, and the paired gap, each with a clip-bootstrap interval; the sharpness of the
generated frame and of the reconstruction (the energy of their Laplacian over the real frame's: 1 keeps
the real detail, below 1 is blur; PSNR alone rewards blur, the mean of what may come); and, against the
first setting (``base``, the evaluation's sampler), the paired PSNR and sharpness differences per
horizon. One JSON row per setting goes to ``--out``; the table prints. Sampling seconds are the
machine's: time nothing beside another torch process.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import time
from pathlib import Path

import cv2
import numpy as np
import torch

from orbis2.accel import default_device
from orbis2.config.params import load_config
from orbis2.data.shards import split_clips
from orbis2.eval.metrics.pixels import psnr
from orbis2.eval.metrics.stats import mean_interval, paired_difference
from orbis2.eval.protocols.rollout_fvd import real_videos
from orbis2.eval.protocols.starts import rollout_steps
from orbis2.eval.protocols.systems import (
    SYSTEMS,
    cache_latents,
    eval_samples,
    generate,
    generated_indices,
    inference_settings,
    load_system,
    sample_clusters,
)
from orbis2.latents import open_cache
from orbis2.registry import layout_path
from orbis2.stage import PREDICTOR_FILE, latent_paths

KEYS = ("top_nfe", "bottom_nfe")


def parse_setting(text: str) -> tuple[str, dict[str, int]]:
    name, _, rest = text.partition(":")
    values = {}
    for item in filter(None, rest.split(",")):
        key, _, value = item.partition("=")
        if key not in KEYS or not value.isdigit() or int(value) < 1:
            raise SystemExit(f"--setting {text}: {item!r} is not KEY=STEPS with KEY one of {', '.join(KEYS)} and "
                             f"STEPS >= 1")
        values[key] = int(value)
    return name, values


def detail_energy(frames: np.ndarray) -> np.ndarray:
    """Mean squared Laplacian of each frame's luma at half resolution [..., H, W, 3] uint8 -> [...]: the energy
    of its detail (at full resolution the pixel-level aliasing of the rendered frames dominates it)."""
    flat = frames.reshape(-1, *frames.shape[-3:])
    half = [cv2.resize(cv2.cvtColor(f, cv2.COLOR_RGB2GRAY), None, fx=0.5, fy=0.5, interpolation=cv2.INTER_AREA)
            for f in flat]
    energy = [float(np.mean(cv2.Laplacian(g, cv2.CV_32F) ** 2)) for g in half]
    return np.array(energy).reshape(frames.shape[:-3])


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--profile", default=None, help="params.yaml profile (default: the file's)")
    p.add_argument("--split", default="val")
    p.add_argument("--seconds", type=float, default=1.0, help="rollout length")
    p.add_argument("--horizons", type=float, nargs="+", default=[0.1, 0.5, 1.0])
    p.add_argument("--setting", action="append", default=[], help="NAME:key=value,... (repeatable)")
    p.add_argument("--out", type=Path, default=Path("reports/sampler_sweep.jsonl"))
    a = p.parse_args()
    cfg = load_config("params.yaml", a.profile)
    ev, data, dev = cfg.evaluation, cfg.data, default_device()
    system_name = "hierarchical"
    paths = latent_paths(argparse.Namespace(), SYSTEMS[system_name].latents)
    files = {stage: layout_path("predictor", stage) / PREDICTOR_FILE for stage in SYSTEMS[system_name].stages}
    system = load_system(system_name, files, paths.tokenizers, dev, inference=inference_settings(ev))
    cache = open_cache(paths.root)
    steps = rollout_steps(data, a.seconds)
    samples = eval_samples(cache, a.split, data, steps, ev.starts_per_clip)
    clusters = sample_clusters(cache, a.split, samples)
    indices = [generated_indices(data, s.context_end, steps) for s in samples]
    picks = {h: int(round(h * data.detail_hz)) - 1 for h in a.horizons}
    if max(picks.values()) >= len(indices[0]) or min(picks.values()) < 0:
        raise SystemExit(f"--horizons {a.horizons}: the rollout of {a.seconds:g} s generates {len(indices[0])} "
                         f"frames at {data.detail_hz:g} Hz")
    clips = split_clips(layout_path("shards"), a.split)
    at = [np.array([idx[k] for k in picks.values()]) for idx in indices]
    real = real_videos(clips, samples, at)
    reconstructed = system.decode(cache_latents(cache, a.split, system.output_level, samples, at))
    recon, real_energy = psnr(reconstructed, real), detail_energy(real)
    recon_sharpness = detail_energy(reconstructed) / real_energy
    settings = [("base", {})] + [parse_setting(s) for s in a.setting]
    rows, base = [], None
    for name, values in settings:
        run_ev = dataclasses.replace(ev, **values)
        began = time.perf_counter()
        latents = generate(system, cache, a.split, samples, steps, data, run_ev, dev)
        seconds = time.perf_counter() - began
        generated = system.decode(latents[:, list(picks.values())])
        ours, sharpness = psnr(generated, real), detail_energy(generated) / real_energy
        row = {"setting": name, "top_nfe": run_ev.top_nfe, "bottom_nfe": run_ev.bottom_nfe, "split": a.split,
               "rollouts": len(samples), "clips": len(set(clusters)), "sampling_seconds": seconds, "horizons": {}}
        for j, h in enumerate(a.horizons):
            entry = {"generated_psnr": mean_interval(ours[:, j], clusters, seed=ev.seed).to_dict(),
                     "reconstruction_psnr": mean_interval(recon[:, j], clusters, seed=ev.seed).to_dict(),
                     "gap_db": paired_difference(recon[:, j], ours[:, j], clusters, seed=ev.seed).to_dict(),
                     "sharpness": mean_interval(sharpness[:, j], clusters, seed=ev.seed).to_dict(),
                     "reconstruction_sharpness": mean_interval(recon_sharpness[:, j], clusters,
                                                               seed=ev.seed).to_dict()}
            if base is not None:
                entry["vs_base_db"] = paired_difference(ours[:, j], base[0][:, j], clusters, seed=ev.seed).to_dict()
                entry["vs_base_sharpness"] = paired_difference(sharpness[:, j], base[1][:, j], clusters,
                                                               seed=ev.seed).to_dict()
            row["horizons"][f"{h:g}"] = entry
        base = (ours, sharpness) if base is None else base
        rows.append(row)
        a.out.parent.mkdir(parents=True, exist_ok=True)
        with a.out.open("a") as fh:
            fh.write(json.dumps(row) + "\n")
        print(format_row(row), flush=True)


def format_row(row: dict) -> str:
    def interval(d: dict) -> str:
        return f"{d['estimate']:.3g} [{d['low']:.3g}, {d['high']:.3g}]"

    parts = [f"{row['setting']} (top {row['top_nfe']}, detail {row['bottom_nfe']} NFE; {row['rollouts']} rollouts of "
             f"{row['clips']} clips; {row['sampling_seconds']:.0f} s)"]
    for h, e in row["horizons"].items():
        vs = (f"; vs base {interval(e['vs_base_db'])} dB, sharpness {interval(e['vs_base_sharpness'])}"
              if "vs_base_db" in e else "")
        parts.append(f"  {h} s: generated {interval(e['generated_psnr'])} dB, tokenizer "
                     f"{interval(e['reconstruction_psnr'])}, gap {interval(e['gap_db'])}; sharpness generated "
                     f"{interval(e['sharpness'])}, tokenizer {interval(e['reconstruction_sharpness'])}{vs}")
    return "\n".join(parts)


if __name__ == "__main__":
    with torch.inference_mode():
        main()
