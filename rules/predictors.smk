# Every predictor of registry.yaml, main and ablation: the same stage script given
# the predictor's name and its params.yaml section; its init_from adds the weights
# it starts from as an input.

for predictor, spec in REG.predictors.items():
    init_from = section(predictor).get("init_from")

    rule:
        name: predictor
        threads: TRAIN["threads"]
        resources: **resources_of(TRAIN)
        input:
            code_inputs("stages/predictor.py"),
            **latent_inputs(spec.latents),
            **({"init": P("predictor", init_from)} if init_from else {}),
        output:
            weights=directory(P("predictor", predictor)),
            report=P("report", predictor),
        params:
            profile=PROFILE,
            data=section("data"),
            **{predictor: section(predictor)},
            spec=dataclasses.asdict(spec),  # registry.yaml's entry: a changed spec re-runs the predictor
            args=f" --init {P('predictor', init_from)}" if init_from else "",  # see named_args
        log: log(predictor)
        benchmark: bench(predictor)
        shell:
            ("{config[train_launcher]} stages/predictor.py {rule} --profile {params.profile}" + LATENT_ARGS
             + "{params.args} --out {output.weights} --report {output.report}"
             + TEE)
