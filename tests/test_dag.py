"""The DAG: dvc.yaml is generated from the Snakefile and current, both tools describe the same stages,
re-run on the same params.yaml edits, and a registry entry adds a predictor to both."""

import copy
import json
import re
import shutil
from pathlib import Path

import pytest
import yaml
from snakemake.utils import format as snakemake_format

from orbis2 import dag
from orbis2.config.params import PROFILES, load_params, resolve_section
from orbis2.registry import registry

from conftest import ROOT

DVC_FILES = ("dvc.yaml", "pipelines/import/dvc.yaml")


def fill_templates(text: str, params: dict) -> str:
    """``${a.b}`` filled from params.yaml, the way DVC does."""
    def lookup(match):
        value = params
        for part in match.group(1).split("."):
            value = value[part]
        return str(value)

    return re.sub(r"\$\{([^}]+)\}", lookup, text)


def tracked_sections(params: list) -> set[str]:
    """DVC's params entries as section names (``spec`` for a predictor's registry.yaml entry)."""
    out = set()
    for entry in params:
        if isinstance(entry, dict):
            out.add("spec")
        else:
            out.add(entry.split(".")[0])
    return out


def dvc_stages(root: Path = ROOT, texts: dict[str, str] | None = None) -> dict[str, dict]:
    """Every dvc.yaml's stages with templates filled from params.yaml; params as tracked keys and sections."""
    params = load_params(root / "params.yaml")
    stages = {}
    for name in DVC_FILES:
        text = texts[name] if texts else (root / name).read_text()
        stages.update(yaml.safe_load(text)["stages"])
    out = {}
    for name, stage in stages.items():
        outs = [next(iter(o)) if isinstance(o, dict) else o for o in stage.get("outs", []) + stage.get("metrics", [])]
        out[name] = {"cmd": fill_templates(stage["cmd"], params),
                     "deps": {fill_templates(d, params) for d in stage.get("deps", [])},
                     "outs": {fill_templates(o, params) for o in outs},
                     "params": tracked_sections(stage.get("params", [])),
                     "keys": {fill_templates(p, params) for p in stage.get("params", []) if isinstance(p, str)}}
    return out


# Rule params DVC tracks as top-level keys of params.yaml, or as the registry.yaml entry (spec).
SETTINGS = {"spec", "parts", "official_weights"}


def snakemake_rules(root: Path = ROOT, videos_as_folder: bool = True) -> dict[str, dict]:
    """Every rule with its command as the shell would run it (no log redirection; paths, params and the
    launcher filled in by Snakemake's own formatter) and its params' sections."""
    raw = load_params(root / "params.yaml")
    videos = resolve_section(raw, "import", raw["profile"])["videos"] if videos_as_folder else None
    rules = {}
    for rule in dag.snakemake_rules(root):
        if dag.snakemake_only(rule):  # test_wildcard_rules_are_snakemake_only
            continue
        cmd = rule.shellcmd.split(" 2>&1 | tee")[0].strip()
        cmd = snakemake_format(cmd, input=rule.input, output=rule.output, params=rule.params, rule=rule.name,
                               config={"train_launcher": raw["train_launcher"], "parts": raw["parts"]})
        sections = {s for key in rule.params.keys() if key not in dag.NOT_SECTIONS
                    for s in dag.section_chain(raw, key)}
        rules[rule.name] = {"cmd": cmd, "deps": {_as_folder(str(f), videos) for f in rule.input if not callable(f)},
                            "outs": {str(f) for f in rule.output},
                            "params": sections | {"profile"} | (SETTINGS & set(rule.params.keys())),
                            "param_keys": [k for k in rule.params.keys() if k not in dag.NOT_SECTIONS]}
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


def test_generated_files_are_current():
    stale = [str(f.relative_to(ROOT)) for f, text in dag.generate().items() if f.read_text() != text]
    assert stale == [], f"run `python -m orbis2.dag`: {stale} differ from the Snakefile"


def test_snakefile_and_dvc_yaml_agree(both):
    dvc, snake = both
    assert {"town", "import", "shards", "assets", "tokenizer_detail", "tokenizer_abstract", "latents",
            "abstract_df", "abstract_tf", "detail", "action"} <= set(dvc)
    assert drift(dvc, snake) == []


def test_wildcard_rules_are_snakemake_only(both):
    """The rules with a wildcard (scoring data/rollouts/<name>/; one part of the town, the import, the shards, a
    latent cache or a system's FVD pass, which DVC's `town`, `import`, `shards`, latents and eval_fvd stages do
    themselves) are left out of dvc.yaml on purpose and no other: a rule that gained a wildcard by mistake would
    vanish from DVC's DAG."""
    dvc, _ = both
    only = {rule.name for rule in dag.snakemake_rules(ROOT) if dag.snakemake_only(rule)}
    assert only == {"evaluate", "town_part", "import_part", "shards_part", "latents_part", "latents_full_part",
                    *(f"eval_fvd_{system}_part" for system in registry().systems)}
    assert not only & set(dvc)
    assert only <= set(yaml.safe_load((ROOT / "profiles/slurm/config.yaml").read_text())["set-resources"])


def test_every_path_reaches_the_stage_as_an_option(both):
    """The commands carry the rules' paths: no placeholder is left, and a stage gets its inputs and outputs."""
    dvc, snake = both
    assert not any("{" in stage["cmd"] for stage in dvc.values())
    assert "--raw data/raw/town --out data/shards" in dvc["shards"]["cmd"]
    assert ("--init data/predictors/abstract_df --out data/predictors/abstract_tf "
            "--report reports/abstract_tf.json") in dvc["abstract_tf"]["cmd"]
    assert ("--predictor abstract_tf=data/predictors/abstract_tf --predictor detail=data/predictors/detail "
            "--fvd reports/eval/fvd_hierarchical.json") in dvc["eval_fvd_hierarchical"]["cmd"]
    raw_source = yaml.safe_load((ROOT / "dvc.yaml").read_text())["stages"]["shards"]["cmd"]
    assert "--raw data/raw/${data.all.source}" in raw_source  # follows `dvc exp run -S data.all.source=...`


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
        assert stage["params"] - {"spec"} <= set(params), name


def test_code_inputs_follow_the_import_graph():
    code = dag.code_inputs("stages/predictor.py")
    assert {"stages/predictor.py", "src/orbis2/tasks/predictors.py", "src/orbis2/models/stdit.py",
            "src/orbis2/flow.py", "src/orbis2/train.py"} <= set(code)
    assert "src/orbis2/eval/report/report.py" not in code  # training does not import the report


def test_evaluation_stages_depend_on_no_training_code():
    """A change in training code re-runs the stages that train, not the evaluation of trained models."""
    stages = yaml.safe_load((ROOT / "dvc.yaml").read_text())["stages"]
    evaluations = [name for name in stages if name.startswith(("eval_", "report"))]
    assert len(evaluations) > 5
    for name in evaluations:
        training = [d for d in stages[name]["deps"] if d.startswith("src/orbis2/tasks/") or d == "src/orbis2/train.py"]
        assert training == [], f"{name} depends on {training}"


@pytest.mark.parametrize("profile", PROFILES)
def test_dvc_and_snakemake_rerun_on_the_same_edits(both, profile):
    """An edit to any part of any params.yaml section changes a rule's resolved params (Snakemake re-runs)
    exactly when DVC tracks that part for the stage."""
    dvc, snake = both
    raw = load_params(ROOT / "params.yaml")
    sections = [s for s, v in raw.items() if isinstance(v, dict)]
    for name, rule in snake.items():
        tracked = {k.replace(raw["profile"], profile) if k.endswith("." + raw["profile"]) else k
                   for k in dvc[name]["keys"]}
        before = {key: resolve_section(raw, key, profile) for key in rule["param_keys"]}
        for section in sections:
            for part in ("all", *PROFILES):
                edited = copy.deepcopy(raw)
                edited[section][part] = {**(edited[section][part] or {}), "edited": 1}
                changed = any(resolve_section(edited, key, profile) != before[key] for key in rule["param_keys"])
                assert changed == (f"{section}.{part}" in tracked), (name, section, part)


def project_copy(dest: Path) -> Path:
    for name in ("Snakefile", "params.yaml", "registry.yaml"):
        shutil.copy2(ROOT / name, dest / name)
    for folder in ("rules", "stages", "pipelines"):
        shutil.copytree(ROOT / folder, dest / folder)
    return dest


def test_a_registry_entry_adds_a_predictor_to_both_dags(tmp_path, monkeypatch):
    root = project_copy(tmp_path)
    registry = yaml.safe_load((root / "registry.yaml").read_text())
    registry["predictors"]["dummy_ablation"] = {"level": "abstract", "rate": "fast", "objective": "teacher_forcing"}
    (root / "registry.yaml").write_text(yaml.safe_dump(registry, sort_keys=False))
    with (root / "params.yaml").open("a") as f:
        f.write("\ndummy_ablation:\n  extends: _teacher_forcing\n  all: {train: {seed: 99}}\n"
                "  smoke: {}\n  default: {}\n  gpu: {}\n  paper: {}\n")
    monkeypatch.setenv("ORBIS2_REGISTRY", str(root / "registry.yaml"))
    snake = snakemake_rules(root)
    dvc = dvc_stages(root, {str(f.relative_to(root)): text for f, text in dag.generate(root).items()})
    for name in ("dummy_ablation", "eval_probe_dummy_ablation"):
        assert name in snake and name in dvc, name
    assert "data/predictors/dummy_ablation" in dvc["eval_probe_dummy_ablation"]["deps"]
    assert {"_teacher_forcing", "_predictor", "dummy_ablation", "spec"} <= dvc["dummy_ablation"]["params"]
    assert drift(dvc, snake) == []


def test_a_params_typo_fails_when_the_snakefile_is_read(tmp_path):
    root = project_copy(tmp_path)
    text = (root / "params.yaml").read_text()
    (root / "params.yaml").write_text(text.replace("abstract_df:\n  extends: _predictor\n  all:",
                                                   "abstract_df:\n  extends: _predictor\n  al:", 1))
    with pytest.raises(Exception, match=r"abstract_df: unknown key\(s\) \['al'\]"):
        snakemake_rules(root)


def test_dvc_metrics_are_the_headline_the_main_job_writes():
    """`dvc metrics show` reads the headline only, which the main job writes (a metrics file of a stage outside
    it, an ablation's training report, failed to load after the main job); the training reports and the
    evaluation records (nested, hundreds of keys) are plain outputs, not cached."""
    stages = yaml.safe_load((ROOT / "dvc.yaml").read_text())["stages"]
    metrics = {next(iter(m)): name for name, stage in stages.items() for m in stage.get("metrics", [])}
    assert metrics == {"reports/headline.json": "report_main"}
    trained = {name for name, stage in stages.items() if "--report reports/" in stage["cmd"]}
    outs = {next(iter(o)): o[next(iter(o))] for name in trained for o in stages[name]["outs"] if isinstance(o, dict)}
    assert len(trained) >= 10 and {"reports/abstract_tf.json": {"cache": False}}.items() <= outs.items()


def test_each_loss_curve_has_its_own_plot():
    """One image per model and loss (each on its own scale), for every training stage."""
    plots = yaml.safe_load((ROOT / "dvc.yaml").read_text())["plots"]
    losses = [p for p in plots if "/curves/" in p]
    stages = yaml.safe_load((ROOT / "dvc.yaml").read_text())["stages"]
    trained = {stage["outs"][0] for stage in stages.values()  # the stages of the one training loop
               if re.search(r"stages/(tokenizer_\w+|predictor|inverse_dynamics)\.py", stage["cmd"])}
    assert {p.split("/curves/")[0] for p in losses} == trained and len(set(losses)) == len(losses)


def test_snakefile_says_when_its_profile_is_not_the_one_dvc_reads(capfd, monkeypatch):
    """A `--config profile=` other than params.yaml's, with the hand-over to DVC off (else the run writes it into
    params.yaml: tests/test_review.py), is a run DVC's views cannot describe: the Snakefile says so."""
    monkeypatch.setenv(dag.COMMIT_ENV, "0")
    file_profile = load_params(ROOT / "params.yaml")["profile"]
    other = next(p for p in PROFILES if p != file_profile)
    dag.snakemake_rules(ROOT, other)
    assert f"profile {other} (--config); params.yaml says {file_profile}" in capfd.readouterr().err
    dag.snakemake_rules(ROOT)
    assert "params.yaml says" not in capfd.readouterr().err


def test_a_local_run_requests_at_most_what_this_machine_has(monkeypatch):
    """Jobs that run here state this machine's GPUs and memory at most (a smoke run's training rules asked for
    8 GPUs and 480 GB); jobs sent to a scheduler, and the SLURM profile, keep the declared needs."""
    declared = {"gpu": 8, "mem_mb": 480000, "runtime": 2880}
    machine = dag.this_machine()
    here = dag.requests(declared, lambda: True)
    assert here["gpu"](None) == min(8, machine["gpu"]) and here["mem_mb"](None) == min(480000, machine["mem_mb"])
    assert here["runtime"] == 2880 and 0 < machine["mem_mb"] < 480000
    assert dag.requests(declared, lambda: False)["gpu"](None) == 8
    monkeypatch.setenv("CUDA_VISIBLE_DEVICES", "")
    assert dag.this_machine()["gpu"] == 0
    slurm = yaml.safe_load((ROOT / "profiles/slurm/config.yaml").read_text())["set-resources"]
    assert slurm["abstract_df"]["gres"] == "gpu:8" and slurm["abstract_df"]["mem_mb"] == 480000


def test_official_weights_make_the_imported_files_inputs_of_the_stages_that_read_them(tmp_path):
    """params.yaml's official_weights (orbis2.tasks.official): the main tokenizers' and the predictors with an
    imported counterpart take the imported file as an input in both DAGs and track the setting; unset, the
    setting is tracked and nothing else changes (the checked-in dvc.yaml)."""
    (tmp_path / "project").mkdir()
    root = project_copy(tmp_path / "project")
    folder = tmp_path / "official"
    written = {"tokenizers/detail": "tokenizers/detail/tokenizer.pt",
               "tokenizers/abstract": "tokenizers/abstract/tokenizer.pt",
               "predictors/abstract_tf": "predictors/abstract_tf/predictor.pt",
               "predictors/detail": "predictors/detail/predictor.pt"}
    folder.mkdir()
    (folder / "manifest.json").write_text(json.dumps({"written": written}))
    text = (root / "params.yaml").read_text()
    (root / "params.yaml").write_text(text.replace("official_weights: null", f"official_weights: {folder}", 1))
    snake = snakemake_rules(root)
    dvc = dvc_stages(root, {str(f.relative_to(root)): text for f, text in dag.generate(root).items()})
    imported = {"tokenizer_detail": "tokenizers/detail", "tokenizer_abstract": "tokenizers/abstract",
                "abstract_df": "predictors/abstract_tf", "abstract_tf": "predictors/abstract_tf",
                "action": "predictors/abstract_tf", "detail": "predictors/detail",
                "detail_distill": "predictors/detail", "abstract_tf_only": "predictors/abstract_tf"}
    for name in ("tokenizer_abstract_full", "flat_detail", "flat_abstract", "top_detail", *imported):
        file = {str(folder / written[imported[name]])} if name in imported else set()
        assert {d for d in dvc[name]["deps"] if d.startswith(str(folder))} == file, name
        assert ("official_weights" in dvc[name]["keys"]) == (name in imported), name
    assert drift(dvc, snake) == []
    checked_in = yaml.safe_load((ROOT / "dvc.yaml").read_text())["stages"]
    assert "official_weights" in checked_in["detail"]["params"] and not any(
        str(folder) in dep for stage in checked_in.values() for dep in stage["deps"])
