"""Lower layers of the library never import higher ones (imports anywhere in a module count, lazy ones too).

The layers, lowest first; a module may import its own layer and those below.
MLflow tracking and the stage helpers (orbis2.tracking, orbis2.stage) sit above the
library proper: the models, data, tasks and evaluation code is pure functions and
classes that know nothing of MLflow. The commands sit above them: orbis2 play's drive,
its web server, then the command line, which no library module imports. Stage scripts
(stages/) and the DAG sit above them all. Nor does any module import, however lazily,
one that imports it back.
"""

import ast
import sys
from collections import deque
from pathlib import Path

from conftest import ROOT

SRC = ROOT / "src"
LAYERS = (
    ("orbis2.errors", "orbis2.typecheck", "orbis2.io", "orbis2.flow", "orbis2.losses", "orbis2.kinematics",
     "orbis2.accel", "orbis2.models", "orbis2.sources"),  # typecheck: the one type checker of params sections
    # and model sizes; sources: the package's import graph and code digests (the DAG's, the resume keys')
    ("orbis2.sim",),  # the driving simulator: numpy/numba/cv2 and orbis2.kinematics only
    ("orbis2.registry", "orbis2.config", "orbis2.interfaces"),  # config checks model presets; all read registry.yaml
    ("orbis2.hierarchy", "orbis2.data"),  # hierarchy: what each predictor sees, its windows included
    ("orbis2.latents", "orbis2.rollout", "orbis2.train", "orbis2.assets", "orbis2.run_profile"),
    # evaluation never imports training tasks: a change in training must not re-run it. Inside it, the measures
    # (with the records and the figure writer, orbis2.eval's own modules), then how they are applied, then the report.
    ("orbis2.eval", "orbis2.eval.metrics"),
    ("orbis2.eval.protocols",),
    ("orbis2.eval.report",),
    ("orbis2.tasks",),
    ("orbis2.inference",),  # trained models in use: what orbis2 rollout and orbis2 play share
    ("orbis2.tracking", "orbis2.stage"),  # the MLflow run and what stage scripts share
    ("orbis2.drive",),  # orbis2 play: the step-wise drive
    ("orbis2.play",),  # and its web server
    ("orbis2.cli", "orbis2.dag", "orbis2.mlflow_app"),  # the orbis2 command; the DAG; the MLflow app
)
# Library packages that must not know about experiment tracking, even through a lazy import.
PURE = ("orbis2.models", "orbis2.data", "orbis2.tasks", "orbis2.eval")
TRACKING = ("mlflow", "orbis2.tracking", "orbis2.stage")


def layer(module: str) -> int:
    """The level of the longest prefix in LAYERS that names ``module`` (orbis2.eval.report is not orbis2.eval's)."""
    found = [(len(p), level) for level, prefixes in enumerate(LAYERS) for p in prefixes
             if module == p or module.startswith(p + ".")]
    if not found:
        raise AssertionError(f"{module} is in no layer: add it to LAYERS in {Path(__file__).name}")
    return max(found)[1]


def module_name(file: Path, src: Path = SRC) -> str:
    parts = file.relative_to(src).with_suffix("").parts
    return ".".join(parts[:-1] if parts[-1] == "__init__" else parts)


def imports(file: Path) -> set[str]:
    """The orbis2 modules ``file`` imports."""
    return {name for name in all_imports(file) if name.startswith("orbis2.")}


def all_imports(file: Path) -> set[str]:
    """Every absolute module name ``file`` imports, anywhere in its body."""
    found = set()
    for node in ast.walk(ast.parse(file.read_text())):
        if isinstance(node, ast.Import):
            found |= {a.name for a in node.names}
        elif isinstance(node, ast.ImportFrom) and node.module and node.level == 0:
            found.add(node.module)
    return found


def tracking_imports(src: Path = SRC) -> list[str]:
    """``module imports name`` for every import of MLflow or of the tracking/stage modules by a pure package."""
    out = []
    for file in sorted(src.rglob("*.py")):
        name = module_name(file, src)
        if not any(name == p or name.startswith(p + ".") for p in PURE):
            continue
        for target in sorted(all_imports(file)):
            if any(target == t or target.startswith(t + ".") for t in TRACKING):
                out.append(f"{name} imports {target}")
    return out


def violations(src: Path = SRC) -> list[str]:
    out = []
    for file in sorted(src.rglob("*.py")):
        name = module_name(file, src)
        if name == "orbis2":
            continue
        for target in sorted(imports(file)):
            if layer(target) > layer(name):
                out.append(f"{name} (layer {layer(name)}) imports {target} (layer {layer(target)})")
    return out


def import_graph(src: Path = SRC) -> dict[str, set[str]]:
    """Each orbis2 module and the other orbis2 modules it imports anywhere in its body (``from package import
    submodule`` counts as importing the package, whose ``__init__`` runs first)."""
    files = {module_name(file, src): file for file in sorted(src.rglob("*.py"))}
    return {name: {t for t in imports(file) if t in files and t != name} for name, file in files.items()}


def import_cycles(src: Path = SRC) -> list[str]:
    """``a -> b -> a`` for the shortest import cycle through each module on one, each cycle once."""
    graph = import_graph(src)
    found = set()
    for start in sorted(graph):
        came_from, queue = {start: start}, deque([start])
        while queue:
            module = queue.popleft()
            if start in graph[module]:
                cycle = [module]
                while cycle[-1] != start:
                    cycle.append(came_from[cycle[-1]])
                cycle.reverse()
                first = cycle.index(min(cycle))
                cycle = cycle[first:] + cycle[:first]
                found.add(" -> ".join(cycle + cycle[:1]))
                break
            for target in sorted(graph[module] - came_from.keys()):
                came_from[target] = module
                queue.append(target)
    return sorted(found)


def test_lower_layers_never_import_higher_ones():
    assert violations() == []


def test_no_module_imports_one_that_imports_it_back():
    assert import_cycles() == []


def test_an_import_cycle_is_found(tmp_path):
    """A lazy import closes a cycle too; a module that only imports into one is not on it."""
    (tmp_path / "orbis2" / "sub").mkdir(parents=True)
    (tmp_path / "orbis2" / "a.py").write_text("from orbis2.sub.b import f\n")
    (tmp_path / "orbis2" / "sub" / "b.py").write_text("def f():\n    import orbis2.a\n")
    (tmp_path / "orbis2" / "c.py").write_text("from orbis2.a import g\nimport orbis2.sub.b\n")
    (tmp_path / "orbis2" / "d.py").write_text("import orbis2.e\n")
    (tmp_path / "orbis2" / "e.py").write_text("from orbis2.f import h\n")
    (tmp_path / "orbis2" / "f.py").write_text("import orbis2.d\nimport orbis2.c\n")
    assert import_cycles(tmp_path) == ["orbis2.a -> orbis2.sub.b -> orbis2.a",
                                       "orbis2.d -> orbis2.e -> orbis2.f -> orbis2.d"]


def test_no_library_module_imports_the_command_line():
    """orbis2.cli parses the command's options and calls the library; only tests and ``python -m`` import it."""
    assert [module_name(f) for f in sorted(SRC.rglob("*.py")) if "orbis2.cli" in imports(f)] == []


def test_library_code_knows_nothing_of_mlflow():
    assert tracking_imports() == []


def test_a_tracking_import_is_found(tmp_path):
    (tmp_path / "orbis2" / "eval" / "protocols").mkdir(parents=True)
    (tmp_path / "orbis2" / "eval" / "protocols" / "speed.py").write_text("def f(run):\n    import mlflow.data\n")
    (tmp_path / "orbis2" / "tasks").mkdir()
    (tmp_path / "orbis2" / "tasks" / "x.py").write_text("from orbis2.tracking import StageRun\n")
    (tmp_path / "orbis2" / "stage.py").write_text("from orbis2.tracking import stage_run\n")  # not a pure package
    assert tracking_imports(tmp_path) == ["orbis2.eval.protocols.speed imports mlflow.data",
                                          "orbis2.tasks.x imports orbis2.tracking"]


def test_every_module_has_a_layer():
    for file in SRC.rglob("*.py"):
        name = module_name(file)
        if name != "orbis2":
            layer(name)


def test_a_violation_is_found(tmp_path):
    (tmp_path / "orbis2" / "models").mkdir(parents=True)
    (tmp_path / "orbis2" / "models" / "probe.py").write_text("def f():\n    from orbis2.eval.report import tables\n")
    (tmp_path / "orbis2" / "eval.py").write_text("from orbis2.models import probe\n")  # downwards: fine
    assert violations(tmp_path) == ["orbis2.models.probe (layer 0) imports orbis2.eval.report (layer 7)"]


def test_the_evaluation_layers_are_found(tmp_path):
    """metrics imports neither protocols nor report, protocols does not import report; downwards is fine."""
    files = {"metrics/fvd.py": "from orbis2.eval.protocols import evaluate\n",
             "metrics/stats.py": "def f():\n    import orbis2.eval.report.tables\n",
             "metrics/odometry.py": "from orbis2.eval import records\nfrom orbis2.eval.metrics import stats\n",
             "protocols/steering.py": "from orbis2.eval.report.claims import fmt\nimport orbis2.eval.metrics.fvd\n",
             "report/tables.py": "from orbis2.eval.protocols import steering\nfrom orbis2.eval import records\n",
             "records.py": "from orbis2.io import write_json\n"}
    for name, text in files.items():
        (tmp_path / "orbis2" / "eval" / name).parent.mkdir(parents=True, exist_ok=True)
        (tmp_path / "orbis2" / "eval" / name).write_text(text)
    assert violations(tmp_path) == [
        "orbis2.eval.metrics.fvd (layer 5) imports orbis2.eval.protocols (layer 6)",
        "orbis2.eval.metrics.stats (layer 5) imports orbis2.eval.report.tables (layer 7)",
        "orbis2.eval.protocols.steering (layer 6) imports orbis2.eval.report.claims (layer 7)"]


def test_the_simulator_needs_only_numpy_numba_cv2_and_kinematics():
    allowed = {"numpy", "numba", "cv2", "orbis2.kinematics", "orbis2.errors", "orbis2.sim"}
    for file in (SRC / "orbis2" / "sim").rglob("*.py"):
        for node in ast.walk(ast.parse(file.read_text())):
            if isinstance(node, ast.Import):
                names = [a.name for a in node.names]
            elif isinstance(node, ast.ImportFrom) and node.level == 0:
                names = [node.module]
            else:
                continue
            for name in names:
                if name.split(".")[0] in sys.stdlib_module_names:
                    continue
                assert any(name == a or name.startswith(a + ".") for a in allowed), f"{file.name} imports {name}"
