# The pipeline DAG for Snakemake. dvc.yaml describes the same DAG for DVC; a test
# fails if the two drift (stage names, commands, inputs, outputs, params).
#
#   snakemake --cores 2                       # everything built so far, profile from params.yaml
#   snakemake --cores 2 --config profile=smoke
#
# Each rule's `params` are the params.yaml sections the stage reads (resolved for
# the profile), so changing them re-runs that stage and its dependents only.

import os
import uuid

from orbis2.config import load_params, resolve_section
from orbis2.data.importer import input_files
from orbis2.eval.conditioning import MAIN_PREDICTORS as CONDITIONING_PREDICTORS
from orbis2.eval.stages import probe_targets
from orbis2.eval.systems import MAIN_SYSTEMS, SPEED_SYSTEMS, SYSTEMS
from orbis2.latents import LATENT_SETS
from orbis2.tasks.predictors import STAGES


def latent_inputs(name):
    """The cache folder and tokenizer folders of a LATENT_SETS entry."""
    latents = LATENT_SETS[name]
    return [str(latents.root), *(str(path.parent) for path in latents.tokenizers.values())]

configfile: "params.yaml"
load_params("params.yaml")  # Snakemake's reader lets a key given twice pass; ours stops

# One id per invocation, inherited by every job (on Slurm via sbatch --export=ALL): the MLflow parent run.
os.environ.setdefault("ORBIS2_PIPELINE_ID", f"snakemake:{uuid.uuid4()}")
envvars: "ORBIS2_PIPELINE_ID"

PROFILE = config["profile"]
# How training stages start: plain python, or e.g. "torchrun --standalone --nproc_per_node 8".
TRAIN_LAUNCHER = config.get("train_launcher", "python")
SOURCE = resolve_section(config, "data", PROFILE)["source"]


def section(name):
    return resolve_section(config, name, PROFILE)


rule all:
    input:
        "reports/main_table.csv",


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
        *input_files(section("import")["videos"]),
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


rule tokenizer_abstract_full:
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
        directory("data/tokenizers/abstract_full"),
        "reports/tokenizer_abstract_full.json",
    params:
        profile=PROFILE,
        data=section("data"),
        tokenizer_abstract_full=section("tokenizer_abstract_full"),
    shell:
        f"{TRAIN_LAUNCHER} stages/tokenizer_abstract.py tokenizer_abstract_full --profile {{params.profile}}"


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


rule latents_full:
    threads: workflow.cores  # uses every core itself; run nothing beside it
    input:
        "stages/latents.py",
        "src/orbis2/latents.py",
        "data/shards",
        "data/tokenizers/detail",
        "data/tokenizers/abstract_full",
    output:
        directory("data/latents_full"),
    params:
        profile=PROFILE,
        data=section("data"),
        latents=section("latents"),
    shell:
        "python stages/latents.py latents_full --profile {params.profile}"


# Every predictor, main and ablation, is one stage script given the predictor's
# name; its init_from (params.yaml) adds the weights it starts from as an input.
# Rules made in a loop pass their name through {rule}: a shell command reads loop
# variables only when it runs, after the loop has moved on.
PREDICTOR_CODE = ["stages/predictor.py", "src/orbis2/tasks/predictors.py", "src/orbis2/models/stdit.py",
                  "src/orbis2/flow.py", "src/orbis2/train.py"]

for predictor in STAGES:
    init_from = section(predictor).get("init_from")

    rule:
        name: predictor
        threads: workflow.cores  # uses every core itself; run nothing beside it
        input:
            *PREDICTOR_CODE,
            *latent_inputs(STAGES[predictor].latents),
            *([f"data/predictors/{init_from}"] if init_from else []),
        output:
            directory(f"data/predictors/{predictor}"),
            f"reports/{predictor}.json",
        params:
            profile=PROFILE,
            data=section("data"),
            **{predictor: section(predictor)},
        shell:
            f"{TRAIN_LAUNCHER} stages/predictor.py {{rule}} --profile {{params.profile}}"


# --------------------------------------------------------------------------- evaluation and reports

EVAL_CODE = ["src/orbis2/eval/stages.py", "src/orbis2/eval/systems.py", "src/orbis2/rollout.py"]
TOKENIZER_DIRS = ["data/tokenizers/detail", "data/tokenizers/abstract"]
MAIN_PROBES = ["abstract_tf", "flat_detail", "flat_abstract"]

for system in SYSTEMS:

    rule:
        name: f"eval_fvd_{system}"
        threads: workflow.cores  # uses every core itself; run nothing beside it
        input:
            "stages/eval_fvd.py",
            *EVAL_CODE,
            "src/orbis2/eval/fvd.py",
            "src/orbis2/eval/references.py",
            "src/orbis2/eval/stats.py",
            *latent_inputs(SYSTEMS[system].latents),
            "data/shards",
            "data/assets",
            *[f"data/predictors/{stage}" for stage in SYSTEMS[system].stages],
        output:
            f"reports/eval/fvd_{system}.json",
            directory(f"reports/eval/media/{system}"),
        params:
            profile=PROFILE,
            data=section("data"),
            assets=section("assets"),
            evaluation=section("evaluation"),
        shell:
            "python stages/eval_fvd.py {rule} --profile {params.profile}"


for target in probe_targets():

    rule:
        name: f"eval_probe_{target}"
        threads: 1  # light: a frozen network's features and a 1x1 conv; two run side by side
        input:
            "stages/eval_probe.py",
            "src/orbis2/eval/stages.py",
            "src/orbis2/eval/probe.py",
            "src/orbis2/data/probes.py",
            "data/shards",
            *(latent_inputs("full" if target.endswith("_full") else "compressed")[1:]),
            *(["data/assets"] if target == "teacher" else []),
            *([f"data/predictors/{target}"] if target in STAGES else []),
        output:
            f"reports/eval/probe_{target}.json",
        params:
            profile=PROFILE,
            data=section("data"),
            evaluation=section("evaluation"),
        shell:
            "python stages/eval_probe.py {rule} --profile {params.profile}"


rule inverse_dynamics:
    threads: workflow.cores  # trains a CNN; run nothing beside it
    input:
        "stages/inverse_dynamics.py",
        "src/orbis2/eval/inverse_dynamics.py",
        "src/orbis2/models/inverse_dynamics.py",
        "data/shards",
        "data/tokenizers/detail",
    output:
        directory("data/inverse_dynamics"),
        "reports/inverse_dynamics.json",
    params:
        profile=PROFILE,
        data=section("data"),
        inverse_dynamics=section("inverse_dynamics"),
    shell:
        "python stages/inverse_dynamics.py --profile {params.profile}"


rule eval_steering:
    threads: workflow.cores  # uses every core itself; run nothing beside it
    input:
        "stages/eval_steering.py",
        *EVAL_CODE,
        "src/orbis2/eval/odometry.py",
        "src/orbis2/eval/stats.py",
        "data/latents",
        "data/shards",
        *TOKENIZER_DIRS,
        "data/predictors/detail",
        "data/predictors/action",
        "data/inverse_dynamics",
    output:
        "reports/eval/steering.json",
        "reports/eval/steering_strip.png",
    params:
        profile=PROFILE,
        data=section("data"),
        town=section("town"),
        evaluation=section("evaluation"),
    shell:
        "python stages/eval_steering.py --profile {params.profile}"


rule eval_speed:
    threads: workflow.cores  # timings need the machine to themselves
    input:
        "stages/eval_speed.py",
        *EVAL_CODE,
        "src/orbis2/eval/speed.py",
        "data/latents",
        *TOKENIZER_DIRS,
        *sorted({f"data/predictors/{s}" for system in [*(SYSTEMS[n] for n in MAIN_SYSTEMS), *SPEED_SYSTEMS.values()]
                 for s in system.stages}),
    output:
        "reports/eval/speed.json",
    params:
        profile=PROFILE,
        data=section("data"),
        evaluation=section("evaluation"),
    shell:
        "python stages/eval_speed.py --profile {params.profile}"


rule eval_conditioning:
    threads: workflow.cores  # batched forward passes of every main predictor
    input:
        "stages/eval_conditioning.py",
        "src/orbis2/eval/conditioning.py",
        "src/orbis2/eval/stats.py",
        "data/latents",
        *TOKENIZER_DIRS,
        *[f"data/predictors/{stage}" for stage in CONDITIONING_PREDICTORS],
    output:
        "reports/eval/conditioning.json",
    params:
        profile=PROFILE,
        data=section("data"),
        evaluation=section("evaluation"),
    shell:
        "python stages/eval_conditioning.py --profile {params.profile}"


rule report_main:
    input:
        "stages/report.py",
        "src/orbis2/eval/report.py",
        *[f"reports/eval/fvd_{name}.json" for name in MAIN_SYSTEMS],
        *[f"reports/eval/probe_{target}.json" for target in MAIN_PROBES],
        "reports/eval/steering.json",
        "reports/eval/speed.json",
        "reports/eval/conditioning.json",
    output:
        "reports/main_table.csv",
        "reports/steering.csv",
        "reports/speed.csv",
        "reports/conditioning.csv",
        "reports/summary.md",
    params:
        profile=PROFILE,
        data=section("data"),
        evaluation=section("evaluation"),
    shell:
        "python stages/report.py main --profile {params.profile}"


rule report_all:
    input:
        "stages/report.py",
        "src/orbis2/eval/report.py",
        *[f"reports/eval/fvd_{name}.json" for name in SYSTEMS],
        *[f"reports/eval/media/{name}" for name in SYSTEMS],
        *[f"reports/eval/probe_{target}.json" for target in probe_targets()],
        "reports/eval/steering.json",
        "reports/eval/steering_strip.png",
        "reports/eval/speed.json",
        "reports/eval/conditioning.json",
    output:
        directory("reports/all"),
    params:
        profile=PROFILE,
        data=section("data"),
        evaluation=section("evaluation"),
    shell:
        "python stages/report.py all --profile {params.profile}"
