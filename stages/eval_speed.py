"""Stage `eval_speed` / `eval_speed_all`: generated frames per second and peak memory
-> reports/eval/speed.json / speed_all.json.

    python stages/eval_speed.py main   # the main table's systems
    python stages/eval_speed.py all    # and the flat baselines, registry.yaml's speed_systems, Orbis v1's sampling

The scope's runs of ``SPEED_RUNS`` one after another in one process (paper Table 5):
batch 1, ``speed_seconds`` of rollout from a val context with the evaluation's NFE
(the distilled detail predictor with its own), the last-decoded frames included
(generation as a user sees it); bf16 / compile / KV cache per ``evaluation``.
"""


import torch

from orbis2.accel import default_device
from orbis2.eval.protocols.speed import measure
from orbis2.eval.protocols.systems import (
    SPEED_SYSTEMS,
    SYSTEMS,
    contexts_for,
    eval_samples,
    inference_settings,
    load_system,
    rollout_steps,
)
from orbis2.eval.records import Nfe, SpeedRecord, SpeedRun, write_record
from orbis2.interfaces import INTERFACES
from orbis2.latents import open_cache
from orbis2.registry import SCOPES, layout_path, registry
from orbis2.stage import (
    add_name_argument,
    latent_paths,
    open_stage,
    predictor_files,
    stage_parser,
)

LATENT_SET = "compressed"
# Speed rows: name -> (system, frames per step; None = the system's own). ``v1_style`` runs the flat detail
# network like Orbis v1, one frame per step at 10 Hz with the full NFE (same parameters, 5x the calls).
SPEED_RUNS = {
    "hierarchical": ("hierarchical", None),
    "hierarchical_distilled": ("hierarchical_distilled", None),
    "flat_detail": ("flat_detail", None),
    "flat_abstract": ("flat_abstract", None),
    "v1_style": ("flat_detail", 1),
}


def scope_runs(scope: str) -> list[str]:
    """The runs of a scope: those of the systems it times (registry.yaml)."""
    systems = registry().timed_systems(scope)
    return [name for name, (system, _) in SPEED_RUNS.items() if system in systems]


def main(argv: list[str] | None = None) -> None:
    parser = stage_parser(INTERFACES["eval_speed"], __doc__)
    add_name_argument(parser, SCOPES, default="main")
    args = parser.parse_args(argv)
    stage_name = "eval_speed" + ("_all" if args.name == "all" else "")
    out = args.out or layout_path("eval") / f"{stage_name.removeprefix('eval_')}.json"
    runs = scope_runs(args.name)
    with open_stage(stage_name, args, INTERFACES["eval_speed"]) as stage:
        cfg, run = stage.cfg, stage.run
        ev, data = cfg.evaluation, cfg.data
        dev = default_device()
        latents = latent_paths(args, LATENT_SET)
        known = {**SYSTEMS, **SPEED_SYSTEMS}
        predictors = predictor_files(args, [p for name in runs for p in known[SPEED_RUNS[name][0]].stages])
        cache = open_cache(latents.root)
        steps = rollout_steps(data, ev.speed_seconds)
        settings = inference_settings(ev)

        models: dict[str, SpeedRun] = {}
        for name in runs:
            system_name, frames_per_step = SPEED_RUNS[name]
            system = load_system(system_name, predictors, latents.tokenizers, dev, inference=settings)
            sample = eval_samples(cache, "val", data, steps, 1)[:1]
            contexts = contexts_for(system, cache, "val", data, sample, dev)
            bottom_nfe = system.bottom_nfe(ev.bottom_nfe)

            def one_rollout(system=system, contexts=contexts, nfe=bottom_nfe, per_step=frames_per_step) -> int:
                latents = system.rollout(contexts, steps, torch.Generator(dev).manual_seed(ev.seed), ev.top_nfe,
                                         nfe, frames_per_step=per_step)
                return system.decode(latents).shape[1]

            result = measure(one_rollout, warmup=1, repeats=ev.speed_repeats, device=dev)
            models[name] = SpeedRun(fps=result["fps"], peak_memory_mb=result["peak_memory_mb"],
                                    parameters=system.parameters, frames=result["frames"],
                                    memory_kind=result["memory_kind"], bottom_nfe=bottom_nfe,
                                    top_nfe=ev.top_nfe if system.top is not None else None,
                                    frames_per_step=frames_per_step or 5)
            del system, contexts

        record = SpeedRecord(device=torch.cuda.get_device_name() if dev.type == "cuda"
                             else f"cpu ({torch.get_num_threads()} threads)",
                             memory_kind=next(iter(models.values())).memory_kind, batch=1, seconds=steps * 0.5,
                             nfe=Nfe(top=ev.top_nfe, bottom=ev.bottom_nfe), models=models,
                             precision=settings.precision if dev.type == "cuda" else "fp32",
                             compile=settings.compile, kv_cache=settings.kv_cache)
        write_record(out, record)
        run.log_artifact(out)
        run.log_metrics({f"fps_{m}": v.fps for m, v in models.items()})
        stage.summary = ", ".join(f"{m} {v.fps:.2f} frames/s, {v.peak_memory_mb:.0f} MB" for m, v in models.items())


if __name__ == "__main__":
    main()
