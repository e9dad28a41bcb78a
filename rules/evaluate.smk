# Any model's rollouts, scored as `orbis2 evaluate` scores them (docs/evaluate.md):
#   snakemake --cores 2 reports/evaluate/<name>/fvd.json     # reads data/rollouts/<name>/
# A rule with a wildcard, so Snakemake only: dvc.yaml's stages are fixed (orbis2.dag leaves it out).

from orbis2.errors import OrbisError
from orbis2.eval.evaluate_videos import read_rollout_folder


def rollouts_of(wildcards):
    """The folder read as the stage reads it; None when the stage will say what is wrong with it."""
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


rule evaluate:
    threads: GPU["threads"]
    resources: **resources_of(GPU)
    wildcard_constraints:
        name=r"[^/]+",
    input:
        code_inputs("stages/evaluate.py"),
        rollouts=P("rollouts", "{name}"),
        rollout_files=rollout_files,
        assets=rules.assets.output.assets,
        instrument=instrument_input,
    output:
        fvd=f"{P('evaluate', '{name}')}/fvd.json",
        table=f"{P('evaluate', '{name}')}/table.txt",
        figure=f"{P('evaluate', '{name}')}/fvd.png",
    params:
        profile=PROFILE,
        assets=section("assets"),
        evaluation=section("evaluation"),
        town=section("town"),
        args=lambda wildcards, input: f" --instrument {input.instrument}" if input.instrument else "",
    log: log("evaluate_{name}")
    benchmark: bench("evaluate_{name}")
    shell:
        ("python stages/evaluate.py --profile {params.profile} --rollouts {input.rollouts} --assets {input.assets}"
         "{params.args} --fvd {output.fvd} --table {output.table} --figure {output.figure}" + TEE)
