"""The parts of the GPU measurement (``tools/gpu_run.sh``) that are not a benchmark of their own.

    python benchmarks/gpu_suite.py PART --out DIR [--rehearse]

PART is one of:

* ``carried``: the size of what travels to the GPU machine (the repository's files and ./wheelhouse),
  against the limit the machine accepts.
* ``peak``: device, driver, memory, the table's dense bf16 peak and a measured bf16 matmul.
* ``forwards``: per forward (detail, abstract, cached abstract, flat) at the preset, batch 1, weights
  cast once (``cast_for_inference``): time per call (CUDA events on the GPU), and the kernels from
  ``torch.profiler``: how many per call and the top ones by device time.
* ``toggles``: each inference switch against its reference on the same inputs: compile
  (``orbis2.accel.compile_predictor``, the ``evaluation.compile`` switch), the KV cache, bf16
  autocast and TF32, each with its largest difference and whether the outputs are equal.
* ``graphs``: a CUDA-graph capture of the detail forward, replayed on new inputs, equal to eager
  (on the CPU: the forward's host syncs, which would stop a capture, counted instead).
* ``dag``: the ``gpu`` profile's DAG with its training and evaluation sizes scaled down
  (:func:`scaled_params`), run by Snakemake in a copy of the project; skipped without the assets.
* ``summary``: every part's JSON and exit status in one summary file.

Every part writes ``DIR/PART.json`` after each measurement, so a part cut short by its time
limit still leaves what it measured. ``--rehearse`` runs on the CPU at the ``smoke`` preset, compiled
without CUDA graphs, and the DAG part as a Snakemake dry run: the same code paths, for the tests.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import shutil
import statistics
import subprocess
import sys
import time
from pathlib import Path
from typing import Any, Callable

import torch
import yaml

sys.path.insert(0, str(Path(__file__).resolve().parent))
from bench_rollout import LATENT_CHANNELS, flat_baseline, hierarchy  # noqa: E402
from bench_train import measured_matmul_tflops, peak_bf16_tflops  # noqa: E402

from orbis2.accel import HostSyncs, cast_for_inference, compile_predictor, inference_autocast, set_tf32  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]
GRIDS = {"smoke": (9, 16), "default": (10, 16), "paper": (18, 32)}


class Record:
    """A JSON file rewritten after every entry."""

    def __init__(self, path: Path, **head: Any):
        self.path, self.data = path, dict(head)
        self.write()

    def __setitem__(self, key: str, value: Any) -> None:
        self.data[key] = value
        self.write()

    def write(self) -> None:
        self.path.parent.mkdir(parents=True, exist_ok=True)
        self.path.write_text(json.dumps(self.data, indent=2, default=str))


def _sync(device: torch.device) -> None:
    if device.type == "cuda":
        torch.cuda.synchronize(device)


def time_call(fn: Callable[[], Any], device: torch.device, repeats: int) -> dict[str, float]:
    """Milliseconds per call after one warm-up: CUDA events on the GPU, the wall clock on the CPU."""
    fn()
    _sync(device)
    times = []
    for _ in range(repeats):
        if device.type == "cuda":
            start, end = torch.cuda.Event(enable_timing=True), torch.cuda.Event(enable_timing=True)
            start.record()
            fn()
            end.record()
            end.synchronize()
            times.append(start.elapsed_time(end))
        else:
            t = time.perf_counter()
            fn()
            times.append(1e3 * (time.perf_counter() - t))
    return {"median_ms": statistics.median(times), "min_ms": min(times), "repeats": repeats}


def kernels(fn: Callable[[], Any], device: torch.device, top: int = 8) -> dict[str, Any]:
    """Kernels of one call from the profiler: count and the ``top`` by device time (CPU ops on the CPU)."""
    activities = [torch.profiler.ProfilerActivity.CPU]
    if device.type == "cuda":
        activities.append(torch.profiler.ProfilerActivity.CUDA)
    with torch.profiler.profile(activities=activities) as prof:
        fn()
        _sync(device)
    events = prof.events()
    if device.type == "cuda":
        launched = [e for e in events if e.device_type == torch.autograd.DeviceType.CUDA]
        key = "self_device_time_total"
    else:
        launched = [e for e in events if e.cpu_parent is None]
        key = "self_cpu_time_total"
    totals: dict[str, float] = {}
    for e in launched:
        totals[e.name] = totals.get(e.name, 0.0) + getattr(e, key, 0.0)
    ranked = sorted(totals.items(), key=lambda kv: -kv[1])[:top]
    return {"count": len(launched), "unit": "cuda kernels" if device.type == "cuda" else "top-level cpu ops",
            "top": [{"name": name[:120], "us": round(us, 1)} for name, us in ranked]}


class Nets:
    """The preset's predictors (random weights, output layer perturbed) and their batch-1 inputs."""

    def __init__(self, preset: str, device: torch.device, cast: bool = True):
        h, w = GRIDS[preset]
        with torch.device(device):
            self.abstract, self.detail = (m.eval().requires_grad_(False) for m in hierarchy(preset))
            self.flat = flat_baseline(preset).eval().requires_grad_(False)
        for net in (self.abstract, self.detail, self.flat):
            torch.nn.init.normal_(net.final_layer.linear.weight, std=0.02)
            if cast:  # as every rollout does: no weight cast per call (only fp32 references keep fp32 weights)
                cast_for_inference(net, device, "bf16")
        g = torch.Generator(device).manual_seed(0)
        self.x10 = torch.randn(1, 10, LATENT_CHANNELS, h, w, device=device, generator=g)
        self.tau10 = torch.rand(1, 10, device=device, generator=g)
        # The conditioned slots as a tuple, as rollouts give them: a mask tensor is read on the host (no capture).
        self.detail_cond = {"frame_rate": 10.0, "cond_mask": (4, 9),
                            "cond_frames": torch.randn(1, 10, LATENT_CHANNELS, h, w, device=device, generator=g)}
        self.x6, self.tau6 = self.x10[:, :6], torch.cat([torch.zeros(1, 5, device=device), self.tau10[:, :1]], 1)
        self.steering = torch.randn(1, 5, 2, device=device, generator=g)

    def forwards(self) -> dict[str, Callable[[], torch.Tensor]]:
        abstract_cond = {"frame_rate": 2.0, "steering": self.steering}
        return {
            "detail": lambda: self.detail(self.x10, self.tau10, **self.detail_cond),
            "abstract": lambda: self.abstract(self.x6, self.tau6, **abstract_cond),
            "cached": self.cached,
            "flat": lambda: self.flat(self.x10, self.tau10, frame_rate=10.0),
        }

    def cached(self) -> torch.Tensor:
        """One Euler step of the abstract predictor after its clean context: cache once, then the target frame."""
        if not hasattr(self, "_cache"):
            self._cache = self.abstract.build_kv_cache(self.x6[:, :5], 1, 2.0, self.steering)
        return self.abstract.forward_cached(self.x6[:, 5:], self.tau6[:, 5:], self._cache, 2.0, self.steering)


def part_peak(args: argparse.Namespace, out: Record) -> None:
    device = args.device
    name = torch.cuda.get_device_name(device) if device.type == "cuda" else "cpu"
    out["device"] = name
    out["torch"] = torch.__version__
    out["cuda"] = torch.version.cuda
    out["python"] = platform.python_version()
    if device.type == "cuda":
        smi = subprocess.run(["nvidia-smi", "--query-gpu=driver_version", "--format=csv,noheader"],
                             capture_output=True, text=True)
        out["driver"] = smi.stdout.strip() if smi.returncode == 0 else None
    if device.type == "cuda":
        out["memory_gb"] = torch.cuda.get_device_properties(device).total_memory / 2**30
    out["peak_bf16_tflops_table"] = peak_bf16_tflops(name) if device.type == "cuda" else None
    out["matmul_tflops_measured"] = measured_matmul_tflops(device)
    out["matmul_dtype"] = "bf16" if device.type == "cuda" else "fp32"


def part_forwards(args: argparse.Namespace, out: Record) -> None:
    nets = Nets(args.preset, args.device)
    with torch.no_grad(), inference_autocast(args.device, "bf16"):
        for name, fn in nets.forwards().items():
            out[name] = {**time_call(fn, args.device, args.repeats), "kernels": kernels(fn, args.device)}


def _compare(on: torch.Tensor, off: torch.Tensor) -> dict[str, Any]:
    return {"equal": bool(torch.equal(on, off)), "max_abs_diff": float((on.float() - off.float()).abs().max()),
            "reference_abs_max": float(off.float().abs().max())}


def part_toggles(args: argparse.Namespace, out: Record) -> None:
    """Each switch on against off on the same inputs (on the CPU, bf16 and TF32 are no-ops: equal by design)."""
    device, nets = args.device, Nets(args.preset, args.device, cast=False)
    fns = nets.forwards()
    with torch.no_grad():
        with inference_autocast(device, "bf16"):
            bf16 = fns["detail"]()
        fp32 = fns["detail"]()
        out["bf16"] = _compare(bf16, fp32)
        set_tf32(True)
        tf32 = fns["detail"]()
        set_tf32(False)
        out["tf32"] = _compare(tf32, fns["detail"]())
        set_tf32(True)
        full = nets.abstract(nets.x6, nets.tau6, frame_rate=2.0, steering=nets.steering)[:, 5:]
        out["kv_cache"] = _compare(fns["cached"](), full)
        if args.compile:
            with inference_autocast(device, "bf16"):
                eager = fns["detail"]()
                compile_predictor(nets.detail)
                start = time.perf_counter()
                compiled = fns["detail"]()
                _sync(device)
                out["compile"] = {**_compare(compiled, eager), "compile_s": time.perf_counter() - start,
                                  **time_call(fns["detail"], device, args.repeats)}
        else:
            out["compile"] = {"skipped": "--no-compile"}


def part_graphs(args: argparse.Namespace, out: Record) -> None:
    """Capture the detail forward in a CUDA graph, replay it on new inputs, compare with eager."""
    device = args.device
    nets = Nets(args.preset, device)
    forward = nets.forwards()["detail"]
    if device.type != "cuda":  # the rehearsal: what would stop a capture is a host sync inside the forward
        with torch.no_grad(), HostSyncs() as syncs:
            forward()
        out["host_syncs"] = syncs.seen
        out["captured"] = None
        if syncs.seen:
            raise SystemExit(f"the detail forward reads tensors on the host ({syncs.seen}): it cannot be captured")
        return
    with torch.no_grad(), inference_autocast(device, "bf16"):
        stream = torch.cuda.Stream()
        stream.wait_stream(torch.cuda.current_stream())
        with torch.cuda.stream(stream):
            for _ in range(2):
                forward()
        torch.cuda.current_stream().wait_stream(stream)
        graph = torch.cuda.CUDAGraph()
        try:
            with torch.cuda.graph(graph):
                static = forward()
        except RuntimeError as err:  # a host sync or a host-built tensor inside the forward
            out["captured"], out["error"] = False, str(err).splitlines()[0][:300]
            return
        out["captured"] = True
        nets.x10.copy_(torch.randn_like(nets.x10))
        graph.replay()
        torch.cuda.synchronize()
        out["replay_vs_eager"] = _compare(static.clone(), forward())
        out["replay"] = time_call(graph.replay, device, args.repeats)
        out["eager"] = time_call(forward, device, args.repeats)


def scaled_params(params: dict[str, Any], profile: str, steps: int) -> dict[str, Any]:
    """``params`` with every training stage of ``profile`` cut to at most ``steps`` steps (logging, evaluation and
    checkpoints within them) and the world and evaluation sizes taken from ``smoke``: each stage still runs, briefly.
    """
    params = json.loads(json.dumps(params))
    params["profile"] = profile
    for name, section in params.items():
        if not isinstance(section, dict) or profile not in section:
            continue
        own = section[profile] = dict(section[profile] or {})
        train = {**section.get("all", {}).get("train", {}), **own.get("train", {})}
        if name.startswith("_") or "train" in own or "train" in section.get("all", {}):
            own["train"] = {**own.get("train", {}), "steps": steps, "warmup_steps": 1, "log_every": 1,
                            "eval_every": steps, "checkpoint_every": steps}
            if "batch_size" in train:
                own["train"]["batch_size"] = min(int(train["batch_size"]), 8)
        smoke = section.get("smoke") or {}
        for key, value in smoke.items():  # world and evaluation sizes: the smoke profile's (not its resolution)
            if name != "data" and key not in ("train", "model", "preset"):
                own[key] = value
    return params


# What the DAG part imports beyond the benchmarks (torch, numpy, yaml, opencv, pillow): ./wheelhouse carries it.
DAG_MODULES = ("snakemake", "mlflow", "webdataset", "pydantic", "sqlalchemy", "matplotlib", "pyarrow", "pandas")
# Top-level folders a project copy leaves out: outputs, the wheels, the published docs.
PROJECT_SKIP = {".git", "wheelhouse", "data", "reports", "docs", "mlruns", ".snakemake", ".dvc"}


def _dag_environment(deps: Path) -> tuple[dict[str, str], list[str]]:
    """The environment of the DAG's subprocess: ./wheelhouse's distributions this Python lacks installed into
    ``deps`` (never shadowing the machine's torch or numpy), and the modules still missing after that."""
    import importlib.metadata as md
    import importlib.util

    missing_wheels = []
    for wheel in sorted((ROOT / "wheelhouse").glob("*.whl")):
        try:
            md.version(wheel.name.split("-")[0])
        except md.PackageNotFoundError:
            missing_wheels.append(str(wheel))
    if missing_wheels:
        subprocess.run([sys.executable, "-m", "pip", "install", "--quiet", "--no-index", "--no-deps", "--no-compile",
                        "--target", str(deps), *missing_wheels], check=True)
    env = {**os.environ, "PYTHONPATH": os.pathsep.join([str(ROOT / "src"), str(deps), os.environ.get("PYTHONPATH",
                                                                                                      "")])}
    sys.path[:0] = [str(deps)]
    missing = [name for name in DAG_MODULES if importlib.util.find_spec(name) is None]
    return env, missing


def part_dag(args: argparse.Namespace, out: Record) -> None:
    """The ``gpu`` profile's DAG, scaled down, in a copy of the project; ``--rehearse``: Snakemake's dry run of it.

    The DAG's first stages need the I3D and Inception assets, which the ``assets`` stage downloads: on a machine
    without a network they come from ``--assets`` (a folder holding ``data/assets``), or the part is skipped."""
    assets = Path(args.assets) / "data" / "assets" if args.assets else None
    if not args.rehearse and (assets is None or not assets.is_dir()):
        out["skipped"] = "no assets: pass ASSETS=<folder holding data/assets> (the machine has no network)"
        return
    env, missing = _dag_environment(Path(os.environ.get("DEPS", "/tmp/pydeps")))
    if missing:
        out["skipped"] = f"modules missing: {missing}; build ./wheelhouse with tools/build_wheelhouse.sh"
        return
    work = args.out / "dag_project"
    if work.exists():
        shutil.rmtree(work)
    shutil.copytree(ROOT, work, ignore=lambda folder, names: [n for n in names if n == "__pycache__" or (
        Path(folder) == ROOT and n in PROJECT_SKIP)])
    if assets is not None and assets.is_dir():
        shutil.copytree(assets, work / "data" / "assets")
    params = yaml.safe_load((ROOT / "params.yaml").read_text())
    (work / "params.yaml").write_text(yaml.safe_dump(scaled_params(params, "gpu", args.dag_steps), sort_keys=False))
    command = [sys.executable, "-m", "snakemake", "--cores", str(args.cores), "--config", "profile=gpu"]
    if args.rehearse:
        command.append("-n")
    out["command"] = " ".join(command)
    start = time.perf_counter()
    done = subprocess.run(command, cwd=work, capture_output=True, text=True, env=env)
    out["seconds"] = time.perf_counter() - start
    out["exit"] = done.returncode
    log = done.stdout + done.stderr
    out["jobs_done"] = log.count("Finished job") if not args.rehearse else None
    out["log_tail"] = log[-4000:]
    shutil.rmtree(work, ignore_errors=True)  # the archive carries the record, not the project
    if done.returncode:
        raise SystemExit(f"snakemake exited with {done.returncode}; see {out.path}")


def carried_files(root: Path) -> tuple[int, int]:
    """Bytes of what travels to the GPU machine: the repository's files (without .git and the outputs that
    git ignores, as a copy of the working tree has them) and ./wheelhouse."""
    listed = subprocess.run(["git", "ls-files", "-co", "--exclude-standard", "-z"], cwd=root, capture_output=True)
    if listed.returncode == 0:
        names = [n for n in listed.stdout.decode().split("\0") if n]
        repository = sum((root / n).stat().st_size for n in names if (root / n).is_file())
    else:  # a copy without .git (on the GPU machine): every file but the ignored outputs
        repository = sum(f.stat().st_size for f in root.rglob("*") if f.is_file()
                         and f.relative_to(root).parts[0] not in PROJECT_SKIP - {"docs"})
    wheels = sum(f.stat().st_size for f in (root / "wheelhouse").glob("*.whl"))
    return repository, wheels


def part_carried(args: argparse.Namespace, out: Record) -> None:
    repository, wheels = carried_files(args.root)
    mib = 2**20
    out["repository_mib"], out["wheelhouse_mib"] = repository / mib, wheels / mib
    out["carried_mib"], out["limit_mib"] = (repository + wheels) / mib, args.limit_mib
    print(f"carried: {out['carried_mib']:.1f} MiB (repository {repository / mib:.1f}, wheelhouse {wheels / mib:.1f}); "
          f"limit {args.limit_mib} MiB")
    if (repository + wheels) / mib > args.limit_mib:
        raise SystemExit(f"the carried files ({out['carried_mib']:.1f} MiB) exceed {args.limit_mib} MiB: "
                         f"build ./wheelhouse with tools/build_wheelhouse.sh (it skips what the machine has)")


# The figures the summary lifts out of each part's JSON (the whole JSON stays in the archive).
HEADLINES = {
    "peak": ("device", "driver", "torch", "cuda", "memory_gb", "peak_bf16_tflops_table", "matmul_tflops_measured"),
    "carried": ("carried_mib", "repository_mib", "wheelhouse_mib", "limit_mib"),
}


def _rollout_figures(record: dict) -> dict:
    keys = ("fps", "seconds", "min_seconds", "frames", "rollout_s", "decode_s", "warmup_s", "compile_s", "nfe",
            "peak_memory_mb", "memory_kind", "error")
    return {system: {k: v for k, v in run.items() if k in keys} | {"repeats": record.get("repeats")}
            for system, run in record.get("systems", {}).items() if isinstance(run, dict)}


def part_summary(args: argparse.Namespace, out: Record) -> None:
    """One summary of the run: machine, commit, each part's exit status, and its headline figures."""
    steps = [json.loads(line) for line in (args.out / "steps.jsonl").read_text().splitlines()] if (
        args.out / "steps.jsonl").is_file() else []
    summary: dict[str, Any] = {"commit": os.environ.get("GIT_COMMIT") or _git_commit(), "parts": {}}
    for name in ["carried"] + [row["step"] for row in steps]:
        path = args.out / f"{name}.json"
        record = json.loads(path.read_text()) if path.is_file() else {}
        entry = next(({k: row[k] for k in ("exit", "seconds", "limit", "skipped") if k in row}
                      for row in steps if row["step"] == name), {})
        if name.startswith("rollouts"):
            entry["systems"] = _rollout_figures(record)
        elif name == "forwards":
            entry["forwards"] = {k: {f: v[f] for f in ("median_ms", "min_ms", "repeats") if f in v}
                                 | {"kernels": v.get("kernels", {}).get("count")}
                                 for k, v in record.items() if isinstance(v, dict) and "median_ms" in v}
        elif name == "train":
            entry["runs"] = record.get("runs", [])
        elif name in ("toggles", "graphs", "dag"):
            entry.update({k: v for k, v in record.items() if k not in ("log_tail",)})
        else:
            entry.update({k: record[k] for k in HEADLINES.get(name, ()) if k in record})
        summary["parts"][name] = entry
    args.summary.write_text(json.dumps(summary, indent=2, default=str))
    out["written"] = str(args.summary)


def _git_commit() -> str | None:
    done = subprocess.run(["git", "rev-parse", "HEAD"], cwd=ROOT, capture_output=True, text=True)
    return done.stdout.strip() if done.returncode == 0 else None


PARTS = {"carried": part_carried, "peak": part_peak, "forwards": part_forwards, "toggles": part_toggles,
         "graphs": part_graphs, "dag": part_dag, "summary": part_summary}


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("part", choices=sorted(PARTS))
    parser.add_argument("--out", type=Path, required=True, help="folder of the JSON files")
    parser.add_argument("--rehearse", action="store_true",
                        help="CPU, smoke preset, inductor without CUDA graphs, Snakemake dry run: for the tests")
    parser.add_argument("--preset", default=None, help="model preset (default: paper, smoke with --rehearse)")
    parser.add_argument("--repeats", type=int, default=None, help="timed calls per forward (default 10, 1 rehearsed)")
    parser.add_argument("--no-compile", dest="compile", action="store_false", help="skip the compile toggle")
    parser.add_argument("--dag-steps", type=int, default=3, help="training steps per stage in the scaled DAG")
    parser.add_argument("--assets", default="", help="dag: a folder holding data/assets (I3D, Inception)")
    parser.add_argument("--cores", type=int, default=8)
    parser.add_argument("--root", type=Path, default=ROOT, help="carried: the repository copy to measure")
    parser.add_argument("--limit-mib", type=float, default=60.0, help="carried: the most the machine accepts")
    parser.add_argument("--summary", type=Path, default=None, help="summary: the file to write")
    args = parser.parse_args(argv)
    args.device = torch.device("cpu" if args.rehearse or not torch.cuda.is_available() else "cuda")
    args.preset = args.preset or ("smoke" if args.rehearse else "paper")
    args.repeats = args.repeats or (1 if args.rehearse else 10)
    if args.part == "summary":
        args.summary = args.summary or args.out / "summary.json"
        part_summary(args, Record(args.out / "summary_part.json", part="summary"))
        return
    torch.manual_seed(0)
    set_tf32(True)
    out = Record(args.out / f"{args.part}.json", part=args.part, preset=args.preset, device_type=args.device.type)
    start = time.perf_counter()
    PARTS[args.part](args, out)
    out["part_s"] = time.perf_counter() - start


if __name__ == "__main__":
    main()
