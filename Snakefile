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
# How training stages start: plain python, or e.g. "torchrun --standalone --nproc_per_node 8".
TRAIN_LAUNCHER = config.get("train_launcher", "python")
SOURCE = resolve_section(config, "data", PROFILE)["source"]


def section(name):
    return resolve_section(config, name, PROFILE)


rule all:
    input:
        "data/predictors/detail",
        "data/predictors/action",


rule town:
    threads: workflow.cores  # uses every core itself; run nothing beside it
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


rule assets:
    input:
        "stages/assets.py",
        "src/orbis2/assets.py",
    output:
        directory("data/assets"),
    params:
        profile=PROFILE,
        assets=section("assets"),
    shell:
        "python stages/assets.py --profile {params.profile}"


rule tokenizer_detail:
    threads: workflow.cores  # uses every core itself; run nothing beside it
    input:
        "stages/tokenizer_detail.py",
        "src/orbis2/tasks/tokenizers.py",
        "src/orbis2/models/tokenizer.py",
        "src/orbis2/losses.py",
        "src/orbis2/train.py",
        "data/shards",
        "data/assets",
    output:
        directory("data/tokenizers/detail"),
        "reports/tokenizer_detail.json",
    params:
        profile=PROFILE,
        data=section("data"),
        tokenizer_detail=section("tokenizer_detail"),
    shell:
        f"{TRAIN_LAUNCHER} stages/tokenizer_detail.py --profile {{params.profile}}"


rule tokenizer_abstract:
    threads: workflow.cores  # uses every core itself; run nothing beside it
    input:
        "stages/tokenizer_abstract.py",
        "src/orbis2/tasks/tokenizers.py",
        "src/orbis2/models/tokenizer.py",
        "src/orbis2/models/teachers.py",
        "src/orbis2/losses.py",
        "src/orbis2/train.py",
        "data/shards",
        "data/assets",
    output:
        directory("data/tokenizers/abstract"),
        "reports/tokenizer_abstract.json",
    params:
        profile=PROFILE,
        data=section("data"),
        tokenizer_abstract=section("tokenizer_abstract"),
    shell:
        f"{TRAIN_LAUNCHER} stages/tokenizer_abstract.py --profile {{params.profile}}"


rule latents:
    threads: workflow.cores  # uses every core itself; run nothing beside it
    input:
        "stages/latents.py",
        "src/orbis2/latents.py",
        "data/shards",
        "data/tokenizers/detail",
        "data/tokenizers/abstract",
    output:
        directory("data/latents"),
    params:
        profile=PROFILE,
        data=section("data"),
        latents=section("latents"),
    shell:
        "python stages/latents.py --profile {params.profile}"


rule abstract_df:
    threads: workflow.cores  # uses every core itself; run nothing beside it
    input:
        "stages/abstract_df.py",
        "src/orbis2/tasks/predictors.py",
        "src/orbis2/models/stdit.py",
        "src/orbis2/flow.py",
        "src/orbis2/train.py",
        "data/latents",
        "data/tokenizers/detail",
        "data/tokenizers/abstract",
    output:
        directory("data/predictors/abstract_df"),
        "reports/abstract_df.json",
    params:
        profile=PROFILE,
        data=section("data"),
        abstract_df=section("abstract_df"),
    shell:
        f"{TRAIN_LAUNCHER} stages/abstract_df.py --profile {{params.profile}}"


rule abstract_tf:
    threads: workflow.cores  # uses every core itself; run nothing beside it
    input:
        "stages/abstract_tf.py",
        "src/orbis2/tasks/predictors.py",
        "src/orbis2/models/stdit.py",
        "src/orbis2/flow.py",
        "src/orbis2/train.py",
        "data/latents",
        "data/tokenizers/detail",
        "data/tokenizers/abstract",
        "data/predictors/abstract_df",
    output:
        directory("data/predictors/abstract_tf"),
        "reports/abstract_tf.json",
    params:
        profile=PROFILE,
        data=section("data"),
        abstract_tf=section("abstract_tf"),
    shell:
        f"{TRAIN_LAUNCHER} stages/abstract_tf.py --profile {{params.profile}}"


rule detail:
    threads: workflow.cores  # uses every core itself; run nothing beside it
    input:
        "stages/detail.py",
        "src/orbis2/tasks/predictors.py",
        "src/orbis2/models/stdit.py",
        "src/orbis2/flow.py",
        "src/orbis2/train.py",
        "data/latents",
        "data/tokenizers/detail",
        "data/tokenizers/abstract",
    output:
        directory("data/predictors/detail"),
        "reports/detail.json",
    params:
        profile=PROFILE,
        data=section("data"),
        detail=section("detail"),
    shell:
        f"{TRAIN_LAUNCHER} stages/detail.py --profile {{params.profile}}"


rule action:
    threads: workflow.cores  # uses every core itself; run nothing beside it
    input:
        "stages/action.py",
        "src/orbis2/tasks/predictors.py",
        "src/orbis2/models/stdit.py",
        "src/orbis2/flow.py",
        "src/orbis2/train.py",
        "data/latents",
        "data/tokenizers/detail",
        "data/tokenizers/abstract",
        "data/predictors/abstract_tf",
    output:
        directory("data/predictors/action"),
        "reports/action.json",
    params:
        profile=PROFILE,
        data=section("data"),
        action=section("action"),
    shell:
        f"{TRAIN_LAUNCHER} stages/action.py --profile {{params.profile}}"
