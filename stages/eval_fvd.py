"""Stage `eval_fvd_<system>`: FVD over rollouts on each evaluation split, chunked FVD and FVD-slope
-> reports/eval/fvd_<system>.json, reports/eval/media/<system>/ (sample videos, frames for the grid).

    python stages/eval_fvd.py hierarchical --profile default

Systems (``orbis2.eval.protocols.systems.SYSTEMS``): flat_detail, flat_abstract, hierarchical
(the main table), top_detail and top_abstract_10hz (hierarchy Exps. 4 and 5).

Each split gets FVD over ``seconds`` with a clip-bootstrap interval beside the
reference rows of :mod:`orbis2.eval.protocols.references`; ``long_split`` also chunked FVD and
the FVD-slope over ``long_seconds`` (:mod:`orbis2.eval.protocols.rollout_fvd`). Whether a
rollout beats repeating the last frame in latent space is the ``eval_conditioning``
stage's unbiased one-step comparison, not a sample's MSE (which pays twice the
conditional variance).

The rollouts' side runs in ``parts`` (params.yaml ``parts``, or ``--parts``): part i generates,
decodes and featurises the i-th block of each split's rollout batches. ``--part I`` does that
part only (the DAG runs one job per part above one part, Snakemake's rule
``eval_fvd_<system>_part``, an array of GPU jobs on Slurm) and writes its outcome into
data/runs/ (one file per batch, so a killed part resumes at its batch) and its part manifest;
without it the stage makes every batch no job left there, then the real side, the intervals and
the media. Each batch draws its own noise and is processed alone, so the figures do not depend
on ``parts``.
"""

from contextlib import nullcontext
from pathlib import Path

from orbis2.accel import default_device
from orbis2.assets import ensure_asset
from orbis2.data.parts import add_part_options, part_name, parts_of, write_part_manifest
from orbis2.data.shards import MANIFEST
from orbis2.eval.protocols.rollout_fvd import (
    part_outcome,
    split_fvd,
    split_plan,
    write_manifest,
    write_media,
)
from orbis2.eval.protocols.systems import SYSTEMS, inference_settings, load_system
from orbis2.eval.records import FvdRecord, Nfe, write_record
from orbis2.interfaces import INTERFACES
from orbis2.io import atomic_dir, sha256_file
from orbis2.latents import META, open_cache
from orbis2.models.i3d import load_i3d
from orbis2.registry import layout_path
from orbis2.stage import (
    add_name_argument,
    latent_paths,
    open_stage,
    predictor_files,
    stage_parser,
    work_dir,
)

INTERFACE = INTERFACES["eval_fvd"]


def main(argv: list[str] | None = None) -> None:
    parser = stage_parser(INTERFACE, __doc__)  # --assets: I3D
    add_name_argument(parser, SYSTEMS, prefix="eval_fvd_")
    add_part_options(parser, "eval_parts", prefix="<system>/")
    # Real-data I3D statistics, keyed by the shards' hashes; outside every stage's outputs so they survive re-runs.
    parser.add_argument("--stats-cache", type=Path, default=layout_path("eval_cache"),
                        help="cache of real-data I3D statistics, not a DAG output (default: %(default)s)")
    parser.add_argument("--rollouts", type=Path, default=None,
                        help="also write every rollout, its real video and a manifest per split here, losslessly, "
                             "for `orbis2 evaluate` (decodes every frame: slower; every part in this process)")
    args = parser.parse_args(argv)
    parts = parts_of(parser, args)
    if args.rollouts and args.part is not None:
        parser.error("--rollouts writes every rollout from this process: leave out --part")
    name = args.name
    stage_name = f"eval_fvd_{name}" if args.part is None else f"eval_fvd_{name}_part_{part_name(args.part, parts)}"
    report = args.fvd or INTERFACE.option("fvd").path(name)
    media = args.media or INTERFACE.option("media").path(name)
    with open_stage(stage_name, args, INTERFACE) as stage:
        cfg, run = stage.cfg, stage.run
        ev, dev = cfg.evaluation, default_device()

        latents = latent_paths(args, SYSTEMS[name].latents)
        predictors = predictor_files(args, SYSTEMS[name].stages)
        system = load_system(name, predictors, latents.tokenizers, dev, inference=inference_settings(ev))
        cache = open_cache(latents.root)
        assets = args.assets or Path(cfg.assets.dir)
        i3d_file = ensure_asset("i3d_kinetics400", assets, cfg.assets.local.get("i3d_kinetics400"), download=False)
        i3d = load_i3d(i3d_file).to(dev).eval()
        i3d_sha = sha256_file(i3d_file)
        # Where each batch's outcome is kept: keyed by everything it depends on, so that no run reads an outcome
        # made from other models, latents, settings or code.
        work = work_dir(f"eval_fvd_{name}", cfg, ["data", "evaluation"],
                        {"manifest": args.shards / MANIFEST, "latents": latents.root / META, "i3d": i3d_file,
                         **latents.tokenizers, **predictors}, __file__)
        plans = {split: split_plan(split, cache, cfg.data, ev) for split in ev.fvd_splits}

        if args.part is not None:
            rollouts = {split: len(part_outcome(plan, plan.part_batches(args.part, parts), system, cache, i3d,
                                                cfg.data, ev, dev, args.shards, work).get("generated_psnr", ()))
                        for split, plan in plans.items()}
            write_part_manifest(args, "eval_parts", parts, {"outcomes": str(work), "rollouts": rollouts},
                                prefix=f"{name}/")
            run.log_metrics({f"rollouts_{split}": n for split, n in rollouts.items()})
            stage.summary = f"{name} part {part_name(args.part, parts)}: rollouts {rollouts} -> {work}"
            return

        results = {}
        with atomic_dir(media) as tmp, (atomic_dir(args.rollouts) if args.rollouts else nullcontext()) as rollouts:
            for split, plan in plans.items():  # the batches no part job left in `work` are made here
                outcome = part_outcome(plan, range(plan.batches), system, cache, i3d, cfg.data, ev, dev, args.shards,
                                       work, rollouts)
                results[split] = split_fvd(plan, outcome, system, cache, i3d, cfg.data, ev, args.shards,
                                           args.stats_cache, i3d_sha)  # first: it checks the rollout count
                write_media(plan, outcome, system, cache, tmp, cfg.data, args.shards)
                if rollouts is not None:
                    write_manifest(rollouts / split, plan, cfg.data)
        chunked = [r["chunked"] for r in results.values() if "chunked" in r]
        record = FvdRecord(model=name, label=SYSTEMS[name].label, parameters=system.parameters,
                           latent_channels=system.bottom.model.latent_channels, predictors=SYSTEMS[name].stages,
                           nfe=Nfe(top=ev.top_nfe, bottom=ev.bottom_nfe), starts_per_clip=ev.starts_per_clip,
                           fvd_material=ev.fvd_material, fvd={s: r["fvd"] for s, r in results.items()},
                           references={s: r["references"] for s, r in results.items()},
                           protocol={s: r["protocol"] for s, r in results.items()},
                           chunked=chunked[-1] if chunked else None,
                           first_frame={s: r["first_frame"] for s, r in results.items()})

        # the parent's rollout gallery: per system and split, real beside generated as VP9 and as GIF
        for video in sorted([*media.glob("*.mp4"), *media.glob("*.gif")]):
            run.log_artifact(video, "videos")
            run.publish(video, "gallery", f"{name}_{video.name}")
        write_record(report, record)
        run.log_artifact(report)
        run.log_metrics({f"fvd_{split}": v.fvd for split, v in record.fvd.items()})
        run.log_metrics({f"fvd_{split}_{ref}": v.fvd for split, refs in record.references.items()
                         for ref, v in refs if v is not None and v.fvd is not None})
        if record.chunked is not None:
            run.log_metrics({"fvd_slope": record.chunked.fvd_slope})
        splits = ", ".join(f"{s} {v.fvd:.1f} [{v.low:.1f}, {v.high:.1f}] (n={v.videos}, {v.clips} clips)"
                           for s, v in record.fvd.items())
        slope = f"; FVD-slope {record.chunked.fvd_slope:.1f}" if record.chunked is not None else ""
        first = "; first frame PSNR (generated, tokenizer): " + ", ".join(
            f"{s} {v.generated_psnr.estimate:.1f}, {v.reconstruction_psnr.estimate:.1f} dB"
            for s, v in (record.first_frame or {}).items())
        stage.summary = f"{name}: FVD {splits}{slope}{first}"


if __name__ == "__main__":
    main()
