"""Stage `tokenizer_detail`: train the VQ detail tokenizer -> data/tokenizers/detail, reports/tokenizer_detail.json.

The VQGAN objective; the stage measures the result and saves tokenizer.pt with its
latent scale. Checkpoints live in data/runs/ (see `work_dir`): a killed run
resumes there; tokenizer.pt, the samples and the report are published atomically
at the end. With params.yaml's ``official_weights`` set, the stage publishes the
imported tokenizer instead (orbis2.tasks.official).
"""

from pathlib import Path

from orbis2.interfaces import INTERFACES
from orbis2.stage import (
    TOKENIZER_FILE,
    add_name_argument,
    open_stage,
    publish_training,
    stage_parser,
    work_dir,
)
from orbis2.tasks.official import imported_tokenizer, publish_tokenizer
from orbis2.tasks.tokenizers import train_detail_tokenizer

INTERFACE = INTERFACES["tokenizer_detail"]
ENTRY = "detail"  # registry.yaml's tokenizer of this kind
SECTIONS = INTERFACE.sections_with([f"tokenizer_{ENTRY}"])


def main(argv: list[str] | None = None) -> None:
    parser = stage_parser(INTERFACE, __doc__)  # --assets: InceptionV3 for rFID
    add_name_argument(parser, ["tokenizer_detail"], default="tokenizer_detail")  # the DAG names the stage
    args = parser.parse_args(argv)
    out = args.out or INTERFACE.option("weights").path(ENTRY)
    report = args.report or INTERFACE.option("report").path(ENTRY)
    with open_stage("tokenizer_detail", args, INTERFACE, SECTIONS) as stage:
        cfg, run = stage.cfg, stage.run
        imported = imported_tokenizer(cfg.official_weights, ENTRY)  # params.yaml official_weights
        if imported is not None:
            stage.summary = publish_tokenizer(imported, cfg, out / TOKENIZER_FILE, report, run)
            return
        assets = args.assets or Path(cfg.assets.dir)
        work = work_dir("tokenizer_detail", cfg, SECTIONS, {"shards": args.shards / "manifest.json"}, __file__)
        metrics = train_detail_tokenizer(cfg, args.shards, work, assets, run)
        if not metrics:
            stage.summary = "training rank done; rank 0 writes the outputs"
            return

        publish_training(work, out, [TOKENIZER_FILE], report, metrics, run)
        stage.summary = (f"{metrics['steps']} steps, PSNR {metrics['val_psnr']:.2f} dB, SSIM "
                         f"{metrics['val_ssim']:.3f}, rFID {metrics['rfid']:.1f}, codebook perplexity "
                         f"{metrics['val_perplexity']:.0f}, latent scale {metrics['latent_scale']:.2f} -> "
                         f"{out / TOKENIZER_FILE}")


if __name__ == "__main__":
    main()
