# Every predictor of registry.yaml, main and ablation: the same stage script given
# the predictor's name and its params.yaml section; its init_from adds the weights
# it starts from as an input.

from orbis2.tasks.official import counterpart, imported_predictor

PREDICTOR = INTERFACES["predictor"]

for predictor, spec in REG.predictors.items():
    init_from = section(predictor).get("init_from")
    paths = stage_paths(PREDICTOR, predictor, **latent_paths(spec.latents),
                        init=P("predictor", init_from) if init_from else None)
    # params.yaml official_weights: built from (and without init_from started from) the imported predictor
    official = (official_setting(imported_predictor(config["official_weights"], spec))
                if counterpart(spec) else ({}, {}))

    rule:
        name: predictor
        threads: PREDICTOR.resources.threads
        priority: PREDICTOR.priority
        resources: **resources_of(PREDICTOR)
        input:
            code_inputs(PREDICTOR.script),
            **inputs(PREDICTOR, paths),
            **official[0],
        output:
            **outputs(PREDICTOR, paths),
        params:
            # spec: registry.yaml's entry, so that a changed spec re-runs the predictor
            **stage_params(PREDICTOR, paths, [predictor], spec=dataclasses.asdict(spec), **official[1]),
        log: log(predictor)
        benchmark: bench(predictor)
        shell:
            command(PREDICTOR, head=" {rule}")
