"""What the data benchmarks (bench_shards, bench_latent_parts, bench_latent_cache) share: a corpus grown by linking
its files under new names, so that a job's work grows with the corpus while the disk does not; random-weight
tokenizers (an encoder's work does not depend on its weights); the CPU a figure was measured on."""

from __future__ import annotations

import dataclasses
import os
from pathlib import Path


def grown(base: Path, root: Path, scale: int) -> Path:
    """``base``'s raw episodes ``scale`` times under ``root``, under new names, their files hard-linked (the
    per-frame labels too, where an episode has them)."""
    from orbis2.data.episodes import RawIndex

    index = RawIndex.read(base)
    records = []
    for copy in range(scale):
        for ep in index.episodes:
            new = dataclasses.replace(ep, stem=f"{ep.stem}_c{copy}")
            (root / ep.split).mkdir(parents=True, exist_ok=True)
            for old_path, new_path in ((ep.video(base), new.video(root)), (ep.odometry(base), new.odometry(root)),
                                       (ep.labels(base), new.labels(root))):
                if old_path.is_file():
                    os.link(old_path, new_path)
            records.append(new)
    dataclasses.replace(index, episodes=records).write(root)
    return root


def random_tokenizers(root: Path, cfg) -> tuple[Path, Path]:
    """Random-weight tokenizer files of the profile's presets (and its abstract tokenizer's bottleneck) in
    ``root``: ``(detail.pt, abstract.pt)``."""
    import torch

    from orbis2.models.files import save_tokenizer
    from orbis2.models.tokenizer import build_abstract_tokenizer, build_detail_tokenizer

    torch.manual_seed(0)
    abstract = cfg.tokenizer_abstract
    save_tokenizer(root / "detail.pt", "detail", build_detail_tokenizer(cfg.tokenizer_detail.preset), 1.0,
                   {"preset": cfg.tokenizer_detail.preset})
    save_tokenizer(root / "abstract.pt", "abstract",
                   build_abstract_tokenizer(abstract.preset, compress=abstract.compress), 1.0,
                   {"preset": abstract.preset, "teacher_dim": 768, "compress": abstract.compress})
    return root / "detail.pt", root / "abstract.pt"


def cpu_model() -> str:
    """The CPU's model name and its widest vector extension (timings differ 1.5-3x between AVX-512 and AVX2)."""
    for line in Path("/proc/cpuinfo").read_text().splitlines() if Path("/proc/cpuinfo").is_file() else []:
        if line.startswith("model name"):
            flags = Path("/proc/cpuinfo").read_text()
            return line.split(":", 1)[1].strip() + (" (AVX-512)" if "avx512f" in flags else " (AVX2)")
    return "unknown"
