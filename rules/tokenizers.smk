# The tokenizers (one rule per registry.yaml entry) and the latent caches they write.
# Rules made in a loop pass per-rule values through {rule}, {params.*}, {input.*} and
# {output.*}, or through plain strings built while the loop runs: Snakemake fills a
# shell command's {...} when the job runs, after the loop has moved on, so a loop
# variable named inside braces would hold the last entry.

for tokenizer, kind in REG.tokenizers.items():

    rule:
        name: f"tokenizer_{tokenizer}"
        threads: TRAIN["threads"]
        resources: **resources_of(TRAIN)
        input:
            code_inputs(f"stages/tokenizer_{kind}.py"),
            **shard_inputs(),
            assets=rules.assets.output.assets,
        output:
            weights=directory(P("tokenizer", tokenizer)),
            report=P("report", f"tokenizer_{tokenizer}"),
        params:
            profile=PROFILE,
            script=f"stages/tokenizer_{kind}.py",  # a param: the command is formatted when it runs
            data=section("data"),
            **{f"tokenizer_{tokenizer}": section(f"tokenizer_{tokenizer}")},
        log: log(f"tokenizer_{tokenizer}")
        benchmark: bench(f"tokenizer_{tokenizer}")
        shell:
            ("{config[train_launcher]} {params.script} {rule} --profile {params.profile} --shards {input.shards}"
             " --assets {input.assets} --out {output.weights} --report {output.report}" + TEE)


# Checkpoints, like `shards`: the rules that read a cache list its files (folder_files).
for latent_set, entry in REG.latent_sets.items():

    checkpoint:
        name: entry.stage
        threads: GPU["threads"]
        resources: **resources_of(GPU)
        input:
            code_inputs("stages/latents.py"),
            **shard_inputs(),
            **tokenizer_inputs(latent_set),
        output:
            latents=directory(P("latents", entry.stage)),
        params:
            profile=PROFILE,
            data=section("data"),
            latents=section("latents"),
        log: log(entry.stage)
        benchmark: bench(entry.stage)
        shell:
            ("python stages/latents.py {rule} --profile {params.profile} --shards {input.shards}" + TOKENIZER_ARGS
             + " --out {output.latents}" + TEE)
