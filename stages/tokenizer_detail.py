"""Stage `tokenizer_detail`: train the VQ detail tokenizer -> data/tokenizers/detail, reports/tokenizer_detail.json.

The VQGAN objective; the stage measures the result and saves tokenizer.pt with its
latent scale. Checkpoints live in data/runs/ (see `training_dir`): a killed run
resumes there; tokenizer.pt, the samples and the report are published atomically
at the end.
"""

from pathlib import Path

from orbis2.registry import layout_path
from orbis2.stage import add_name_argument, open_stage, publish_training, stage_parser, training_dir
from orbis2.tasks.tokenizers import train_detail_tokenizer

OUT = layout_path("tokenizer", "detail")
REPORT = layout_path("report", "tokenizer_detail")
SHARDS = layout_path("shards")
SECTIONS = ["data", "tokenizer_detail"]


def main(argv: list[str] | None = None) -> None:
    parser = stage_parser("tokenizer_detail.py", __doc__)
    add_name_argument(parser, ["tokenizer_detail"], default="tokenizer_detail")  # the DAG names the stage
    args = parser.parse_args(argv)
    with open_stage("tokenizer_detail", args, SECTIONS) as stage:
        cfg, run = stage.cfg, stage.run
        work = training_dir("tokenizer_detail", cfg, SECTIONS, {"shards": SHARDS / "manifest.json"})
        metrics = train_detail_tokenizer(cfg, SHARDS, work, Path(cfg.assets.dir), run)
        if not metrics:
            stage.summary = "training rank done; rank 0 writes the outputs"
            return

        run.log_metrics(metrics, step=int(metrics["steps"]))
        publish_training(work, OUT, ["tokenizer.pt"], REPORT, metrics, run)
        stage.summary = (f"{metrics['steps']} steps, PSNR {metrics['val_psnr']:.2f} dB, SSIM "
                         f"{metrics['val_ssim']:.3f}, rFID {metrics['rfid']:.1f}, codebook perplexity "
                         f"{metrics['val_perplexity']:.0f}, latent scale {metrics['latent_scale']:.2f} -> "
                         f"{OUT / 'tokenizer.pt'}")


if __name__ == "__main__":
    main()
