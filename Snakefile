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
from orbis2.dag import adopt_profile, code_inputs, commit_to_dvc, config_drift, follows_profile, requests
from orbis2.errors import ConfigError
from orbis2.interfaces import INTERFACES
from orbis2.registry import layout_path, registry

configfile: "params.yaml"
FILE_PROFILE = load_params("params.yaml")["profile"]  # Snakemake's reader lets a key given twice pass; ours stops

# One id per invocation, inherited by every job (on Slurm via sbatch --export=ALL): the MLflow parent run.
os.environ.setdefault("ORBIS2_PIPELINE_ID", f"snakemake:{uuid.uuid4()}")
envvars: "ORBIS2_PIPELINE_ID"

DVC_DRIFT = config_drift(config)  # the keys DVC cannot see
PROFILE = config["profile"]
FOLLOWS = follows_profile(DVC_DRIFT)  # params.yaml takes the run's profile when it starts (onstart below)
if PROFILE != FILE_PROFILE and not FOLLOWS:  # DVC reads params.yaml only: say where its views and the run part ways
    print(f"profile {PROFILE} (--config); params.yaml says {FILE_PROFILE}, which is what `dvc params diff`, "
          f"`dvc exp show` and `dvc status` read. MLflow records {PROFILE}. To let DVC see this run, set "
          f"`profile: {PROFILE}` in params.yaml instead (docs/tracking.md).", file=sys.stderr)
parse_config(config, PROFILE)  # every key, type and value, and the file's shape; errors name the key
if "official_weights" in DVC_DRIFT:  # the stages read it from params.yaml, where DVC sees it too
    raise ConfigError(f"--config official_weights={config['official_weights']}: set official_weights in "
                      f"params.yaml instead (the stages read it there)")
REG = registry()


def section(name):
    return resolve_section(config, name, PROFILE)


def P(kind, name=None):
    """A path from registry.yaml's layout."""
    return str(layout_path(kind, name))


# Every stage is declared once (orbis2.interfaces: its script, path options, params sections, machine
# needs); its rules are made from the declaration with the helpers below, and its script builds its
# options from the same declaration. A rule passes every input and output path as an option; a stage
# run by hand without them falls back on the same layout.


def latent_paths(latent_set):
    """A latent set's cache folder and the folders of its tokenizers (path options latents, <level>_tokenizer)."""
    entry = REG.latent_sets[latent_set]
    return {"latents": P("latents", entry.stage),
            **{f"{level}_tokenizer": P("tokenizer", entry.tokenizers[level]) for level in ("detail", "abstract")}}


def folder_files(stage):
    """Every file in a checkpoint rule's output folder (input files of the rules that read it).

    Snakemake dates a folder by the folder itself, so a shard or cache array changed in place
    would go unseen; as files, a changed one is newer than what was made from it and re-runs
    that rule, whose stage then verifies it. Listed once the checkpoint has run, so the first
    run already records the full list. dvc.yaml leaves these out: DVC hashes the folder's content.
    """
    return lambda wildcards: sorted(str(f) for f in Path(getattr(checkpoints, stage).get().output[0]).rglob("*")
                                    if f.is_file())


# The checkpoints' folders: an input of one of them brings its files (folder_files): shard_files, latent_files.
CHECKPOINTS = {P("shards"): "shards", **{P("latents", e.stage): e.stage for e in REG.latent_sets.values()}}


def stage_paths(stage, entry=None, **given):
    """The paths of one rule of ``stage``: {key: path}, a repeatable option's {name: path}.

    Each is given (a repeatable one as the names of its entries, each at the layout's path), or the
    layout's for ``entry``; an optional one is passed only when given."""
    unknown = set(given) - {o.key for o in stage.paths}
    if unknown:
        raise ValueError(f"{stage.kind}: no path option {', '.join(sorted(unknown))} (orbis2.interfaces)")
    values = {}
    for option in stage.paths:
        value = given.get(option.key)
        if option.named:
            value = {name: str(option.path(name)) for name in dict.fromkeys(value or ())}
        elif value is None and not option.optional:
            value = str(option.path(entry))
        if value:
            values[option.key] = value
    return values


def inputs(stage, values):
    """The rule's named inputs: <key> per input path, <key>_<name> per entry of a repeatable one."""
    out = {}
    for option in stage.paths:
        value = values.get(option.key)
        if option.output or not value:
            continue
        out.update({f"{option.key}_{n}": p for n, p in value.items()} if option.named else {option.key: value})
        if not option.named and value in CHECKPOINTS:
            out[f"{option.key.removesuffix('s')}_files"] = folder_files(CHECKPOINTS[value])  # shard_files, ...
    return out


def outputs(stage, values):
    """The rule's named outputs, folders as directory()."""
    return {o.key: directory(values[o.key]) if o.folder else values[o.key] for o in stage.paths
            if o.output and o.key in values}


def _passed_from(stage):
    """The first path option passed as a concrete path (a repeatable or optional one): it and those after it
    reach the command through params.args, the others as {input.<key>} / {output.<key>}.

    Snakemake evaluates a `shell:` expression again when the job runs, when a loop's variables hold their
    last values: what a rule made in a loop passes for its entry goes through params (set when the rule is
    defined), and the command itself depends on the declaration alone."""
    return next((i for i, o in enumerate(stage.paths) if o.named or o.optional), len(stage.paths))


def shell_args(stage, values, start=None):
    """` <option> <path>` (` <option> NAME=PATH` per entry) for the options from ``start`` on."""
    args = []
    for option in stage.paths[_passed_from(stage) if start is None else start:]:
        value = values.get(option.key)
        if option.named and value:
            args += [f" {option.option} {name}={path}" for name, path in value.items()]
        elif value:
            args.append(f" {option.option} {value}")
    return "".join(args)


def stage_params(stage, values, extra=(), **more):
    """profile, the sections the stage reads (its declaration's and an entry's ``extra``) and the args its
    command passes (where it passes some: see _passed_from)."""
    args = {"args": shell_args(stage, values)} if _passed_from(stage) < len(stage.paths) else {}
    return {"profile": PROFILE, **{name: section(name) for name in stage.sections_with(extra)}, **args, **more}


def command(stage, head="", script=None):
    """The rule's shell command: launcher, script, ``head`` (the entry: {rule}, {params.scope}), --profile and
    the path options (see _passed_from); its output goes to the console and the log."""
    cmd = f"{stage.launcher} {script or stage.script}{head} --profile {{params.profile}}"
    cut = _passed_from(stage)
    cmd += "".join(f" {o.option} {{{'output' if o.output else 'input'}.{o.key}}}" for o in stage.paths[:cut])
    return cmd + ("{params.args}" if cut < len(stage.paths) else "") + " 2>&1 | tee {log}"


def official_setting(imported):
    """A rule's extra inputs and params for params.yaml's ``official_weights``: the imported file its stage reads
    (None: unset) and the setting itself (which DVC tracks, so that setting it re-runs the stage)."""
    return ({"imported": str(imported)} if imported is not None else {}), {"official_weights": config["official_weights"]}


def resources_of(stage):
    """The declared needs for a scheduler; GPUs and memory at most this machine's when the jobs run here."""
    return requests(stage.resources.scheduler(), lambda: workflow.local_exec)


def log(name):
    return f"logs/{name}.log"


def bench(name):
    return f"logs/benchmarks/{name}.tsv"


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
include: "rules/declared.smk"


# A successful run leaves DVC's lock in step (when DVC reads the same config): `dvc status` is clean and
# `dvc repro` re-runs only what changes. ORBIS2_DVC_COMMIT=0 turns it off.
# A run that changes only the profile (`--config profile=smoke`) writes it into params.yaml when it starts (not
# in a dry run), so that DVC and the orbis2 command describe the run it makes.
onstart:
    if FOLLOWS:
        adopt_profile(PROFILE)
        DVC_DRIFT.clear()

onsuccess:
    commit_to_dvc([job.rule.name for job in workflow.dag.jobs], DVC_DRIFT)
