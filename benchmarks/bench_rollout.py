"""Generation speed side by side (paper Table 5): hierarchical, distilled, flat detail and an Orbis v1-style model.

    python benchmarks/bench_rollout.py [--preset paper] [--grid 18x32] [--seconds 2] [--precision bf16]
        [--compile] [--compile-cache DIR] [--no-kv-cache] [--distill-nfe 4] [--json out.json]

Random weights at an ST-DiT preset's size, 16-channel latents on the latent grid,
batch 1, every frame decoded by the detail tokenizer's decoder of the same preset
(decoding is part of generation as a user sees it):

* ``hierarchical``: steered causal abstract predictor (15 NFE, KV-cached context)
  + abstract-conditioned detail predictor (30 NFE), 5 frames per 0.5-s step;
* ``distilled``: the same with the few-step detail predictor (``--distill-nfe``);
* ``flat_detail``: one detail-level predictor widened to the hierarchy's total
  parameter count, 5 frames per step, 30 NFE;
* ``v1_style``: the same network run like Orbis v1: one frame per step at 10 Hz,
  30 NFE.

Every system runs the same way (sampling plans, weights cast to bf16 once on
CUDA, and with ``--compile`` regional compilation with CUDA graphs on CUDA), so
the ratios compare the networks and their NFE, not the implementations. Each
system runs in its own subprocess so its peak memory is its own (CUDA:
``max_memory_allocated``, weights included; CPU: peak RSS). The first rollout
is a warm-up whose time is reported apart (it holds the compilation with
``--compile``; ``compile_s`` is its excess over a timed rollout, and
``--compile-cache`` keeps the compiled artifacts between runs). Frames/s
include decoding; the rollout's and the decoder's times are also reported
apart (medians). Speed depends on the network sizes and NFE only, so random
weights measure what trained ones would.
"""

from __future__ import annotations

import argparse
import json
import resource
import subprocess
import sys
import time
from pathlib import Path

import torch

from orbis2.accel import (
    cast_for_inference,
    compile_cache,
    compile_decoder,
    compile_predictor,
    inference_autocast,
    set_tf32,
)
from orbis2.config.params import load_config
from orbis2.models.sizes import STDIT_PRESETS, TOKENIZER_PRESETS, stdit_config
from orbis2.models.stdit import build_stdit
from orbis2.models.tokenizer import build_detail_tokenizer
from orbis2.rollout import ABSTRACT_NFE, DETAIL_NFE, cascaded_rollout, detail_frames_per_step, flat_rollout

LATENT_CHANNELS = 16
DATA = load_config(Path(__file__).resolve().parents[1] / "params.yaml").data  # the rates: one for every profile
CONTEXT, PER_STEP = 5, detail_frames_per_step(DATA.detail_hz, DATA.abstract_hz)
SYSTEMS = ("hierarchical", "distilled", "flat_detail", "v1_style")


def n_params(model: torch.nn.Module) -> int:
    return sum(p.numel() for p in model.parameters())


def hierarchy(preset: str) -> tuple[torch.nn.Module, torch.nn.Module]:
    """The steered causal abstract predictor and the abstract-conditioned detail predictor."""
    abstract = build_stdit(preset, LATENT_CHANNELS, causal=True, steering=True)
    detail = build_stdit(preset, LATENT_CHANNELS, causal=False, abstract_channels=LATENT_CHANNELS)
    return abstract, detail


def flat_baseline(preset: str) -> torch.nn.Module:
    """A detail-level predictor widened until its parameter count is closest to the whole hierarchy's
    (widths in steps of 8 per head, so flash attention applies: 1,152M against 1,069M at the paper preset)."""
    with torch.device("meta"):  # sizes only, nothing allocated
        target = sum(n_params(m) for m in hierarchy(preset))
        step = 8 * STDIT_PRESETS[preset].num_heads  # head size a multiple of 8: flash attention applies
        widths = range(step, 8 * STDIT_PRESETS[preset].hidden_size, step)
        size = lambda w: n_params(build_stdit(stdit_config(preset, hidden_size=w), LATENT_CHANNELS, False))  # noqa: E731
        lo, hi = 0, len(widths) - 1  # the count grows with the width: bisect to the first one >= target
        while lo < hi:
            mid = (lo + hi) // 2
            lo, hi = (mid + 1, hi) if size(widths[mid]) < target else (lo, mid)
        width = min(widths[max(lo - 1, 0)], widths[lo], key=lambda w: abs(size(w) - target))
    return build_stdit(stdit_config(preset, hidden_size=width), LATENT_CHANNELS, causal=False)


def decoder(preset: str) -> torch.nn.Module:
    """The detail tokenizer of the preset (its decoder is what runs); ``smoke`` for presets it lacks."""
    return build_detail_tokenizer(preset if preset in TOKENIZER_PRESETS else "smoke")


def _perturb_outputs(*models: torch.nn.Module) -> None:
    """DiT init zeroes the output layer; give it weights so sampling does real arithmetic end to end."""
    for model in models:
        torch.nn.init.normal_(model.final_layer.linear.weight, std=0.02)


def _sync(device: torch.device) -> None:
    if device.type == "cuda":
        torch.cuda.synchronize(device)


def rollout_worker(args: argparse.Namespace) -> dict:
    """One system's rollouts in this process: warm-up time, frames/s (decoding included), peak memory."""
    device = torch.device(args.device)
    h, w = args.grid
    gen = torch.Generator(device=device).manual_seed(0)
    steps = max(1, round(args.seconds * DATA.abstract_hz))
    d_ctx = torch.randn(1, CONTEXT, LATENT_CHANNELS, h, w, device=device)
    with torch.device(device):  # initialise on the device: fast even at the paper's sizes
        tokenizer = decoder(args.preset).eval()
        cascaded = args.worker in ("hierarchical", "distilled")
        models = hierarchy(args.preset) if cascaded else [flat_baseline(args.preset)]
    nets: list[torch.nn.Module] = []
    if args.worker in ("hierarchical", "distilled"):
        abstract, detail = (m.eval() for m in models)
        nets = [abstract, detail]
        a_ctx = torch.randn(1, CONTEXT, LATENT_CHANNELS, h, w, device=device)
        steering = torch.randn(1, steps, PER_STEP, 2, device=device)
        detail_nfe = args.distill_nfe if args.worker == "distilled" else DETAIL_NFE

        def generate() -> torch.Tensor:
            return cascaded_rollout(abstract, detail, d_ctx, a_ctx, steps, gen, abstract_nfe=ABSTRACT_NFE,
                                    detail_nfe=detail_nfe, abstract_hz=DATA.abstract_hz, detail_hz=DATA.detail_hz,
                                    steering=steering, kv_cache=args.kv_cache)[0]
    else:
        flat = models[0].eval()
        nets = [flat]
        per_step = PER_STEP if args.worker == "flat_detail" else 1

        def generate() -> torch.Tensor:
            return flat_rollout(flat, d_ctx, steps * PER_STEP // per_step, per_step, 30, DATA.detail_hz, gen)
    _perturb_outputs(*nets)
    for net in nets:
        net.requires_grad_(False)
        cast_for_inference(net, device, args.precision)
    tokenizer.requires_grad_(False)
    if args.compile:
        for net in nets:
            compile_predictor(net, backend=args.backend)
        compile_decoder(tokenizer, backend=args.backend)

    @torch.no_grad()
    def run() -> tuple[int, float, float]:
        with inference_autocast(device, args.precision):
            start = time.perf_counter()
            latents = generate()
            _sync(device)
            rollout_s = time.perf_counter() - start
            frames = [tokenizer.decode(chunk).float() for chunk in latents[0].split(8)]
            _sync(device)
        return sum(f.shape[0] for f in frames), rollout_s, time.perf_counter() - start - rollout_s

    cache_dir = args.compile_cache if args.compile else None
    with compile_cache(cache_dir / f"{args.worker}-{args.preset}.bin" if cache_dir else None) as cache_record:
        _sync(device)
        if device.type == "cuda":
            torch.cuda.reset_peak_memory_stats(device)
        start = time.perf_counter()
        run()  # warm-up: kernel selection, allocator, compilation
        _sync(device)
        warmup_s = time.perf_counter() - start
    timings, rollouts, decodes = [], [], []
    for _ in range(args.repeats):
        start = time.perf_counter()
        frames, rollout_s, decode_s = run()
        _sync(device)
        timings.append(time.perf_counter() - start)
        rollouts.append(rollout_s)
        decodes.append(decode_s)
    median = lambda values: sorted(values)[len(values) // 2]  # noqa: E731
    seconds = median(timings)
    if device.type == "cuda":
        peak_mb = torch.cuda.max_memory_allocated(device) / 2**20
    else:
        peak_mb = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024  # KiB on Linux
    return {"system": args.worker, "params": sum(n_params(n) for n in nets), "decoder_params": n_params(tokenizer),
            "frames": frames, "fps": frames / seconds, "seconds": seconds, "min_seconds": min(timings),
            "rollout_s": median(rollouts), "decode_s": median(decodes), "warmup_s": warmup_s,
            "compile_s": max(warmup_s - seconds, 0.0) if args.compile else 0.0,
            "compile_cache_loaded": cache_record["loaded"],
            "peak_memory_mb": peak_mb, "memory_kind": "cuda_max_allocated" if device.type == "cuda" else "cpu_peak_rss",
            "nfe": {"hierarchical": [15, 30], "distilled": [15, args.distill_nfe]}.get(args.worker, [30])}


def parse_args(argv: list[str] | None = None) -> argparse.Namespace:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--preset", default="default")
    parser.add_argument("--grid", type=lambda s: tuple(int(v) for v in s.split("x")), default=None,
                        help="latent grid HxW (default: 18x32 for paper, else 9x16)")
    parser.add_argument("--seconds", type=float, default=1.0, help="seconds of 10 Hz video per timed rollout")
    parser.add_argument("--repeats", type=int, default=2, help="timed rollouts per system (median)")
    parser.add_argument("--precision", choices=("bf16", "fp32"), default="bf16", help="bf16 autocast on CUDA only")
    parser.add_argument("--compile", action="store_true",
                        help="torch.compile predictors (by region; CUDA graphs on CUDA) and decoder")
    parser.add_argument("--backend", default="inductor",
                        help="with --compile: torch.compile's backend for the predictors and the decoder; eager traces "
                             "the same graphs through dynamo and runs them as they are (tools/gpu_run.sh's CPU "
                             "rehearsal: inductor's CPU code is not what runs on a GPU, and "
                             "tests/test_compiled_path.py runs the predictors' inductor code)")
    parser.add_argument("--compile-cache", type=Path, default=None,
                        help="with --compile: directory keeping the compiled artifacts between runs")
    parser.add_argument("--no-kv-cache", dest="kv_cache", action="store_false")
    parser.add_argument("--distill-nfe", type=int, default=4, help="Euler steps of the distilled detail predictor")
    parser.add_argument("--systems", default=",".join(SYSTEMS), help=f"comma-separated subset of {SYSTEMS}")
    parser.add_argument("--threads", type=int, default=1, help="torch CPU threads")
    parser.add_argument("--device", default="cuda" if torch.cuda.is_available() else "cpu")
    parser.add_argument("--timeout", type=float, default=600, help="seconds per system before it is skipped")
    parser.add_argument("--json", type=Path, default=None, help="also write the results here")
    parser.add_argument("--worker", choices=SYSTEMS, help=argparse.SUPPRESS)
    args = parser.parse_args(argv)
    if args.grid is None:
        args.grid = (18, 32) if args.preset == "paper" else (9, 16)
    return args


def main(argv: list[str] | None = None) -> None:
    args = parse_args(argv)
    torch.set_num_threads(args.threads)
    set_tf32(True)
    torch.manual_seed(0)
    if args.worker:
        print(json.dumps(rollout_worker(args)))
        return
    forwarded = [a for a in (argv if argv is not None else sys.argv[1:])]
    device_name = torch.cuda.get_device_name() if args.device.startswith("cuda") else f"cpu ({args.threads} threads)"
    results: dict[str, dict] = {}

    def ratios() -> dict[str, float]:
        ok = {k: v for k, v in results.items() if "error" not in v}
        if "v1_style" not in ok:
            return {}
        return {f"{k}_over_v1_style": ok[k]["fps"] / ok["v1_style"]["fps"] for k in ok if k != "v1_style"}

    def write() -> None:  # after every system, so a run cut short still leaves what it measured
        if args.json is None:
            return
        record = {"device": device_name, "preset": args.preset, "grid": list(args.grid), "precision": args.precision,
                  "compile": args.compile and args.backend, "kv_cache": args.kv_cache,
                  "seconds": args.seconds, "batch": 1, "repeats": args.repeats,
                  "decoding_included": True, "systems": results, "ratios": ratios()}
        args.json.parent.mkdir(parents=True, exist_ok=True)
        args.json.write_text(json.dumps(record, indent=2))

    for name in args.systems.split(","):
        if name not in SYSTEMS:
            raise SystemExit(f"unknown system {name!r}; choose from {SYSTEMS}")
        cmd = [sys.executable, __file__, *forwarded, "--worker", name]
        try:
            out = subprocess.run(cmd, check=True, capture_output=True, text=True, timeout=args.timeout).stdout
            results[name] = json.loads(out.strip().splitlines()[-1])
        except subprocess.TimeoutExpired:
            results[name] = {"system": name, "error": f"over {args.timeout:.0f} s"}
        except subprocess.CalledProcessError as err:
            results[name] = {"system": name, "error": err.stderr.strip().splitlines()[-1] if err.stderr else "failed"}
        write()
    print(f"device {device_name}, preset {args.preset}, grid {args.grid[0]}x{args.grid[1]}x{LATENT_CHANNELS}, "
          f"{args.precision}{', compiled' if args.compile else ''}, KV cache {'on' if args.kv_cache else 'off'}, "
          f"{args.seconds:g} s of video per rollout, decoding included")
    print(f"{'system':<14}{'params':>14}{'frames/s':>10}{'rollout s':>10}{'decode s':>10}{'peak MB':>10}"
          f"{'warm-up s':>11}")
    for name, r in results.items():
        if "error" in r:
            print(f"{name:<14}  skipped: {r['error']}")
            continue
        print(f"{name:<14}{r['params']:>14,}{r['fps']:>10.2f}{r['rollout_s']:>10.2f}{r['decode_s']:>10.2f}"
              f"{r['peak_memory_mb']:>10.0f}{r['warmup_s']:>11.1f}")
    for key, value in ratios().items():
        print(f"speed ratio {key}: {value:.2f}x")


if __name__ == "__main__":
    main()
