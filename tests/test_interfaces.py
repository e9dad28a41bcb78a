"""Each stage is declared once (orbis2.interfaces): every rule reads the sections its stage opens and passes
only options its script accepts, and a new declaration + script becomes a stage of both DAGs."""

import importlib.util
import shlex
from pathlib import Path
from types import SimpleNamespace

import pytest
import yaml
from pydantic import BaseModel
from snakemake.utils import format as snakemake_format
from test_dag import drift, dvc_stages, project_copy, snakemake_rules

from orbis2 import dag, interfaces, sources
from orbis2.config.params import load_params
from orbis2.eval import records
from orbis2.interfaces import INTERFACES, LIGHT, SHARDS, SHORT, Interface, PathOption
from orbis2.registry import registry

from conftest import ROOT


class Opened(Exception):
    """Raised in place of opening the stage's run: what the script parsed and the sections it would read."""


def opened_stage(script: Path, argv: list[str], monkeypatch) -> Opened:
    """Run ``script``'s main() on ``argv`` up to its open_stage call."""
    spec = importlib.util.spec_from_file_location(f"stage_{script.stem}", script)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)

    def fake_open_stage(name, args, interface, extra=()):
        raise Opened(name, args, interface.sections_with(extra))

    monkeypatch.setattr(module, "open_stage", fake_open_stage)
    with pytest.raises(Opened) as caught:
        module.main(argv)
    return caught.value


def rule_commands(root: Path = ROOT) -> dict[str, tuple[list[str], list[str]]]:
    """Every rule's command as the shell runs it (a wildcard rule's job-time args left out)
    and the params.yaml sections of its ``params:``."""
    raw = load_params(root / "params.yaml")
    out = {}
    for rule in dag.snakemake_rules(root):
        params = SimpleNamespace(**{k: "" if callable(v) else v for k, v in rule.params.items()})
        cmd = snakemake_format(rule.shellcmd.split(" 2>&1 | tee")[0], input=rule.input, output=rule.output,
                               params=params, rule=rule.name,
                               config={"train_launcher": raw["train_launcher"], "parts": raw["parts"]})
        out[rule.name] = (shlex.split(cmd), [k for k in rule.params.keys() if k not in dag.NOT_SECTIONS])
    return out


@pytest.fixture(scope="module")
def commands():
    return rule_commands()


def test_every_rule_is_made_from_a_declaration(commands):
    by_script = {i.script: i for i in INTERFACES.values()}
    assert len(commands) > 40
    for name, (words, _) in commands.items():
        script = next(w for w in words if w.startswith("stages/"))
        assert script in by_script, f"rule {name}: {script} has no declaration in orbis2.interfaces"


def test_every_rule_is_scheduled_at_its_declarations_priority(commands):
    """Among ready jobs, the stages others wait on start first, then the long evaluations, then the short ones."""
    by_script = {i.script: i for i in INTERFACES.values()}
    priorities = {rule.name: rule.priority for rule in dag.snakemake_rules(ROOT)}
    for name, (words, _) in commands.items():
        script = next(w for w in words if w.startswith("stages/"))
        assert priorities[name] == by_script[script].priority, name
    assert INTERFACES["predictor"].priority > INTERFACES["eval_fvd"].priority > INTERFACES["eval_probe"].priority


def test_each_rule_reads_the_sections_its_stage_opens_and_passes_options_it_accepts(commands, monkeypatch):
    """Parse each rule's command with its script's own parser: an option the script lacks stops argparse, and
    the sections the stage opens its run with must be the rule's params sections (what re-runs it)."""
    by_script = {i.script: i for i in INTERFACES.values()}
    for name, (words, sections) in commands.items():
        at = next(i for i, w in enumerate(words) if w.startswith("stages/"))
        interface = by_script[words[at]]
        options = {w for w in words[at + 1:] if w.startswith("--")}
        assert options <= {o.option for o in interface.paths} | {"--profile", *interface.options}, name
        try:
            run = opened_stage(ROOT / words[at], words[at + 1:], monkeypatch)
        except SystemExit as err:  # argparse: an option or value the script does not accept
            raise AssertionError(f"rule {name}: {words[at]} rejects {words[at + 1:]}") from err
        _, args, opened = run.args
        assert opened == sections, f"rule {name}: params {sections}, the stage reads {opened}"
        for option in interface.paths:
            if option.option in options and not option.named:
                given = words[words.index(option.option) + 1]
                assert getattr(args, option.option[2:].replace("-", "_")) == Path(given), (name, option.option)


def test_declarations_name_real_scripts_layouts_records_and_rule_files():
    layout = registry().layout
    for interface in INTERFACES.values():
        assert (ROOT / interface.script).is_file(), interface.script
        assert interface.rules is None or (ROOT / interface.rules).is_file(), interface.rules
        assert {o.layout for o in interface.paths} <= set(layout), interface.kind
        assert len({o.option for o in interface.paths}) == len(interface.paths), interface.kind
        if interface.record is not None:
            model = getattr(records, interface.record)
            assert isinstance(model, type) and issubclass(model, BaseModel), interface.record


def test_a_declaration_and_a_script_add_an_evaluation_stage_to_both_dags(tmp_path, monkeypatch):
    """No rule of its own: the stage is made from its declaration, with its record at its layout path."""
    root = project_copy(tmp_path)
    (root / "src").symlink_to(ROOT / "src")  # the code inputs are paths inside the project
    monkeypatch.setattr(dag, "ROOT", root)
    monkeypatch.setattr(sources, "PACKAGE_HOME", root / "src")
    reg = yaml.safe_load((root / "registry.yaml").read_text())
    reg["layout"]["dummy"] = "reports/eval/dummy.json"
    (root / "registry.yaml").write_text(yaml.safe_dump(reg, sort_keys=False))
    monkeypatch.setenv("ORBIS2_REGISTRY", str(root / "registry.yaml"))
    dummy = Interface("eval_dummy", "stages/eval_dummy.py",
                      (SHARDS, PathOption("record", "--out", "the record", "dummy", output=True)),
                      ("data", "evaluation"), LIGHT, SHORT)
    monkeypatch.setitem(interfaces.INTERFACES, "eval_dummy", dummy)
    (root / dummy.script).write_text(
        '"""Stage `eval_dummy`: the number of shard files -> reports/eval/dummy.json."""\n\n'
        "from orbis2.interfaces import INTERFACES\n"
        "from orbis2.io import write_json\n"
        "from orbis2.stage import open_stage, stage_parser\n\n\n"
        "def main(argv=None):\n"
        '    args = stage_parser(INTERFACES["eval_dummy"], __doc__).parse_args(argv)\n'
        '    with open_stage("eval_dummy", args, INTERFACES["eval_dummy"]) as stage:\n'
        '        write_json(args.out, {"files": len(list(args.shards.iterdir()))})\n'
        '        stage.summary = f"-> {args.out}"\n')

    snake = snakemake_rules(root)
    dvc = dvc_stages(root, {str(f.relative_to(root)): text for f, text in dag.generate(root).items()})
    for dag_stages in (snake, dvc):
        stage = dag_stages["eval_dummy"]
        assert stage["outs"] == {"reports/eval/dummy.json"}
        assert {"data/shards", "stages/eval_dummy.py", "src/orbis2/stage.py"} <= stage["deps"]
        assert {"data", "evaluation"} <= stage["params"]
        assert stage["cmd"].endswith("stages/eval_dummy.py --profile default --shards data/shards "
                                     "--out reports/eval/dummy.json")
    assert drift(dvc, snake) == []
    run = opened_stage(root / dummy.script, shlex.split(dvc["eval_dummy"]["cmd"])[2:], monkeypatch)
    assert run.args[0] == "eval_dummy" and run.args[1].out == Path("reports/eval/dummy.json")
