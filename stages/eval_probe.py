"""Stage `eval_probe_<target>`: linear probes (segmentation mIoU, depth RMSE) of one representation
-> reports/eval/probe_<target>.json.

    python stages/eval_probe.py abstract_tf --profile default

Targets (registry.yaml, ``probe_targets``): abstract_tokenizer, teacher, and every
predictor stage but action. Predictors follow the null-context protocol of
:func:`orbis2.eval.protocols.probe.predictor_features` (paper appendix "Linear probing
details"); the k-th block from the end is clamped to the network's depth.
"""

from pathlib import Path

from orbis2.accel import default_device
from orbis2.assets import TEACHER_ASSETS, asset_path
from orbis2.eval.protocols.probe import (
    predictor_features,
    probe_all,
    probe_config,
    probe_sets,
    teacher_features,
    tokenizer_features,
)
from orbis2.eval.records import BlockProbe, ProbeRecord, write_record
from orbis2.interfaces import INTERFACES
from orbis2.models.files import load_predictor, load_tokenizer
from orbis2.models.teachers import build_teacher
from orbis2.registry import registry
from orbis2.stage import (
    add_name_argument,
    latent_paths,
    open_stage,
    predictor_files,
    stage_parser,
)

# The main model's predictors are probed at ``block_main`` (the paper's 4th from the end), ablations at
# ``block_ablation``. Per-block curves (paper Fig. 5: diffusion forcing vs teacher forcing at every block)
# for the DF-only and TF-only predictors; both are ablation targets, so the main report does not wait for them.
MAIN_PROBES = ("abstract_tf", "detail")
PER_BLOCK = ("abstract_df", "abstract_tf_only")

INTERFACE = INTERFACES["eval_probe"]


def main(argv: list[str] | None = None) -> None:
    reg = registry()
    parser = stage_parser(INTERFACE, __doc__)  # --shards: its probe split
    add_name_argument(parser, reg.probe_targets, prefix="eval_probe_")
    args = parser.parse_args(argv)
    target = args.name
    out = args.out or INTERFACE.option("probe").path(target)
    with open_stage(f"eval_probe_{target}", args, INTERFACE) as stage:
        cfg, run = stage.cfg, stage.run
        ps, dev = cfg.evaluation.probe, default_device()
        probe_cfg = probe_config(ps, str(dev))
        sets = probe_sets(ps, (cfg.data.width, cfg.data.height), args.shards)
        tokenizers = latent_paths(args, reg.target_latents(target)).tokenizers

        representation = reg.representations.get(target)
        block, per_block = None, None
        if representation is not None and not representation.teacher:
            label = f"Abstract tokenizer ({representation.latents})"
            tokenizer = load_tokenizer(tokenizers["abstract"], dev)
            result = probe_all(tokenizer_features(tokenizer), sets, probe_cfg)
        elif representation is not None:
            tc = cfg.tokenizer_abstract
            assets = args.assets or Path(cfg.assets.dir)
            teacher = build_teacher(tc.teacher, asset_path(assets, TEACHER_ASSETS[tc.teacher]),
                                    tc.teacher_layer).to(dev)
            label = f"Teacher ({tc.teacher})"
            result = probe_all(teacher_features(teacher), sets, probe_cfg)
        else:
            predictor = load_predictor(predictor_files(args, [target])[target], dev)
            tokenizer = load_tokenizer(tokenizers[predictor.meta["level"]], dev)
            depth = len(predictor.model.blocks)
            wanted = ps.block_main if target in MAIN_PROBES else ps.block_ablation
            label, block = target, min(wanted, depth)
            result = probe_all(predictor_features(predictor, tokenizer, block), sets, probe_cfg)
            if target in PER_BLOCK:
                per_block = []
                for k in range(1, depth + 1):
                    r = result if k == block else probe_all(predictor_features(predictor, tokenizer, k), sets,
                                                            probe_cfg)
                    per_block.append(BlockProbe(block=k, miou=r["segmentation"]["miou"], rmse=r["depth"]["rmse"]))
        record = ProbeRecord(target=target, label=label, block=block, segmentation=result["segmentation"],
                             depth=result["depth"], data=result["data"], per_block=per_block)

        write_record(out, record)
        run.log_artifact(out)
        run.log_metrics({"miou": result["segmentation"]["miou"], "depth_rmse": result["depth"]["rmse"]})
        stage.summary = (f"{target}: mIoU {result['segmentation']['miou']:.3f} ({result['data']['segmentation']}), "
                         f"depth RMSE {result['depth']['rmse']:.2f} m ({result['data']['depth']})")


if __name__ == "__main__":
    main()
