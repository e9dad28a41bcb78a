# Evaluation: FVD of every system, linear probes of every probe target, the inverse-dynamics
# instrument, steering, speed, conditioning diagnostics.

from orbis2.eval.conditioning import scope_predictors

# The hierarchy's bottom predictor under the steered top one (registry.yaml's `steering: true`).
STEERING_PREDICTORS = [REG.systems["hierarchical"].bottom, REG.steered]
# Per report scope (main, all): the suffix of the eval_speed and eval_conditioning rules and records.
SCOPE_SUFFIX = {"main": "", "all": "_all"}


def speed_predictors(scope):
    """Every predictor of the systems eval_speed{,_all} times (Registry.timed_systems)."""
    systems = REG.timed_systems(scope).values()
    return sorted({p for system in systems for p in system.stages})

for system_name, system in REG.systems.items():

    rule:
        name: f"eval_fvd_{system_name}"
        threads: GPU["threads"]
        resources: **resources_of(GPU)
        input:
            code_inputs("stages/eval_fvd.py"),
            **latent_inputs(system.latents),
            **shard_inputs(),
            assets=rules.assets.output.assets,
            **predictor_inputs(system.stages),
        output:
            fvd=P("fvd", system_name),
            media=directory(P("media", system_name)),
        params:
            profile=PROFILE,
            data=section("data"),
            assets=section("assets"),
            evaluation=section("evaluation"),
            args=predictor_args(system.stages),  # see named_args
        log: log(f"eval_fvd_{system_name}")
        benchmark: bench(f"eval_fvd_{system_name}")
        shell:
            ("python stages/eval_fvd.py {rule} --profile {params.profile}" + LATENT_ARGS
             + " --shards {input.shards} --assets {input.assets}{params.args}"
             + " --fvd {output.fvd} --media {output.media}" + TEE)


for target in REG.probe_targets:
    representation = REG.representations.get(target)
    teacher = representation is not None and representation.teacher
    own_predictor = [target] if representation is None else []  # a predictor target: its own folder

    rule:
        name: f"eval_probe_{target}"
        # A frozen network's features and small heads: little memory, but every core. The main target's
        # single probe would otherwise run last and alone on one thread (1.8x slower on 2 cores);
        # reports/all's probes queue instead of sharing, at the same throughput.
        threads: CPU["threads"]
        resources: **resources_of(LIGHT)
        input:
            code_inputs("stages/eval_probe.py"),
            **shard_inputs(),
            **tokenizer_inputs(REG.target_latents(target)),
            **({"assets": rules.assets.output.assets} if teacher else {}),
            **predictor_inputs(own_predictor),
        output:
            probe=P("probe", target),
        params:
            profile=PROFILE,
            data=section("data"),
            evaluation=section("evaluation"),
            args=(f" --assets {rules.assets.output.assets}" if teacher else "") + predictor_args(own_predictor),
        log: log(f"eval_probe_{target}")
        benchmark: bench(f"eval_probe_{target}")
        shell:
            ("python stages/eval_probe.py {rule} --profile {params.profile} --shards {input.shards}" + TOKENIZER_ARGS
             + "{params.args} --out {output.probe}" + TEE)


rule inverse_dynamics:
    threads: GPU["threads"]  # trains a CNN on dense optical flow
    resources: **resources_of(GPU)
    input:
        code_inputs("stages/inverse_dynamics.py"),
        **shard_inputs(),
        tokenizer=P("tokenizer", "detail"),
    output:
        weights=directory(P("inverse_dynamics")),  # trained: its curves/loss.png is one of dvc.yaml's plots
        report=P("report", "inverse_dynamics"),
    params:
        profile=PROFILE,
        data=section("data"),
        inverse_dynamics=section("inverse_dynamics"),
    log: log("inverse_dynamics")
    benchmark: bench("inverse_dynamics")
    shell:
        ("python stages/inverse_dynamics.py --profile {params.profile} --shards {input.shards}"
         " --tokenizer {input.tokenizer} --out {output.weights} --report {output.report}" + TEE)


rule eval_steering:
    threads: GPU["threads"]
    resources: **resources_of(GPU)
    input:
        code_inputs("stages/eval_steering.py"),
        **latent_inputs("compressed"),
        **shard_inputs(),
        **predictor_inputs(STEERING_PREDICTORS),
        inverse_dynamics=rules.inverse_dynamics.output.weights,
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
        ("python stages/eval_steering.py --profile {params.profile}" + LATENT_ARGS + " --shards {input.shards}"
         + predictor_args(STEERING_PREDICTORS) + " --inverse-dynamics {input.inverse_dynamics}"
         " --out {output.steering} --strip {output.strip}" + TEE)


for scope, suffix in SCOPE_SUFFIX.items():

    rule:
        name: f"eval_speed{suffix}"
        threads: GPU["threads"]  # timings need the machine to themselves
        resources: **resources_of(GPU)
        input:
            code_inputs("stages/eval_speed.py"),
            **latent_inputs("compressed"),
            **predictor_inputs(speed_predictors(scope)),
        output:
            speed=P("eval") + f"/speed{suffix}.json",
        params:
            profile=PROFILE,
            data=section("data"),
            evaluation=section("evaluation"),
            args=scope + predictor_args(speed_predictors(scope)),  # set now: the shell runs after the loop
        log: log(f"eval_speed{suffix}")
        benchmark: bench(f"eval_speed{suffix}")
        shell:
            ("python stages/eval_speed.py {params.args} --profile {params.profile}" + LATENT_ARGS
             + " --out {output.speed}" + TEE)

    rule:
        name: f"eval_conditioning{suffix}"
        threads: GPU["threads"]  # batched forward passes of every predictor of the scope
        resources: **resources_of(GPU)
        input:
            code_inputs("stages/eval_conditioning.py"),
            **latent_inputs("compressed"),  # the cache's tokenizers: a retrained one re-runs the stage
            **predictor_inputs(scope_predictors(scope)),
        output:
            conditioning=P("eval") + f"/conditioning{suffix}.json",
        params:
            profile=PROFILE,
            data=section("data"),
            evaluation=section("evaluation"),
            args=scope + predictor_args(scope_predictors(scope)),  # set now: the shell runs after the loop
        log: log(f"eval_conditioning{suffix}")
        benchmark: bench(f"eval_conditioning{suffix}")
        shell:
            ("python stages/eval_conditioning.py {params.args} --profile {params.profile} --latents {input.latents}"
             + " --out {output.conditioning}" + TEE)
