"""Every command the documentation shows is run, at the smoke scale, or is marked as not run with a reason.

The commands are the lines of the ```bash blocks of README.md, docs/*.md and the package READMEs. A
block whose commands cannot run here (a GPU, a cluster, a real dataset) has the line
`<!-- not run in tests: <reason> -->` right before its opening fence. Every other command runs in a
copy of the session's finished smoke project (the main job and `reports/all` done; the pages of
`AFTER_MAIN`'s groups, which read only the main job, in a copy of it made before `reports/all` starts), in
the order the pages give them, and must exit 0. Only what cannot run as written in a test is adapted, each in one
place below: the install prefix must equal what CI installs, `pytest` collects (in one process) instead of recursing,
DVC's runs are dry (the Snakemake runs made the outputs; `dvc repro` would redo them), a server is
started, asked for its page and stopped, and a command given more than once (the same words, its options in
any order) is run once, in the first group that gives it: the pages repeat a step as a reminder (the README's
quick start and docs/pipeline.md both start the DAG), and its second run would only redo the same work on the
same finished project. The pages run in five groups side by side (`GROUPS`), each in its own copy.
The slowest commands are printed with their times.
"""

from __future__ import annotations

import contextlib
import os
import re
import shlex
import shutil
import signal
import socket
import subprocess
import time
import urllib.request
from dataclasses import dataclass
from pathlib import Path

import pytest

from conftest import ROOT, project_env

PAGES = [ROOT / "README.md", *sorted((ROOT / "docs").glob("*.md")), *sorted((ROOT / "src").glob("**/README.md"))]
SHELL = {"bash", "sh", "shell"}
NOT_RUN = re.compile(r"<!--\s*not run in tests:\s*(?P<why>.*?)\s*-->")
INSTALL = 'pip install torch==2.13.0 && pip install -e ".[dev]"'


@dataclass(frozen=True)
class Command:
    page: Path
    line: int
    text: str
    not_run: str | None  # the reason, for a command in a marked block

    def __str__(self) -> str:
        return f"{self.page.relative_to(ROOT)}:{self.line}: {self.text}"


def documented_commands(page: Path) -> list[Command]:
    """The commands of a page's shell blocks: comments dropped, `\\`-continued lines joined."""
    lines = page.read_text().splitlines()
    commands, i = [], 0
    while i < len(lines):
        fence = re.match(r"^\s*```\s*(\w*)", lines[i])
        if not fence:
            i += 1
            continue
        previous = next((lines[j] for j in range(i - 1, -1, -1) if lines[j].strip()), "")
        marked = NOT_RUN.search(previous)
        end = next(j for j in range(i + 1, len(lines)) if lines[j].strip().startswith("```"))
        if fence.group(1) in SHELL:
            pending, start = "", None
            for j in range(i + 1, end):
                start = start or j + 1
                pending += lines[j] + "\n"
                if pending.rstrip().endswith("\\"):
                    pending = pending.rstrip()[:-1] + " "
                    continue
                if not quotes_closed(pending):  # a quoted argument over several lines (python -c "...")
                    continue
                text = strip_comment(pending).strip()
                if text:
                    commands.append(Command(page, start, text, marked.group("why") if marked else None))
                pending, start = "", None
            assert not pending, f"{page}:{start}: a command is not finished when its block ends"
        i = end + 1
    return commands


def quotes_closed(text: str) -> bool:
    try:
        shlex.split(text, comments=True)
    except ValueError:
        return False
    return True


def strip_comment(text: str) -> str:
    """The command without a trailing `# comment` (a `#` inside quotes, or inside a word, stays)."""
    quote = None
    for i, char in enumerate(text):
        if quote:
            quote = None if char == quote else quote
        elif char in "'\"":
            quote = char
        elif char == "#" and (i == 0 or text[i - 1].isspace()):
            return text[:i]
    return text


ALL = [command for page in PAGES for command in documented_commands(page)]


def ci_commands() -> list[str]:
    """.ci/run's commands, less its block that installs the browser tests' Debian packages (``if ... fi``)."""
    commands, skipping = [], False
    for line in (line.strip() for line in (ROOT / ".ci/run").read_text().splitlines()):
        skipping = skipping or line.startswith("if ")
        if not skipping and line and not line.startswith(("#", "set ", "cd ")):
            commands.append(line)
        skipping = skipping and line != "fi"
    return commands


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def serve(text: str, cwd: Path) -> str:
    """Start a documented server (MLflow's, ``orbis2 play``) on a free port, wait for its page, stop it with
    everything it started; '' when it answered. For MLflow: one worker process, not its four, and without its
    job runners (seven processes for its GenAI features, started beside the server): each imports the whole of
    MLflow, and the page needs none of them."""
    port = free_port()
    env = {**project_env(cwd), "MLFLOW_SERVER_ENABLE_JOB_EXECUTION": "false"}
    workers = ["--workers", "1"] if text.startswith("mlflow") else []
    proc = subprocess.Popen(shlex.split(text) + ["--host", "127.0.0.1", "--port", str(port), *workers], cwd=cwd,
                            env=env, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True,
                            start_new_session=True)
    try:
        for _ in range(120):
            if proc.poll() is not None:
                return f"exited with {proc.returncode}: {proc.stdout.read()[-2000:]}"
            try:
                with urllib.request.urlopen(f"http://127.0.0.1:{port}/", timeout=2) as page:
                    return "" if page.status == 200 else f"answered {page.status}"
            except OSError:
                time.sleep(0.5)
        return "did not answer within 60 s"
    finally:
        with contextlib.suppress(ProcessLookupError):  # it may have exited on its own
            os.killpg(proc.pid, signal.SIGTERM)
        proc.wait(timeout=30)


def adapted(text: str) -> str | None:
    """What the test runs for a documented command (None: nothing more to run)."""
    if text.startswith(INSTALL):
        rest = text[len(INSTALL):].strip()
        return adapted(rest.removeprefix("&&").strip()) if rest else None
    if text == "pytest" or text.startswith("pytest "):
        return text.replace("pytest", "pytest --collect-only -q -n 0", 1)
    if re.match(r"^dvc (repro|exp run)\b", text):
        return text + " --dry"
    return text


def same_command(text: str) -> tuple:
    """What makes two commands the same: the words that are not options, in order, and the options with their
    values in any order (``--seconds 3 --yaw-rate-scale 1.5`` = ``--yaw-rate-scale 1.5 --seconds 3``). A
    command with shell syntax (pipes, redirections, ``&&``, quotes) is only the same as its exact text."""
    words = shlex.split(text)
    if any(char in text for char in "|&;<>$`'\"\n"):
        return (text,)
    positional, options, i = [], set(), 0
    while i < len(words):
        if words[i].startswith("-"):
            takes_value = i + 1 < len(words) and not words[i + 1].startswith("-")
            options.add((words[i], words[i + 1]) if takes_value else (words[i],))
            i += 2 if takes_value else 1
        else:
            positional.append(words[i])
            i += 1
    return tuple(positional), frozenset(options)


def test_a_repeated_command_is_recognised_with_its_options_in_any_order():
    assert same_command("orbis2 rollout --seconds 3 --yaw-rate-scale 1.5 --out a.mp4") == same_command(
        "orbis2 rollout --yaw-rate-scale 1.5 --out a.mp4 --seconds 3")
    assert same_command("orbis2 rollout --seconds 3 --out a.mp4") != same_command("orbis2 rollout --seconds 3 "
                                                                                  "--out b.mp4")
    assert same_command("cp a b") != same_command("cp b a")
    assert same_command("x --flag a b") != same_command("x --flag b a")
    assert same_command("dvc params diff | grep a") != same_command("dvc params diff  | grep a")


def test_every_shell_block_command_is_found_and_marked_blocks_say_why():
    assert len(ALL) >= 10 and any(c.page.name == "README.md" for c in ALL)
    for command in ALL:
        assert command.not_run is None or len(command.not_run) > 10, f"{command}: say why it is not run"


def test_the_documented_install_and_test_commands_are_what_ci_runs():
    """The README's set-up installs exactly as CI does, and its test command is CI's."""
    readme = [c.text for c in ALL if c.page.name == "README.md"]
    ci = ci_commands()
    assert ci == [f"{INSTALL} && pytest"], ci
    assert f"{INSTALL} && pytest" in readme


# The pages run in groups side by side, each group in its own copy of the smoke project (no page reads what
# another page's commands write); every page not named here is in "docs".
GROUPS = {"README.md": "readme", "docs/evaluate.md": "evaluate", "docs/tracking.md": "tracking",
          **{page: "main_only" for page in ("docs/data.md", "docs/evaluation.md", "docs/gpu-inference.md",
                                            "docs/gpu-training.md", "docs/integrity.md", "docs/play.md",
                                            "docs/scale.md", "src/orbis2/sim/README.md")}}


def group_of(command: Command) -> str:
    return GROUPS.get(command.page.relative_to(ROOT).as_posix(), "docs")


def test_every_group_has_commands_to_run():
    assert {group_of(c) for c in ALL if not c.not_run} == {*GROUPS.values(), "docs"}


def first_of_each() -> dict[tuple, Command]:
    """Each command to run (:func:`same_command` of what the test runs) and the first, in the pages' order, that
    gives it: the one that runs, in its own group."""
    first = {}
    for command in ALL:
        text = None if command.not_run else adapted(command.text)
        if text is not None:
            first.setdefault(same_command(text), command)
    return first


def test_a_command_two_groups_give_runs_in_the_first():
    group = {key: group_of(command) for key, command in first_of_each().items()}
    assert group[same_command("snakemake --cores 2")] == "readme"  # the README's quick start, then docs/pipeline.md
    assert group[same_command("python -m orbis2.dag --check")] == "readme"
    assert set(group.values()) == {*GROUPS.values(), "docs"}  # every group keeps commands of its own


# Groups whose pages read only the main job's outputs: they run while `reports/all` is still being built.
AFTER_MAIN = {"evaluate", "main_only"}


# The whole build's groups, the longest first: they are the session's last tests (conftest), and pytest-xdist
# cannot hand a worker's last queued test to an idle one, so the end of the session is shorter when the last are
# short.
FINISHED_PROJECT_GROUPS = ["readme", "docs", "tracking"]


def test_the_finished_project_groups_are_every_group_that_needs_it():
    assert set(FINISHED_PROJECT_GROUPS) == {*GROUPS.values(), "docs"} - AFTER_MAIN


@pytest.mark.slow
@pytest.mark.parametrize("group", FINISHED_PROJECT_GROUPS)
def test_documented_commands_run_in_a_finished_smoke_project(smoke_project, tmp_path, group):
    run_group(smoke_project, tmp_path, group)


@pytest.mark.slow
@pytest.mark.parametrize("group", sorted(AFTER_MAIN))
def test_documented_commands_run_after_the_main_job(smoke_main, tmp_path, group):
    run_group(smoke_main, tmp_path, group)


def run_group(project: Path, tmp_path: Path, group: str) -> None:
    """Run a group's commands in a copy of ``project``; every failure is reported at the end."""
    root = Path(shutil.copytree(project, tmp_path / "project", symlinks=True))
    failures, ran, times, first = [], 0, [], first_of_each()
    for command in ALL:
        if command.not_run or group_of(command) != group:
            continue
        text = adapted(command.text)
        if text is None or first[same_command(text)] != command:
            continue
        started = time.perf_counter()
        if re.match(r"^(mlflow (ui|server)|orbis2 play)\b(?!.*--help)", text):  # servers, not their help
            problem = serve(text, root)
        else:
            proc = subprocess.run(["bash", "-c", text], cwd=root, env=project_env(root), capture_output=True,
                                  text=True, timeout=900)
            problem = "" if proc.returncode == 0 else \
                f"exit {proc.returncode}:\n{proc.stdout[-1500:]}\n{proc.stderr[-1500:]}"
        ran += 1
        times.append((time.perf_counter() - started, str(command)))
        if problem:
            failures.append(f"{command}\n  ran: {text}\n  {problem}")
    print("slowest documented commands:", *(f"{s:6.1f} s  {c}" for s, c in sorted(times, reverse=True)[:12]),
          sep="\n")
    assert not failures, "\n\n".join(failures)
    assert ran >= 3


def slug(heading: str) -> str:
    """A heading's anchor as GitHub makes it."""
    text = re.sub(r"[^\w\- ]", "", heading.strip().lower())
    return text.replace(" ", "-")


def test_relative_links_of_the_docs_point_at_files_and_headings_that_exist():
    broken = []
    for page in PAGES:
        for target in re.findall(r"\]\(([^)\s]+)\)", page.read_text()):
            if re.match(r"^[a-z]+:", target):
                continue
            path, _, anchor = target.partition("#")
            file = (page.parent / path).resolve() if path else page
            if not file.exists():
                broken.append(f"{page.relative_to(ROOT)}: {target} (no such file)")
            elif anchor and file.suffix == ".md":
                headings = re.findall(r"^#+ (.*)$", file.read_text(), re.MULTILINE)
                if anchor not in {slug(h) for h in headings}:
                    broken.append(f"{page.relative_to(ROOT)}: {target} (no such heading)")
    assert not broken, "\n".join(broken)
