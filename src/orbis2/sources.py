"""The package's own source as the DAG and the resume keys read it: which orbis2 modules a script reaches through
its imports (:func:`module_closure`: when a rule re-runs) and a digest of what they compute (:func:`code_version`:
when a training run may resume). Only the standard library: data code that keys its resumable parts on its own
code (the dataset converters) reads it too.
"""

from __future__ import annotations

import ast
import functools
import hashlib
from pathlib import Path
from typing import Iterable, Iterator

import orbis2

# The folder holding the orbis2 package (a checkout's src/): where its modules' files are.
PACKAGE_HOME = Path(orbis2.__file__).resolve().parents[1]


def _module_file(module: str) -> Path | None:
    base = PACKAGE_HOME / Path(*module.split("."))
    for candidate in (base.with_suffix(".py"), base / "__init__.py"):
        if candidate.is_file():
            return candidate
    return None


@functools.lru_cache(maxsize=None)
def _imports(file: Path) -> frozenset[Path]:
    """The orbis2 modules ``file`` imports anywhere in its body (lazy imports included)."""
    found = set()
    for node in _statements(ast.parse(file.read_text()).body):
        names = []
        if isinstance(node, ast.Import):
            names = [a.name for a in node.names]
        elif isinstance(node, ast.ImportFrom) and node.module and node.level == 0:
            names = [node.module] + [f"{node.module}.{a.name}" for a in node.names]
        for name in names:
            if name == "orbis2" or name.startswith("orbis2."):
                target = _module_file(name)
                if target is not None:
                    found.add(target)
    return frozenset(found)


def _statements(body: list[ast.stmt]) -> Iterator[ast.stmt]:
    """Every statement of ``body`` and of the blocks nested in it: where imports are, without visiting the
    expressions (``ast.walk``'s bulk) of a module read at every Snakemake start."""
    for node in body:
        yield node
        for block in ("body", "orelse", "finalbody", "handlers", "cases"):
            nested = getattr(node, block, None)
            if isinstance(nested, list):
                yield from _statements(nested)


def module_closure(script: Path | str) -> list[Path]:
    """``script`` and every orbis2 module it reaches through imports (lazy ones included), sorted: the code a
    stage runs, which both the DAG (:func:`orbis2.dag.code_inputs`: when a rule re-runs) and a training run's
    resume key (:func:`code_version`) follow."""
    seen, todo = set(), [Path(script).absolute()]
    while todo:
        file = todo.pop()
        if file in seen:
            continue
        seen.add(file)
        todo.extend(_imports(file) - seen)
    return sorted(seen)


@functools.cache
def code_version(script: Path | str) -> str:
    """The resume key's code (:func:`work_dir`): :func:`source_digest` of the stage ``script`` and the orbis2
    modules it reaches through imports (lazy ones included: :func:`module_closure`, the import graph that also
    decides when the DAG re-runs the stage).

    The modules a stage's numbers come from, and only what they compute: a fix to a docstring, a comment, the
    layout or the wording of a log line or an error message, or any change to a module the stage does not
    import (an evaluation, a report), must not restart days of training; any other change to its modules (a
    model, a loss, a sampler, a constant) starts a new run.
    """
    return source_digest(module_closure(script))


def source_digest(files: Iterable[Path]) -> str:
    """SHA-256 over each file's name (relative to the folder holding the orbis2 package, else its own name)
    and its :func:`computing_tree`: docstrings, comments, layout and the text of messages do not count. A new
    Python version may parse the same source into another tree: that, too, gives another digest."""
    digest = hashlib.sha256()
    for path in sorted(Path(f).resolve() for f in files):
        name = path.relative_to(PACKAGE_HOME) if PACKAGE_HOME in path.parents else Path(path.name)
        digest.update(str(name).encode() + b"\0" + computing_tree(path.read_text()).encode() + b"\0")
    return digest.hexdigest()


# Calls whose string arguments are messages for people: print(...), warnings.warn(...), a logger's methods.
MESSAGE_CALLS = frozenset({"print", "warn", "debug", "info", "warning", "error", "exception", "critical"})


def computing_tree(source: str) -> str:
    """``source``'s syntax tree as text (``ast.dump``: no comments, no layout, no line numbers) with every
    docstring removed and the text of every message left out: the string literals in the arguments of
    :data:`MESSAGE_CALLS` and of the exception a ``raise`` constructs. Expressions inside those messages
    (an f-string's values) stay: they are code."""
    tree = ast.parse(source)
    for node in ast.walk(tree):
        body = getattr(node, "body", None)
        if (isinstance(node, (ast.Module, ast.ClassDef, ast.FunctionDef, ast.AsyncFunctionDef)) and body
                and isinstance(body[0], ast.Expr) and isinstance(body[0].value, ast.Constant)
                and isinstance(body[0].value.value, str)):
            node.body = body[1:] or [ast.Pass()]
        if isinstance(node, ast.Raise) and isinstance(node.exc, ast.Call):
            _blank_strings(node.exc.args + [k.value for k in node.exc.keywords])
        if isinstance(node, ast.Call):
            name = node.func.attr if isinstance(node.func, ast.Attribute) else getattr(node.func, "id", None)
            if name in MESSAGE_CALLS:
                _blank_strings(node.args + [k.value for k in node.keywords])
    return ast.dump(tree)


def _blank_strings(nodes: list[ast.expr]) -> None:
    """The text of messages out: an f-string keeps only its values, a plain string becomes empty."""
    for top in nodes:
        for node in ast.walk(top):
            if isinstance(node, ast.JoinedStr):
                node.values = [value for value in node.values if not isinstance(value, ast.Constant)]
            elif isinstance(node, ast.Constant) and isinstance(node.value, str):
                node.value = ""
