# Raw episodes (the embedded town or your videos) -> shards; pretrained assets.

from orbis2.data.importer import input_files

SOURCE = section("data")["source"]
TOWN, IMPORT, SHARDS, ASSETS = (INTERFACES[kind] for kind in ("town", "import", "shards", "assets"))


rule town:
    threads: TOWN.resources.threads  # one process per core
    priority: TOWN.priority
    resources: **resources_of(TOWN)
    input:
        code_inputs(TOWN.script),
    output:
        **outputs(TOWN, stage_paths(TOWN)),
    params:
        **stage_params(TOWN, stage_paths(TOWN)),
    log: log("town")
    benchmark: bench("town")
    shell:
        command(TOWN)


rule import_videos:
    name: "import"
    threads: IMPORT.resources.threads
    priority: IMPORT.priority
    resources: **resources_of(IMPORT)
    input:
        code_inputs(IMPORT.script),
        *input_files(section("import")["videos"]),  # every video file, so a changed one re-imports
    output:
        **outputs(IMPORT, stage_paths(IMPORT)),
    params:
        **stage_params(IMPORT, stage_paths(IMPORT)),
    log: log("import")
    benchmark: bench("import")
    shell:
        command(IMPORT)


# A checkpoint: the rules that read the shards list its files once it has run (folder_files).
checkpoint shards:
    threads: SHARDS.resources.threads
    priority: SHARDS.priority
    resources: **resources_of(SHARDS)
    input:
        code_inputs(SHARDS.script),
        **inputs(SHARDS, stage_paths(SHARDS, SOURCE)),  # the configured source's raw folder
    output:
        **outputs(SHARDS, stage_paths(SHARDS, SOURCE)),
    params:
        **stage_params(SHARDS, stage_paths(SHARDS, SOURCE)),
    log: log("shards")
    benchmark: bench("shards")
    shell:
        command(SHARDS)


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
