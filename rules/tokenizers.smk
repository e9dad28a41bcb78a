# The tokenizers (one rule per registry.yaml entry) and the latent caches they write.
# Rules made in a loop pass per-rule values through {rule}, {params.*}, {input.*} and
# {output.*}: Snakemake fills a shell command's {...} when the job runs, after the loop
# has moved on, so a loop variable named inside braces would hold the last entry
# (see the Snakefile's _passed_from).

TOKENIZER_KINDS = {kind: INTERFACES[f"tokenizer_{kind}"] for kind in ("detail", "abstract")}
# One command for both kinds, the script a param: their path options are the same.
assert len({stage.paths for stage in TOKENIZER_KINDS.values()}) == 1, "tokenizer kinds' path options differ"
TOKENIZER_SHELL = command(TOKENIZER_KINDS["detail"], head=" {rule}", script="{params.script}")
LATENTS = INTERFACES["latents"]

for tokenizer, kind in REG.tokenizers.items():
    stage = TOKENIZER_KINDS[kind]
    paths = stage_paths(stage, tokenizer)

    rule:
        name: f"tokenizer_{tokenizer}"
        threads: stage.resources.threads
        priority: stage.priority
        resources: **resources_of(stage)
        input:
            code_inputs(stage.script),
            **inputs(stage, paths),
        output:
            **outputs(stage, paths),
        params:
            **stage_params(stage, paths, [f"tokenizer_{tokenizer}"], script=stage.script),
        log: log(f"tokenizer_{tokenizer}")
        benchmark: bench(f"tokenizer_{tokenizer}")
        shell:
            TOKENIZER_SHELL


# Checkpoints, like `shards`: the rules that read a cache list its files (folder_files).
for latent_set, entry in REG.latent_sets.items():
    paths = stage_paths(LATENTS, entry.stage, **{k: v for k, v in latent_paths(latent_set).items() if k != "latents"})

    checkpoint:
        name: entry.stage
        threads: LATENTS.resources.threads
        priority: LATENTS.priority
        resources: **resources_of(LATENTS)
        input:
            code_inputs(LATENTS.script),
            **inputs(LATENTS, paths),
        output:
            **outputs(LATENTS, paths),
        params:
            **stage_params(LATENTS, paths),
        log: log(entry.stage)
        benchmark: bench(entry.stage)
        shell:
            command(LATENTS, head=" {rule}")
