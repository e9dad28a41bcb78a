"""Stage `eval_conditioning` / `eval_conditioning_all`: does each predictor use its conditioning and beat
trivial predictions? -> reports/eval/conditioning.json / conditioning_all.json.

    python stages/eval_conditioning.py main   # the main table's predictors and the steered one
    python stages/eval_conditioning.py all    # and the flat baselines' (registry.yaml `baselines`)

Paired variant errors on val windows, one-step conditional means vs baselines,
latent statistics and the steered predictor's response inside the model
(:mod:`orbis2.eval.protocols.conditioning`): every predictor of the scope on the same val
windows and noise draws, over ``evaluation.seeds``.

Each predictor's rows depend on that predictor alone (its own noise draws and bootstrap), and the
latent statistics on the cache alone, so the all scope given ``--main-record`` (as the DAG gives it)
takes the main scope's rows and statistics from that record and evaluates only the other predictors:
the same record, bit for bit, as evaluating them all again.
"""


import numpy as np

from orbis2.accel import default_device
from orbis2.errors import OrbisError
from orbis2.eval.protocols.conditioning import (
    evaluate_predictor,
    latent_statistics,
    latent_steering_response,
    latent_templates,
    predictor_rows,
    steering_readouts,
    val_window_pairs,
)
from orbis2.eval.records import ConditioningRecord, from_json, write_record
from orbis2.interfaces import INTERFACES
from orbis2.latents import open_cache
from orbis2.models.files import load_predictor
from orbis2.registry import SCOPES, layout_path, registry
from orbis2.stage import add_name_argument, open_stage, predictor_files, stage_parser

LATENT_SET = "compressed"


def main(argv: list[str] | None = None) -> None:
    parser = stage_parser(INTERFACES["eval_conditioning"], __doc__)
    add_name_argument(parser, SCOPES, default="main")
    args = parser.parse_args(argv)
    if args.main_record and args.name == "main":
        parser.error("--main-record is the all scope's: the main scope evaluates its predictors")
    stage_name = "eval_conditioning" + ("_all" if args.name == "all" else "")
    out = args.out or layout_path("eval") / f"{stage_name.removeprefix('eval_')}.json"
    with open_stage(stage_name, args, INTERFACES["eval_conditioning"]) as stage:
        cfg, run = stage.cfg, stage.run
        ev, data, settings = cfg.evaluation, cfg.data, cfg.evaluation.conditioning
        dev = default_device()
        names = registry().conditioning_predictors(args.name)
        predictors = predictor_files(args, names)
        cache = open_cache(args.latents or registry().latent_sets[LATENT_SET].root)
        first, second, keys = val_window_pairs(cache, data, settings)
        templates = latent_templates(cache)
        shared = (main_rows(args.main_record, registry().conditioning_predictors("main"), keys, settings, ev.seeds)
                  if args.main_record else None)
        if shared is None:
            latents, probe = latent_statistics(cache, data, settings, ev.seed, templates)
            variants, baselines, response = [], [], None
        else:
            latents, probe, response = shared.latents.model_dump(), None, shared.steering_response
            variants, baselines = [row.model_dump() for row in shared.variants], [row.model_dump() for row in
                                                                                 shared.baselines]
            names = [name for name in names if name not in {row["model"] for row in baselines}]
        for name in names:
            predictor = load_predictor(predictors[name], dev)
            per_seed = [evaluate_predictor(name, predictor, first, second, keys, templates, data, settings, seed, dev)
                        for seed in ev.seeds]
            its_variants, its_baselines = predictor_rows(name, per_seed, keys, settings.threshold,
                                                         settings.bootstrap_reps, ev.seed)
            variants += its_variants
            baselines += its_baselines
            if registry().predictors[name].steering:  # its response inside the model, read by the ego-motion probe
                readouts = [steering_readouts(name, predictor, first, data, ev.steering_modes, probe, settings, seed,
                                              dev) for seed in ev.seeds]
                mean = {k: np.mean([r[k] for r in readouts], axis=0) for k in readouts[0]}
                response = {"model": name, **latent_steering_response(
                    mean, ev.steering_modes, keys, settings.bootstrap_reps, ev.seed, settings.response_material)}
            del predictor
        record = ConditioningRecord(split="val", windows=len(keys), clips=len(set(keys)), draws=settings.draws,
                                    seeds=list(ev.seeds), threshold=settings.threshold,
                                    bootstrap_reps=settings.bootstrap_reps, variants=variants, baselines=baselines,
                                    latents=latents, steering_response=response)

        write_record(out, record)
        run.log_artifact(out)
        run.log_metrics({f"{r.model}_{r.metric}_{r.variant}_effect": r.effect
                         for r in record.variants if r.verdict != "reference"})
        run.log_metrics({f"{r.model}_{r.baseline}_{r.horizon_s:g}s_effect": r.effect for r in record.baselines})
        stats = record.latents
        run.log_metrics({f"latents_{level}_{k}": getattr(shares, k) for level, shares in
                         (("abstract", stats.abstract), ("detail", stats.detail))
                         for k in ("varying_share", "within_clip_share", "repeat_last_relative")})
        ego = stats.ego_motion_probe
        run.log_metrics({f"ego_probe_{name}_r2": fit.r2 for name, fit in (("speed", ego.speed),
                                                                        ("yaw_rate", ego.yaw_rate))
                         if np.isfinite(fit.r2)})
        responses = record.steering_response.responses if record.steering_response is not None else {}
        run.log_metrics({f"steering_latent_response_{name}": r.relative for name, r in responses.items() if r})
        used = [f"{r.model}/{r.variant}" for r in record.variants
                if r.metric == "one_step_mse" and r.verdict == "used"]
        used += [f"latent response to {name}" + (" (ordered x0.5 < original < x1.5)" if r.ordered else "")
                 for name, r in responses.items() if r and r.verdict == "used"]
        stage.summary = (f"{len(keys)} val windows from {record.clips} clips x {settings.draws} draws x "
                         f"{len(ev.seeds)} seeds; inputs used (one-step mean): {', '.join(used) or 'none shown'}; "
                         f"ego-motion probe R^2 speed {ego.speed.r2:.2f}, yaw rate {ego.yaw_rate.r2:.2f}")


def main_rows(path, names: list[str], keys, settings, seeds) -> ConditioningRecord:
    """The main scope's record at ``path``, checked to fit this run: its windows, draws, seeds and bootstrap, and
    its predictors ``names``, the main scope's (the steered one among them, so the all scope never needs the
    ego-motion probe itself)."""
    record = from_json(ConditioningRecord, path, "eval_conditioning")
    models = list(dict.fromkeys(row.model for row in record.baselines))
    made = (record.windows, record.clips, record.draws, list(record.seeds), record.threshold, record.bootstrap_reps)
    wanted = (len(keys), len(set(keys)), settings.draws, list(seeds), settings.threshold, settings.bootstrap_reps)
    if made != wanted or models != names:
        raise OrbisError(f"{path} was made with other settings or predictors (windows, clips, draws, seeds, "
                         f"threshold, bootstrap: {made}, predictors {models}; this run: {wanted}, predictors "
                         f"{names}); run `python stages/eval_conditioning.py main` again, or leave out --main-record")
    return record


if __name__ == "__main__":
    main()
