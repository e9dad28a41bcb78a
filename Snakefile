# The pipeline DAG. Rules live in rules/*.smk; what they are made of (tokenizers,
# latent sets, predictors, systems, probe targets, the main table) in registry.yaml,
# every hyper-parameter in params.yaml (checked by the typed config, orbis2.config,
# when this file is read, so a typo fails here). dvc.yaml is generated
# from these rules: `python -m orbis2.dag` (a test fails when it is stale).
#
#   snakemake --cores 2                       # main table, profile from params.yaml
#   snakemake --cores 2 reports/all --config profile=smoke
#
# Each rule's `params` are the params.yaml sections the stage reads (resolved for
# the profile), so changing them re-runs that stage and its dependents only; its
# code inputs are the stage script and the modules it imports. Logs go to logs/,
# wall times and memory to logs/benchmarks/<rule>.tsv.

import dataclasses
import os
import sys
import uuid
from pathlib import Path

from orbis2.config.params import load_params, parse_config, resolve_section
from orbis2.dag import code_inputs, commit_to_dvc, config_drift
from orbis2.registry import layout_path, registry

configfile: "params.yaml"
FILE_PROFILE = load_params("params.yaml")["profile"]  # Snakemake's reader lets a key given twice pass; ours stops

# One id per invocation, inherited by every job (on Slurm via sbatch --export=ALL): the MLflow parent run.
os.environ.setdefault("ORBIS2_PIPELINE_ID", f"snakemake:{uuid.uuid4()}")
envvars: "ORBIS2_PIPELINE_ID"

DVC_DRIFT = config_drift(config)  # the keys DVC cannot see
PROFILE = config["profile"]
if PROFILE != FILE_PROFILE:  # DVC reads params.yaml only: say where its views and this run part ways
    print(f"profile {PROFILE} (--config); params.yaml says {FILE_PROFILE}, which is what `dvc params diff`, "
          f"`dvc exp show` and `dvc status` read. MLflow records {PROFILE}. To let DVC see this run, set "
          f"`profile: {PROFILE}` in params.yaml instead (docs/tracking.md).", file=sys.stderr)
parse_config(config, PROFILE)  # every key, type and value, and the file's shape; errors name the key
REG = registry()


def section(name):
    return resolve_section(config, name, PROFILE)


def P(kind, name=None):
    """A path from registry.yaml's layout."""
    return str(layout_path(kind, name))


# Every stage gets its input and output paths as options, from its rule's named inputs and outputs
# ({input.shards}, {output.report}, ...): the rules decide where files live; a stage run by hand
# without them falls back on the same layout. The helpers below name the inputs shared by many rules
# and write the options that pass them.


def tokenizer_inputs(latent_set):
    """The folders of a latent set's tokenizers: inputs detail_tokenizer, abstract_tokenizer."""
    entry = REG.latent_sets[latent_set]
    return {f"{level}_tokenizer": P("tokenizer", entry.tokenizers[level]) for level in ("detail", "abstract")}


def folder_files(stage):
    """Every file in a checkpoint rule's output folder (input files of the rules that read it).

    Snakemake dates a folder by the folder itself, so a shard or cache array changed in place
    would go unseen; as files, a changed one is newer than what was made from it and re-runs
    that rule, whose stage then verifies it. Listed once the checkpoint has run, so the first
    run already records the full list. dvc.yaml leaves these out: DVC hashes the folder's content.
    """
    return lambda wildcards: sorted(str(f) for f in Path(getattr(checkpoints, stage).get().output[0]).rglob("*")
                                    if f.is_file())


def shard_inputs():
    """The shards folder (input shards) and every file in it."""
    return {"shards": P("shards"), "shard_files": folder_files("shards")}


def latent_inputs(latent_set):
    """A latent set's cache folder (input latents), every file in it, and its tokenizers' folders."""
    stage = REG.latent_sets[latent_set].stage
    return {"latents": P("latents", stage), "latent_files": folder_files(stage), **tokenizer_inputs(latent_set)}


TOKENIZER_ARGS = " --detail-tokenizer {input.detail_tokenizer} --abstract-tokenizer {input.abstract_tokenizer}"
LATENT_ARGS = " --latents {input.latents}" + TOKENIZER_ARGS


def named_inputs(prefix, kind, names):
    """Inputs <prefix><name>: the layout path of kind for each name (once each, in order)."""
    return {f"{prefix}{name}": P(kind, name) for name in dict.fromkeys(names)}


def named_args(option, kind, names):
    """` <option> <name>=<path>` for each name: one family's layout paths (the same as named_inputs'),
    each with its entry's name.

    Concrete paths, not {input...} placeholders: Snakemake evaluates a `shell:` expression again
    when the job runs, when a loop's variables hold their last values, so a rule made in a loop
    passes what depends on the loop through `params.args` (set when the rule is defined)."""
    return "".join(f" {option} {name}={P(kind, name)}" for name in dict.fromkeys(names))


def predictor_inputs(names):
    """Predictor folders: inputs predictor_<name>, passed by predictor_args."""
    return named_inputs("predictor_", "predictor", names)


def predictor_args(names):
    return named_args("--predictor", "predictor", names)


def log(name):
    return f"logs/{name}.log"


def bench(name):
    return f"logs/benchmarks/{name}.tsv"


# Shell suffix: the stage's output on the console and in its log.
TEE = " 2>&1 | tee {log}"

# Machine needs of each kind of rule. threads are capped at --cores, so a rule
# asking for more than the machine has runs alone; gpu, mem_mb and runtime
# (minutes) are for schedulers (profiles/slurm) and are the paper profile's needs.
LIGHT = dict(threads=1, gpu=0, mem_mb=4000, runtime=60)
CPU = dict(threads=16, gpu=0, mem_mb=32000, runtime=600)
TRAIN = dict(threads=16, gpu=8, mem_mb=480000, runtime=2880)
GPU = dict(threads=16, gpu=1, mem_mb=64000, runtime=600)


def resources_of(kind):
    return {k: v for k, v in kind.items() if k != "threads"}


# The default target (`snakemake --cores 2`): rules in included files never become it.
rule all:
    input:
        "reports/main_table.csv",


include: "rules/data.smk"
include: "rules/tokenizers.smk"
include: "rules/predictors.smk"
include: "rules/evaluation.smk"
include: "rules/evaluate.smk"
include: "rules/reports.smk"


# A successful run leaves DVC's lock in step (when DVC reads the same config): `dvc status` is clean and
# `dvc repro` re-runs only what changes. ORBIS2_DVC_COMMIT=0 turns it off.
onsuccess:
    commit_to_dvc([job.rule.name for job in workflow.dag.jobs], DVC_DRIFT)
