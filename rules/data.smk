# Raw episodes (the embedded town or your videos) -> shards; pretrained assets.

from orbis2.data.importer import input_files
from orbis2.data.parts import part_name
from orbis2.interfaces import PART

SOURCE = section("data")["source"]
TOWN, IMPORT, SHARDS, ASSETS = (INTERFACES[kind] for kind in ("town", "import", "shards", "assets"))
PARTS = [part_name(i, config["parts"]) for i in range(config["parts"])]  # params.yaml `parts`, or --config parts=N


# One job per part of the town's episodes (an array on Slurm), rendered into data/runs/ (resumable per episode),
# then the gather with the motion statistics and previews. Snakemake's only: DVC's `town` renders every part itself.
rule town_part:
    threads: TOWN.resources.threads  # one process per core
    priority: TOWN.priority
    resources: **resources_of(TOWN)
    input:
        code_inputs(TOWN.script),
    output:
        part=P("town_parts", "{part}"),
    wildcard_constraints:
        part=r"\d{4}-of-\d{4}",
    params:
        **stage_params(TOWN, stage_paths(TOWN)),
        args=lambda wildcards, output: f" --part {int(wildcards.part[:4])} --part-manifest {output.part}",
    log: log("town_part_{part}")
    benchmark: bench("town_part_{part}")
    shell:
        f"python {TOWN.script} --profile {{params.profile}} --parts {{config[parts]}}{{params.args}} 2>&1 | tee {{log}}"


rule town:
    threads: TOWN.resources.threads
    priority: TOWN.priority
    resources: **resources_of(TOWN)
    input:
        code_inputs(TOWN.script),
        parts=lambda wildcards: [P("town_parts", part) for part in PARTS],  # a function: DVC's stage runs them
    output:
        **outputs(TOWN, stage_paths(TOWN)),
    params:
        **stage_params(TOWN, stage_paths(TOWN)),
        parts=config["parts"],
    log: log("town")
    benchmark: bench("town")
    shell:
        command(TOWN, head=" --parts {config[parts]}")


# One job per part of your videos (an array on Slurm), imported into data/runs/ (resumable per video), then the
# gather. Snakemake's only: DVC's `import` stage imports every part itself.
rule import_part:
    threads: PART.threads
    priority: IMPORT.priority
    resources: **requests(PART.scheduler(), lambda: workflow.local_exec)
    input:
        code_inputs(IMPORT.script),
        *input_files(section("import")["videos"]),  # every video file, so a changed one re-imports
    output:
        part=P("import_parts", "{part}"),
    wildcard_constraints:
        part=r"\d{4}-of-\d{4}",
    params:
        **stage_params(IMPORT, stage_paths(IMPORT)),
        args=lambda wildcards, output: f" --part {int(wildcards.part[:4])} --part-manifest {output.part}",
    log: log("import_part_{part}")
    benchmark: bench("import_part_{part}")
    shell:
        f"python {IMPORT.script} --profile {{params.profile}} --parts {{config[parts]}}{{params.args}} 2>&1 | tee {{log}}"


rule import_videos:
    name: "import"
    threads: IMPORT.resources.threads
    priority: IMPORT.priority
    resources: **resources_of(IMPORT)
    input:
        code_inputs(IMPORT.script),
        *input_files(section("import")["videos"]),  # every video file, so a changed one re-imports
        parts=lambda wildcards: [P("import_parts", part) for part in PARTS],  # a function: DVC's stage runs them
    output:
        **outputs(IMPORT, stage_paths(IMPORT)),
    params:
        **stage_params(IMPORT, stage_paths(IMPORT)),
        parts=config["parts"],
    log: log("import")
    benchmark: bench("import")
    shell:
        command(IMPORT, head=" --parts {config[parts]}")


# One job per part of the shards (an array on Slurm): part I of N writes the I-th block of every split's
# episodes into data/runs/ (resumable) and its part manifest. Snakemake's only: DVC's `shards` runs every part.
rule shards_part:
    threads: PART.threads
    priority: SHARDS.priority
    resources: **requests(PART.scheduler(), lambda: workflow.local_exec)
    input:
        code_inputs(SHARDS.script),
        raw=stage_paths(SHARDS, SOURCE)["raw"],
    output:
        part=P("shard_parts", "{part}"),
    wildcard_constraints:
        part=r"\d{4}-of-\d{4}",
    params:
        **stage_params(SHARDS, stage_paths(SHARDS, SOURCE)),
        args=lambda wildcards, output: f" --part {int(wildcards.part[:4])} --part-manifest {output.part}",
    log: log("shards_part_{part}")
    benchmark: bench("shards_part_{part}")
    shell:
        f"python {SHARDS.script} --profile {{params.profile}} --raw {{input.raw}} --parts {{config[parts]}}"
        "{params.args} 2>&1 | tee {log}"


# A checkpoint: the rules that read the shards list its files once it has run (folder_files). With every part
# written it only gathers them (hard links and the manifest).
checkpoint shards:
    threads: SHARDS.resources.threads
    priority: SHARDS.priority
    resources: **resources_of(SHARDS)
    input:
        code_inputs(SHARDS.script),
        **inputs(SHARDS, stage_paths(SHARDS, SOURCE)),  # the configured source's raw folder
        parts=lambda wildcards: [P("shard_parts", part) for part in PARTS],  # a function: DVC's stage runs them
    output:
        **outputs(SHARDS, stage_paths(SHARDS, SOURCE)),
    params:
        **stage_params(SHARDS, stage_paths(SHARDS, SOURCE)),
        parts=config["parts"],
    log: log("shards")
    benchmark: bench("shards")
    shell:
        command(SHARDS, head=" --parts {config[parts]}")


rule assets:
    threads: ASSETS.resources.threads
    priority: ASSETS.priority
    resources: **resources_of(ASSETS)
    input:
        code_inputs(ASSETS.script),
    output:
        **outputs(ASSETS, stage_paths(ASSETS)),
    params:
        **stage_params(ASSETS, stage_paths(ASSETS)),
    log: log("assets")
    benchmark: bench("assets")
    shell:
        command(ASSETS)
