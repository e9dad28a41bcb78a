# Raw episodes (the embedded town or your videos) -> shards; pretrained assets.

from orbis2.data.importer import input_files

SOURCE = section("data")["source"]


rule town:
    threads: CPU["threads"]  # one process per core
    resources: **resources_of(CPU)
    input:
        code_inputs("stages/town.py"),
    output:
        raw=directory(P("raw", "town")),
        sheet="reports/town_contact_sheet.png",
        preview="reports/town_preview.mp4",
    params:
        profile=PROFILE,
        data=section("data"),
        town=section("town"),
    log: log("town")
    benchmark: bench("town")
    shell:
        ("python stages/town.py --profile {params.profile} --out {output.raw} --sheet {output.sheet}"
         " --preview {output.preview}" + TEE)


rule import_videos:
    name: "import"
    threads: LIGHT["threads"]
    resources: **resources_of(LIGHT)
    input:
        code_inputs("stages/import.py"),
        *input_files(section("import")["videos"]),  # every video file, so a changed one re-imports
    output:
        raw=directory(P("raw", "import")),
    params:
        profile=PROFILE,
        data=section("data"),
        **{"import": section("import")},
    log: log("import")
    benchmark: bench("import")
    shell:
        "python stages/import.py --profile {params.profile} --out {output.raw}" + TEE


# A checkpoint: the rules that read the shards list its files once it has run (folder_files).
checkpoint shards:
    threads: CPU["threads"]
    resources: **resources_of(CPU)
    input:
        code_inputs("stages/shards.py"),
        raw=P("raw", SOURCE),
    output:
        shards=directory(P("shards")),
    params:
        profile=PROFILE,
        data=section("data"),
        shards=section("shards"),
    log: log("shards")
    benchmark: bench("shards")
    shell:
        "python stages/shards.py --profile {params.profile} --raw {input.raw} --out {output.shards}" + TEE


rule assets:
    threads: LIGHT["threads"]
    resources: **resources_of(LIGHT)
    input:
        code_inputs("stages/assets.py"),
    output:
        assets=directory(P("assets")),
    params:
        profile=PROFILE,
        assets=section("assets"),
    log: log("assets")
    benchmark: bench("assets")
    shell:
        "python stages/assets.py --profile {params.profile} --out {output.assets}" + TEE
