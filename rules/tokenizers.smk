# The tokenizers (one rule per registry.yaml entry) and the latent caches they write (in parts, then a gather).
# Rules made in a loop pass per-rule values through {rule}, {params.*}, {input.*} and
# {output.*}: Snakemake fills a shell command's {...} when the job runs, after the loop
# has moved on, so a loop variable named inside braces would hold the last entry
# (see the Snakefile's _passed_from).

from orbis2.interfaces import GPU_PART
from orbis2.tasks.official import imported_tokenizer, replaced_tokenizers

TOKENIZER_KINDS = {kind: INTERFACES[f"tokenizer_{kind}"] for kind in ("detail", "abstract")}
# One command for both kinds, the script a param: their path options are the same.
assert len({stage.paths for stage in TOKENIZER_KINDS.values()}) == 1, "tokenizer kinds' path options differ"
TOKENIZER_SHELL = command(TOKENIZER_KINDS["detail"], head=" {rule}", script="{params.script}")
LATENTS = INTERFACES["latents"]
# A latents part's command: the gather's without its output (the part writes into data/runs/ and its manifest).
LATENT_PART_SHELL = (f"python {LATENTS.script} {{params.stage}} --profile {{params.profile}} --shards {{input.shards}}"
                     " --detail-tokenizer {input.detail_tokenizer} --abstract-tokenizer {input.abstract_tokenizer}"
                     " --parts {config[parts]}{params.args} 2>&1 | tee {log}")

for tokenizer, kind in REG.tokenizers.items():
    stage = TOKENIZER_KINDS[kind]
    paths = stage_paths(stage, tokenizer)
    # params.yaml official_weights: the main set's tokenizers publish the imported ones (orbis2.tasks.official)
    official = (official_setting(imported_tokenizer(config["official_weights"], tokenizer))
                if tokenizer in replaced_tokenizers() else ({}, {}))

    rule:
        name: f"tokenizer_{tokenizer}"
        threads: stage.resources.threads
        priority: stage.priority
        resources: **resources_of(stage)
        input:
            code_inputs(stage.script),
            **inputs(stage, paths),
            **official[0],
        output:
            **outputs(stage, paths),
        params:
            **stage_params(stage, paths, [f"tokenizer_{tokenizer}"], script=stage.script, **official[1]),
        log: log(f"tokenizer_{tokenizer}")
        benchmark: bench(f"tokenizer_{tokenizer}")
        shell:
            TOKENIZER_SHELL


def latent_part_manifests(stage):
    """The part manifests a latent set's gather waits on (a function: DVC's stage encodes every part itself)."""
    return lambda wildcards: [P("latent_parts", f"{stage}/{part}") for part in PARTS]


# Per latent set: one job per part of the shards (an array of GPU jobs on Slurm): part I of N encodes the I-th block
# of each split's shards into data/runs/ (resumable per shard) and writes its part manifest; then the gather, a
# checkpoint like `shards` (the rules that read a cache list its files, folder_files), which with every part
# encoded only moves their chunks into the cache and writes its tables. The parts are Snakemake's only: DVC's stage
# encodes every part itself. The part's stage name travels in params.stage (see the Snakefile's _passed_from).
for latent_set, entry in REG.latent_sets.items():
    paths = stage_paths(LATENTS, entry.stage, **{k: v for k, v in latent_paths(latent_set).items() if k != "latents"})

    rule:
        name: f"{entry.stage}_part"
        threads: GPU_PART.threads
        priority: LATENTS.priority
        resources: **requests(GPU_PART.scheduler(), lambda: workflow.local_exec)
        input:
            code_inputs(LATENTS.script),
            **inputs(LATENTS, paths),
        output:
            part=P("latent_parts", f"{entry.stage}/{{part}}"),
        wildcard_constraints:
            part=r"\d{4}-of-\d{4}",
        params:
            **stage_params(LATENTS, paths),
            stage=entry.stage,
            args=lambda wildcards, output: f" --part {int(wildcards.part[:4])} --part-manifest {output.part}",
        log: log(f"{entry.stage}_part_{{part}}")
        benchmark: bench(f"{entry.stage}_part_{{part}}")
        shell:
            LATENT_PART_SHELL

    checkpoint:
        name: entry.stage
        threads: LATENTS.resources.threads
        priority: LATENTS.priority
        resources: **resources_of(LATENTS)
        input:
            code_inputs(LATENTS.script),
            **inputs(LATENTS, paths),
            parts=latent_part_manifests(entry.stage),
        output:
            **outputs(LATENTS, paths),
        params:
            **stage_params(LATENTS, paths),
            parts=config["parts"],
        log: log(entry.stage)
        benchmark: bench(entry.stage)
        shell:
            command(LATENTS, head=" {rule} --parts {config[parts]}")
