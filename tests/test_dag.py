"""Snakefile and dvc.yaml describe the same DAG: names, commands, inputs, outputs, params."""

import re
from pathlib import Path

import pytest
import yaml

from orbis2.config import load_params, resolve_section

from conftest import ROOT


def dvc_stages(root: Path = ROOT) -> dict[str, dict]:
    """Every dvc.yaml's stages with ``${a.b}`` templates filled from params.yaml, the way DVC does."""
    params = load_params(root / "params.yaml")

    def lookup(match):
        value = params
        for part in match.group(1).split("."):
            value = value[part]
        return str(value)

    def fill(text: str) -> str:
        return re.sub(r"\$\{([^}]+)\}", lookup, text)

    stages = {}
    for path in [root / "dvc.yaml", *sorted((root / "pipelines").glob("*/dvc.yaml"))]:
        stages.update(yaml.safe_load(path.read_text())["stages"])
    out = {}
    for name, stage in stages.items():
        outs = [next(iter(o)) if isinstance(o, dict) else o for o in stage.get("outs", []) + stage.get("metrics", [])]
        out[name] = {"cmd": fill(stage["cmd"]), "deps": {fill(d) for d in stage.get("deps", [])},
                     "outs": {fill(o) for o in outs}, "params": set(stage.get("params", []))}
    return out


def snakemake_rules(root: Path = ROOT, videos_as_folder: bool = True) -> dict[str, dict]:
    from snakemake.api import SnakemakeApi
    from snakemake.settings.types import ConfigSettings, OutputSettings, ResourceSettings

    params = load_params(root / "params.yaml")
    profile = params["profile"]
    videos = resolve_section(params, "import", profile)["videos"] if videos_as_folder else None
    with SnakemakeApi(OutputSettings(quiet={"all"})) as api:
        workflow = api.workflow(resource_settings=ResourceSettings(cores=1),
                                config_settings=ConfigSettings(config={"profile": profile}),
                                snakefile=root / "Snakefile", workdir=root)._workflow
        rules = {}
        for rule in workflow.rules:
            if rule.name == "all":
                continue
            cmd = rule.shellcmd.replace("{params.profile}", profile).replace("{rule}", rule.name)
            rules[rule.name] = {"cmd": cmd,
                                "deps": {_as_folder(str(f), videos) for f in rule.input},
                                "outs": {str(f) for f in rule.output},
                                "params": set(rule.params.keys())}
        return rules


def _as_folder(dep: str, folder: str | None) -> str:
    """The Snakefile lists each user video (so new ones re-run `import`); dvc.yaml names their folder."""
    return folder if folder is not None and Path(folder) in Path(dep).parents else dep


def drift(dvc: dict, snake: dict) -> list[str]:
    problems = [f"stage '{n}' only in dvc.yaml" for n in sorted(set(dvc) - set(snake))]
    problems += [f"rule '{n}' only in the Snakefile" for n in sorted(set(snake) - set(dvc))]
    for name in sorted(set(dvc) & set(snake)):
        for field in ("cmd", "deps", "outs", "params"):
            if dvc[name][field] != snake[name][field]:
                problems.append(f"{name}.{field}: dvc.yaml {dvc[name][field]} != Snakefile {snake[name][field]}")
    return problems


@pytest.fixture(scope="module")
def both():
    return dvc_stages(), snakemake_rules()


def test_snakefile_and_dvc_yaml_agree(both):
    dvc, snake = both
    assert {"town", "import", "shards", "assets", "tokenizer_detail", "tokenizer_abstract", "latents",
            "abstract_df", "abstract_tf", "detail", "action"} <= set(dvc)
    assert drift(dvc, snake) == []


def test_drift_is_detected(both):
    dvc, snake = both
    changed = {name: dict(stage) for name, stage in dvc.items()}
    changed["shards"]["deps"] = changed["shards"]["deps"] | {"src/orbis2/other.py"}
    changed["town"]["cmd"] += " --verbose"
    del changed["import"]
    problems = drift(changed, snake)
    assert any(p.startswith("shards.deps") for p in problems)
    assert any(p.startswith("town.cmd") for p in problems)
    assert "rule 'import' only in the Snakefile" in problems


def test_every_stage_params_section_exists(both):
    params = load_params(ROOT / "params.yaml")
    for name, stage in both[0].items():
        assert stage["params"] <= set(params), name
