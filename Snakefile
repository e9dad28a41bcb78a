# The pipeline DAG for Snakemake. dvc.yaml describes the same DAG for DVC; a test
# fails if the two drift (stage names, commands, inputs, outputs, params).
#
#   snakemake --cores 2                       # everything built so far, profile from params.yaml
#   snakemake --cores 2 --config profile=smoke
#
# Each rule's `params` are the params.yaml sections the stage reads (resolved for
# the profile), so changing them re-runs that stage and its dependents only.

from orbis2.config import resolve_section

configfile: "params.yaml"

PROFILE = config["profile"]
SOURCE = resolve_section(config, "data", PROFILE)["source"]


def section(name):
    return resolve_section(config, name, PROFILE)


rule all:
    input:
        "data/shards",


rule town:
    input:
        "stages/town.py",
        "src/orbis2/data/town.py",
        "src/orbis2/data/town_dataset.py",
    output:
        directory("data/raw/town"),
        "reports/town_contact_sheet.png",
        "reports/town_preview.mp4",
    params:
        profile=PROFILE,
        data=section("data"),
        town=section("town"),
    shell:
        "python stages/town.py --profile {params.profile}"


rule import_videos:
    name: "import"
    input:
        "stages/import.py",
        "src/orbis2/data/importer.py",
        section("import")["videos"],
    output:
        directory("data/raw/import"),
    params:
        profile=PROFILE,
        data=section("data"),
        **{"import": section("import")},
    shell:
        "python stages/import.py --profile {params.profile}"


rule shards:
    input:
        "stages/shards.py",
        "src/orbis2/data/shards.py",
        f"data/raw/{SOURCE}",
    output:
        directory("data/shards"),
    params:
        profile=PROFILE,
        data=section("data"),
        shards=section("shards"),
    shell:
        "python stages/shards.py --profile {params.profile}"
