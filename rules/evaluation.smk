# Evaluation: FVD of every system, linear probes of every probe target, the inverse-dynamics
# instrument, steering, speed, conditioning diagnostics.


EVAL_FVD, EVAL_PROBE, INVERSE_DYNAMICS, EVAL_STEERING, EVAL_SPEED, EVAL_CONDITIONING = (INTERFACES[kind] for kind in (
    "eval_fvd", "eval_probe", "inverse_dynamics", "eval_steering", "eval_speed", "eval_conditioning"))
# The hierarchy's bottom predictor under the steered top one (registry.yaml's `steering: true`).
STEERING_PREDICTORS = [REG.systems["hierarchical"].bottom, REG.steered]
# Per report scope (main, all): the suffix of the eval_speed and eval_conditioning rules and records.
SCOPE_SUFFIX = {"main": "", "all": "_all"}


def speed_predictors(scope):
    """Every predictor of the systems eval_speed{,_all} times (Registry.timed_systems)."""
    systems = REG.timed_systems(scope).values()
    return sorted({p for system in systems for p in system.stages})

def eval_part_manifests(system_name):
    """The part manifests a system's FVD gather waits on: none at parts=1, where the gather's one job does it all
    (a function: DVC's stage does every part itself)."""
    return lambda wildcards: [P("eval_parts", f"{system_name}/{part}") for part in PARTS] if len(PARTS) > 1 else []


def part_args(path_args):
    """A part job's options: the rule's paths (set when the rule is defined), then its part and part manifest."""
    return lambda wildcards, output: f"{path_args} --part {int(wildcards.part[:4])} --part-manifest {output.part}"


# Per system: at parts=N > 1, one job per part (an array of GPU jobs on Slurm): part I of N generates, decodes and
# featurises the I-th block of each split's rollout batches into data/runs/ and writes its part manifest; then the
# gather adds the real side and the intervals. The figures do not depend on `parts` (orbis2.eval.protocols.rollout_fvd).
for system_name, system in REG.systems.items():
    paths = stage_paths(EVAL_FVD, system_name, **latent_paths(system.latents), predictor=system.stages)
    part_paths = {key: value for key, value in paths.items() if key not in ("fvd", "media")}

    rule:
        name: f"eval_fvd_{system_name}_part"
        threads: EVAL_FVD.resources.threads
        priority: EVAL_FVD.priority
        resources: **resources_of(EVAL_FVD)
        input:
            code_inputs(EVAL_FVD.script),
            **inputs(EVAL_FVD, part_paths),
        output:
            part=P("eval_parts", f"{system_name}/{{part}}"),
        wildcard_constraints:
            part=r"\d{4}-of-\d{4}",
        params:  # the system as a param: a loop variable in the command would be read when a job step runs it
            **{**stage_params(EVAL_FVD, part_paths), "args": part_args(shell_args(EVAL_FVD, part_paths))},
            scope=system_name,
        log: log(f"eval_fvd_{system_name}_part_{{part}}")
        benchmark: bench(f"eval_fvd_{system_name}_part_{{part}}")
        shell:
            command(EVAL_FVD, head=" {params.scope} --parts {config[parts]}")

    rule:
        name: f"eval_fvd_{system_name}"
        threads: EVAL_FVD.resources.threads
        priority: EVAL_FVD.priority
        resources: **resources_of(EVAL_FVD)
        input:
            code_inputs(EVAL_FVD.script),
            **inputs(EVAL_FVD, paths),
            parts=eval_part_manifests(system_name),
        output:
            **outputs(EVAL_FVD, paths),
        params:
            **stage_params(EVAL_FVD, paths),
            parts=config["parts"],
        log: log(f"eval_fvd_{system_name}")
        benchmark: bench(f"eval_fvd_{system_name}")
        shell:
            command(EVAL_FVD, head=" {rule} --parts {config[parts]}")


for target in REG.probe_targets:
    representation = REG.representations.get(target)
    teacher = representation is not None and representation.teacher
    tokenizers = {k: v for k, v in latent_paths(REG.target_latents(target)).items() if k != "latents"}
    paths = stage_paths(EVAL_PROBE, target, **tokenizers, assets=P("assets") if teacher else None,
                        predictor=[target] if representation is None else [])  # a predictor target: its own folder

    rule:
        name: f"eval_probe_{target}"
        threads: EVAL_PROBE.resources.threads
        priority: EVAL_PROBE.priority
        resources: **resources_of(EVAL_PROBE)
        input:
            code_inputs(EVAL_PROBE.script),
            **inputs(EVAL_PROBE, paths),
        output:
            **outputs(EVAL_PROBE, paths),
        params:
            **stage_params(EVAL_PROBE, paths),
        log: log(f"eval_probe_{target}")
        benchmark: bench(f"eval_probe_{target}")
        shell:
            command(EVAL_PROBE, head=" {rule}")


rule inverse_dynamics:
    threads: INVERSE_DYNAMICS.resources.threads  # trains a CNN on dense optical flow
    priority: INVERSE_DYNAMICS.priority
    resources: **resources_of(INVERSE_DYNAMICS)
    input:
        code_inputs(INVERSE_DYNAMICS.script),
        **inputs(INVERSE_DYNAMICS, stage_paths(INVERSE_DYNAMICS)),
    output:  # trained: weights/curves/loss.png is one of dvc.yaml's plots
        **outputs(INVERSE_DYNAMICS, stage_paths(INVERSE_DYNAMICS)),
    params:
        **stage_params(INVERSE_DYNAMICS, stage_paths(INVERSE_DYNAMICS)),
    log: log("inverse_dynamics")
    benchmark: bench("inverse_dynamics")
    shell:
        command(INVERSE_DYNAMICS)


STEERING_PATHS = stage_paths(EVAL_STEERING, **latent_paths("compressed"), predictor=STEERING_PREDICTORS)


rule eval_steering:
    threads: EVAL_STEERING.resources.threads
    priority: EVAL_STEERING.priority
    resources: **resources_of(EVAL_STEERING)
    input:
        code_inputs(EVAL_STEERING.script),
        **inputs(EVAL_STEERING, STEERING_PATHS),
    output:
        **outputs(EVAL_STEERING, STEERING_PATHS),
    params:
        **stage_params(EVAL_STEERING, STEERING_PATHS),
    log: log("eval_steering")
    benchmark: bench("eval_steering")
    shell:
        command(EVAL_STEERING)


for scope, suffix in SCOPE_SUFFIX.items():
    speed = stage_paths(EVAL_SPEED, **latent_paths("compressed"), predictor=speed_predictors(scope),
                        speed=P("eval") + f"/speed{suffix}.json")
    # The all scope takes the main predictors' rows from the main scope's record (the same bits).
    conditioning = stage_paths(EVAL_CONDITIONING, latents=latent_paths("compressed")["latents"],
                               predictor=REG.conditioning_predictors(scope),
                               main_record=P("eval") + "/conditioning.json" if scope == "all" else None,
                               conditioning=P("eval") + f"/conditioning{suffix}.json")

    rule:
        name: f"eval_speed{suffix}"
        threads: EVAL_SPEED.resources.threads  # timings need the machine to themselves
        priority: EVAL_SPEED.priority
        resources: **resources_of(EVAL_SPEED)
        input:
            code_inputs(EVAL_SPEED.script),
            **inputs(EVAL_SPEED, speed),
        output:
            **outputs(EVAL_SPEED, speed),
        params:
            **stage_params(EVAL_SPEED, speed, scope=scope),
        log: log(f"eval_speed{suffix}")
        benchmark: bench(f"eval_speed{suffix}")
        shell:
            command(EVAL_SPEED, head=" {params.scope}")

    rule:
        name: f"eval_conditioning{suffix}"
        threads: EVAL_CONDITIONING.resources.threads  # batched forward passes of every predictor of the scope
        priority: EVAL_CONDITIONING.priority
        resources: **resources_of(EVAL_CONDITIONING)
        input:
            code_inputs(EVAL_CONDITIONING.script),
            **inputs(EVAL_CONDITIONING, conditioning),
            # the cache's tokenizers, not read by the stage: a retrained one re-runs it
            **{k: v for k, v in latent_paths("compressed").items() if k != "latents"},
        output:
            **outputs(EVAL_CONDITIONING, conditioning),
        params:
            **stage_params(EVAL_CONDITIONING, conditioning, scope=scope),
        log: log(f"eval_conditioning{suffix}")
        benchmark: bench(f"eval_conditioning{suffix}")
        shell:
            command(EVAL_CONDITIONING, head=" {params.scope}")
