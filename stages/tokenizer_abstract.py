"""Stage `tokenizer_abstract`: train the teacher-aligned tokenizer -> data/tokenizers/abstract,
reports/tokenizer_abstract.json.

    python stages/tokenizer_abstract.py                            # the paper's 16-d latents
    python stages/tokenizer_abstract.py tokenizer_abstract_full    # compression ablation (compress: false)

Trained against the frozen teacher; tokenizer.pt is saved with its latent scale.
Checkpoints live in data/runs/ (see `work_dir`): a killed run resumes there;
tokenizer.pt, the samples and the report are published atomically at the end.
With params.yaml's ``official_weights`` set, the main set's abstract tokenizer
(tokenizer_abstract) is the imported one, published instead (orbis2.tasks.official).
"""

from pathlib import Path

from orbis2.assets import TEACHER_ASSETS, asset_path
from orbis2.interfaces import INTERFACES
from orbis2.registry import registry
from orbis2.stage import (
    TOKENIZER_FILE,
    add_name_argument,
    open_stage,
    publish_training,
    stage_parser,
    work_dir,
)
from orbis2.tasks.official import imported_tokenizer, publish_tokenizer
from orbis2.tasks.tokenizers import train_abstract_tokenizer

# Stage name -> registry.yaml entry, for every abstract tokenizer.
INTERFACE = INTERFACES["tokenizer_abstract"]
VARIANTS = {f"tokenizer_{name}": name for name, kind in registry().tokenizers.items() if kind == "abstract"}


def main(argv: list[str] | None = None) -> None:
    parser = stage_parser(INTERFACE, __doc__)  # --assets: the teacher
    add_name_argument(parser, VARIANTS, default="tokenizer_abstract")
    args = parser.parse_args(argv)
    name = args.name
    out = args.out or INTERFACE.option("weights").path(VARIANTS[name])
    report = args.report or INTERFACE.option("report").path(VARIANTS[name])
    sections = INTERFACE.sections_with([name])  # the entry's own section
    with open_stage(name, args, INTERFACE, sections) as stage:
        cfg, run = stage.cfg, stage.run
        imported = imported_tokenizer(cfg.official_weights, VARIANTS[name])  # params.yaml official_weights
        if imported is not None:
            stage.summary = publish_tokenizer(imported, cfg, out / TOKENIZER_FILE, report, run)
            return
        assets = args.assets or Path(cfg.assets.dir)
        teacher = asset_path(assets, TEACHER_ASSETS[cfg.section(name).teacher])
        inputs = {"shards": args.shards / "manifest.json", "teacher": teacher}
        work = work_dir(name, cfg, sections, inputs, __file__)
        metrics = train_abstract_tokenizer(cfg, args.shards, work, assets, run, name)
        if not metrics:
            stage.summary = "training rank done; rank 0 writes the outputs"
            return

        publish_training(work, out, [TOKENIZER_FILE], report, metrics, run)
        stage.summary = (f"{metrics['steps']} steps against {cfg.section(name).teacher}, alignment "
                         f"{metrics['val_align']:.4g} (cosine {metrics['val_cosine']:.3f}), PSNR "
                         f"{metrics['val_psnr']:.2f} dB, latent scale {metrics['latent_scale']:.2f} -> "
                         f"{out / TOKENIZER_FILE}")


if __name__ == "__main__":
    main()
