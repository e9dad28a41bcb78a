"""Stage `tokenizer_detail`: train the VQ detail tokenizer -> data/tokenizers/detail, reports/tokenizer_detail.json.

The VQGAN objective; the stage measures the result and saves tokenizer.pt with its
latent scale. Checkpoints live in data/runs/ (see `training_dir`): a killed run
resumes there; tokenizer.pt, the samples and the report are published atomically
at the end.
"""

from pathlib import Path

from orbis2.data.shards import verify_shards
from orbis2.registry import layout_path
from orbis2.stage import (
    TOKENIZER_FILE,
    add_name_argument,
    open_stage,
    publish_training,
    stage_parser,
    training_dir,
)
from orbis2.tasks.tokenizers import train_detail_tokenizer

SECTIONS = ["data", "tokenizer_detail"]


def main(argv: list[str] | None = None) -> None:
    parser = stage_parser("tokenizer_detail.py", __doc__)
    add_name_argument(parser, ["tokenizer_detail"], default="tokenizer_detail")  # the DAG names the stage
    parser.add_argument("--shards", type=Path, default=layout_path("shards"), help="shards (default: %(default)s)")
    parser.add_argument("--assets", type=Path, default=None, help="pretrained assets, InceptionV3 for rFID "
                                                                  "(default: assets.dir)")
    parser.add_argument("--out", type=Path, default=layout_path("tokenizer", "detail"),
                        help="output folder (default: %(default)s)")
    parser.add_argument("--report", type=Path, default=layout_path("report", "tokenizer_detail"),
                        help="metrics report (default: %(default)s)")
    args = parser.parse_args(argv)
    with open_stage("tokenizer_detail", args, SECTIONS) as stage:
        cfg, run = stage.cfg, stage.run
        verify_shards(args.shards)  # before any read; see verify_shards for why
        assets = args.assets or Path(cfg.assets.dir)
        work = training_dir("tokenizer_detail", cfg, SECTIONS, {"shards": args.shards / "manifest.json"})
        metrics = train_detail_tokenizer(cfg, args.shards, work, assets, run)
        if not metrics:
            stage.summary = "training rank done; rank 0 writes the outputs"
            return

        publish_training(work, args.out, [TOKENIZER_FILE], args.report, metrics, run)
        stage.summary = (f"{metrics['steps']} steps, PSNR {metrics['val_psnr']:.2f} dB, SSIM "
                         f"{metrics['val_ssim']:.3f}, rFID {metrics['rfid']:.1f}, codebook perplexity "
                         f"{metrics['val_perplexity']:.0f}, latent scale {metrics['latent_scale']:.2f} -> "
                         f"{args.out / TOKENIZER_FILE}")


if __name__ == "__main__":
    main()
