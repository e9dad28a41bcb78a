"""Stage `tokenizer_abstract`: train the teacher-aligned tokenizer -> data/tokenizers/abstract,
reports/tokenizer_abstract.json.

Checkpoints live in data/runs/ (see `training_dir`): a killed run resumes there;
tokenizer.pt, the samples and the report are published atomically at the end.
"""

from pathlib import Path

from orbis2.stage import publish_training, stage_main, training_dir
from orbis2.tasks.tokenizers import train_abstract_tokenizer

OUT = Path("data/tokenizers/abstract")
REPORT = Path("reports/tokenizer_abstract.json")
SECTIONS = ["data", "tokenizer_abstract"]


def run(cfg, args, run):
    """Train the abstract tokenizer against the frozen teacher, and save tokenizer.pt with its latent scale."""
    work = training_dir("tokenizer_abstract", cfg, SECTIONS)
    metrics = train_abstract_tokenizer(cfg, Path("data/shards"), work, Path(cfg.assets.dir), run)
    if not metrics:
        return "training rank done; rank 0 writes the outputs"
    run.log_metrics(metrics, step=int(metrics["steps"]))
    publish_training(work, OUT, ["tokenizer.pt"], REPORT, metrics, run)
    return (f"{metrics['steps']} steps against {cfg.tokenizer_abstract.teacher}, alignment "
            f"{metrics['val_align']:.4g} (cosine {metrics['val_cosine']:.3f}), PSNR {metrics['val_psnr']:.2f} dB, "
            f"latent scale {metrics['latent_scale']:.2f} -> {OUT / 'tokenizer.pt'}")


if __name__ == "__main__":
    stage_main("tokenizer_abstract", SECTIONS, run)
