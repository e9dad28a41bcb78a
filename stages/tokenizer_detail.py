"""Stage `tokenizer_detail`: train the VQ detail tokenizer -> data/tokenizers/detail, reports/tokenizer_detail.json.

Checkpoints live in data/runs/ (see `training_dir`): a killed run resumes there;
tokenizer.pt, the samples and the report are published atomically at the end.
"""

import sys
from pathlib import Path

from orbis2.registry import layout_path
from orbis2.stage import publish_training, stage_main, training_dir
from orbis2.tasks.tokenizers import train_detail_tokenizer

OUT = layout_path("tokenizer", "detail")
REPORT = layout_path("report", "tokenizer_detail")
SHARDS = layout_path("shards")
SECTIONS = ["data", "tokenizer_detail"]


def run(cfg, args, run):
    """Train the detail tokenizer (VQGAN objective), measure it, and save tokenizer.pt with its latent scale."""
    work = training_dir("tokenizer_detail", cfg, SECTIONS, {"shards": SHARDS / "manifest.json"})
    metrics = train_detail_tokenizer(cfg, SHARDS, work, Path(cfg.assets.dir), run)
    if not metrics:
        return "training rank done; rank 0 writes the outputs"
    run.log_metrics(metrics, step=int(metrics["steps"]))
    publish_training(work, OUT, ["tokenizer.pt"], REPORT, metrics, run)
    return (f"{metrics['steps']} steps, PSNR {metrics['val_psnr']:.2f} dB, SSIM {metrics['val_ssim']:.3f}, "
            f"rFID {metrics['rfid']:.1f}, codebook perplexity {metrics['val_perplexity']:.0f}, "
            f"latent scale {metrics['latent_scale']:.2f} -> {OUT / 'tokenizer.pt'}")


if __name__ == "__main__":
    argv = sys.argv[1:]
    if argv and argv[0] == "tokenizer_detail":  # the DAG names the stage; there is one detail tokenizer
        argv.pop(0)
    stage_main("tokenizer_detail", SECTIONS, run, argv=argv)
