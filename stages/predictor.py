"""Stage `<predictor>`: train one predictor of the hierarchy or of its ablations
-> data/predictors/<predictor>/predictor.pt, reports/<predictor>.json.

    python stages/predictor.py abstract_df --profile default

The predictor names are the keys of ``orbis2.tasks.predictors.STAGES`` (each
with its params.yaml section of the same name): abstract_df, abstract_tf,
detail, action, and the ablations abstract_tf_only, flat_detail,
flat_abstract, top_detail, detail_on_detail. Checkpoints live in data/runs/
(see ``orbis2.stage.work_dir``), in a folder keyed by the params, the code and
the upstream files (the latent cache's meta, which names the tokenizers and
shards, the ``init_from`` predictor and, with params.yaml's ``official_weights``,
the imported predictor the stage is built from: orbis2.tasks.official): a killed
run resumes there, while a retrained upstream starts a fresh run instead of
resuming one that trained on other inputs. predictor.pt and the report are
published atomically at the end.
"""


from orbis2.errors import OrbisError
from orbis2.interfaces import INTERFACES
from orbis2.latents import open_cache
from orbis2.stage import (
    PREDICTOR_FILE,
    add_name_argument,
    latent_paths,
    open_stage,
    publish_training,
    stage_parser,
    work_dir,
)
from orbis2.tasks.official import imported_predictor
from orbis2.tasks.predictors import STAGES, tokenizer_checksums, train_predictor

INTERFACE = INTERFACES["predictor"]


def main(argv: list[str] | None = None) -> None:
    parser = stage_parser(INTERFACE, __doc__)
    add_name_argument(parser, STAGES)
    args = parser.parse_args(argv)
    name = args.name
    out = args.out or INTERFACE.option("weights").path(name)
    report = args.report or INTERFACE.option("report").path(name)
    sections = INTERFACE.sections_with([name])  # the entry's own section
    with open_stage(name, args, INTERFACE, sections) as stage:
        cfg, run = stage.cfg, stage.run
        pc = cfg.section(name)
        latents = latent_paths(args, STAGES[name].latents)
        cache = open_cache(latents.root,
                           *tokenizer_checksums(latents.tokenizers["detail"], latents.tokenizers["abstract"]))
        inputs = {"latents": latents.root / "meta.json"}
        init_file = None
        if pc.init_from is None and args.init is not None:
            raise OrbisError(f"--init {args.init}: `{name}` has no init_from in params.yaml")
        if pc.init_from is not None:
            init_file = (args.init or INTERFACE.option("init").path(pc.init_from)) / PREDICTOR_FILE
            if not init_file.is_file():
                raise OrbisError(f"{init_file}: not found; `{name}` starts from it (init_from), run "
                                 f"`{pc.init_from}` first")
            inputs[pc.init_from] = init_file

        imported = imported_predictor(cfg.official_weights, STAGES[name])  # params.yaml official_weights
        if imported is not None:
            inputs["imported"] = imported

        work = work_dir(name, cfg, sections, inputs, __file__)
        metrics = train_predictor(name, cfg, cache, work, run, init_file, imported)
        if not metrics:
            stage.summary = "training rank done; rank 0 writes the outputs"
            return

        publish_training(work, out, [PREDICTOR_FILE], report, metrics, run)
        few = (f"; {pc.student_nfe}-step MSE to the teacher's {pc.teacher_nfe}-step sample "
               f"{metrics['few_step_mse_student']:.4f} (teacher's own {metrics['few_step_mse_teacher']:.4f})"
               if "few_step_mse_student" in metrics else "")
        stage.summary = (f"{metrics['steps']} steps, {metrics['parameters'] / 1e6:.2f}M parameters, val loss "
                         f"{metrics['val_loss']:.4f} (at initialisation {metrics['val_loss_init']:.4f}){few} -> "
                         f"{out / PREDICTOR_FILE}")


if __name__ == "__main__":
    main()
