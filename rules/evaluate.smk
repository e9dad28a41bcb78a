# Any model's rollouts, scored as `orbis2 evaluate` scores them (docs/evaluate.md):
#   snakemake --cores 2 reports/evaluate/<name>/fvd.json     # reads data/rollouts/<name>/
# A rule with a wildcard, so Snakemake only: dvc.yaml's stages are fixed (orbis2.dag leaves it out).

from orbis2.errors import OrbisError


def rollouts_of(wildcards):
    """The folder read as the stage reads it; None when the stage will say what is wrong with it."""
    from orbis2.eval.protocols.evaluate_videos import read_rollout_folder  # imports torch: only for these targets

    try:
        return read_rollout_folder(Path(P("rollouts", wildcards.name)))
    except OrbisError:
        return None


def rollout_files(wildcards):
    """Every file the score reads, so that a changed or added video re-runs it."""
    rollouts = rollouts_of(wildcards)
    return [str(f) for f in rollouts.files()] if rollouts is not None else []


def instrument_input(wildcards):
    """The learned steering instrument, when it reads the rollouts' trajectories."""
    rollouts = rollouts_of(wildcards)
    wanted = rollouts is not None and rollouts.options["instrument"] == "learned" and any(
        p.trajectory for p in rollouts.pairs)
    return [rules.inverse_dynamics.output.weights] if wanted else []


EVALUATE = INTERFACES["evaluate"]
EVALUATE_PATHS = stage_paths(EVALUATE, "{name}")


def evaluate_args(wildcards, input, output):
    """The options from --instrument on (the instrument only when the rollouts need it)."""
    return shell_args(EVALUATE, {"instrument": str(input.instrument) if input.instrument else None,
                                 **{key: getattr(output, key) for key in ("fvd", "table", "figure")}})


rule evaluate:
    threads: EVALUATE.resources.threads
    priority: EVALUATE.priority
    resources: **resources_of(EVALUATE)
    wildcard_constraints:
        name=r"[^/]+",
    input:
        code_inputs(EVALUATE.script),
        **inputs(EVALUATE, EVALUATE_PATHS),
        rollout_files=rollout_files,
        instrument=instrument_input,
    output:
        **outputs(EVALUATE, EVALUATE_PATHS),
    params:
        **stage_params(EVALUATE, EVALUATE_PATHS, args=evaluate_args),
    log: log("evaluate_{name}")
    benchmark: bench("evaluate_{name}")
    shell:
        command(EVALUATE)
