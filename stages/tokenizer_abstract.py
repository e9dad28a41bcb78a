"""Stage `tokenizer_abstract`: train the teacher-aligned tokenizer -> data/tokenizers/abstract,
reports/tokenizer_abstract.json.

    python stages/tokenizer_abstract.py                            # the paper's 16-d latents
    python stages/tokenizer_abstract.py tokenizer_abstract_full    # compression ablation (compress: false)

Checkpoints live in data/runs/ (see `training_dir`): a killed run resumes there;
tokenizer.pt, the samples and the report are published atomically at the end.
"""

import sys
from pathlib import Path

from orbis2.registry import layout_path, registry
from orbis2.stage import publish_training, stage_main, training_dir
from orbis2.tasks.tokenizers import TEACHER_ASSETS, asset_path, train_abstract_tokenizer

# Stage name -> output folder, for every abstract tokenizer of registry.yaml.
VARIANTS = {f"tokenizer_{name}": layout_path("tokenizer", name)
            for name, kind in registry().tokenizers.items() if kind == "abstract"}


def body(name: str):
    out = VARIANTS[name]

    def run(cfg, args, run):
        """Train the abstract tokenizer against the frozen teacher, and save tokenizer.pt with its latent scale."""
        teacher = asset_path(Path(cfg.assets.dir), TEACHER_ASSETS[cfg.section(name).teacher])
        inputs = {"shards": layout_path("shards") / "manifest.json", "teacher": teacher}
        work = training_dir(name, cfg, ["data", name], inputs)
        metrics = train_abstract_tokenizer(cfg, layout_path("shards"), work, Path(cfg.assets.dir), run, name)
        if not metrics:
            return "training rank done; rank 0 writes the outputs"
        run.log_metrics(metrics, step=int(metrics["steps"]))
        publish_training(work, out, ["tokenizer.pt"], layout_path("report", name), metrics, run)
        return (f"{metrics['steps']} steps against {cfg.section(name).teacher}, alignment "
                f"{metrics['val_align']:.4g} (cosine {metrics['val_cosine']:.3f}), PSNR {metrics['val_psnr']:.2f} dB, "
                f"latent scale {metrics['latent_scale']:.2f} -> {out / 'tokenizer.pt'}")

    return run


if __name__ == "__main__":
    argv = sys.argv[1:]
    name = argv.pop(0) if argv and argv[0] in VARIANTS else "tokenizer_abstract"
    stage_main(name, ["data", name], body(name), argv=argv)
