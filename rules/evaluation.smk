# Evaluation: FVD of every system, linear probes of every probe target, steering, speed.

MAIN_SYSTEMS = list(REG.main_table)

for system_name, system in REG.systems.items():

    rule:
        name: f"eval_fvd_{system_name}"
        threads: GPU["threads"]
        resources: **resources_of(GPU)
        input:
            code_inputs("stages/eval_fvd.py"),
            *latent_inputs(system.latents),
            rules.shards.output.shards,
            rules.assets.output.assets,
            *[P("predictor", stage) for stage in system.stages],
        output:
            fvd=P("fvd", system_name),
            media=directory(P("media", system_name)),
        params:
            profile=PROFILE,
            data=section("data"),
            assets=section("assets"),
            evaluation=section("evaluation"),
        log: log(f"eval_fvd_{system_name}")
        benchmark: bench(f"eval_fvd_{system_name}")
        shell:
            "python stages/eval_fvd.py {rule} --profile {params.profile}" + TEE


for target in REG.probe_targets:
    representation = REG.representations.get(target)

    rule:
        name: f"eval_probe_{target}"
        threads: LIGHT["threads"]  # a frozen network's features and a 1x1 conv; several run side by side
        resources: **resources_of(LIGHT)
        input:
            code_inputs("stages/eval_probe.py"),
            rules.shards.output.shards,
            *latent_inputs(REG.target_latents(target))[1:],
            *([rules.assets.output.assets] if representation is not None and representation.teacher else []),
            *([P("predictor", target)] if representation is None else []),
        output:
            probe=P("probe", target),
        params:
            profile=PROFILE,
            data=section("data"),
            evaluation=section("evaluation"),
        log: log(f"eval_probe_{target}")
        benchmark: bench(f"eval_probe_{target}")
        shell:
            "python stages/eval_probe.py {rule} --profile {params.profile}" + TEE


rule eval_steering:
    threads: GPU["threads"]
    resources: **resources_of(GPU)
    input:
        code_inputs("stages/eval_steering.py"),
        *latent_inputs("compressed"),
        rules.shards.output.shards,
        P("predictor", "detail"),
        P("predictor", "action"),
    output:
        steering=P("eval") + "/steering.json",
        strip=P("eval") + "/steering_strip.png",
    params:
        profile=PROFILE,
        data=section("data"),
        town=section("town"),
        evaluation=section("evaluation"),
    log: log("eval_steering")
    benchmark: bench("eval_steering")
    shell:
        "python stages/eval_steering.py --profile {params.profile}" + TEE


rule eval_speed:
    threads: GPU["threads"]  # timings need the machine to themselves
    resources: **resources_of(GPU)
    input:
        code_inputs("stages/eval_speed.py"),
        *latent_inputs("compressed"),
        *sorted({P("predictor", s) for name in MAIN_SYSTEMS for s in REG.systems[name].stages}),
    output:
        speed=P("eval") + "/speed.json",
    params:
        profile=PROFILE,
        data=section("data"),
        evaluation=section("evaluation"),
    log: log("eval_speed")
    benchmark: bench("eval_speed")
    shell:
        "python stages/eval_speed.py --profile {params.profile}" + TEE
