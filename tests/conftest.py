"""Shared fixtures: the project root, a config for the smoke profile, tiny synthetic videos, and one
smoke-profile project run through the main job and `reports/all` for the whole session.

The smoke project takes most of the suite's time, so it is built in the background (tests/smoke_build.py)
from the moment a test that needs it is collected, once for all pytest-xdist workers, and the tests that
read it run last: the other tests run meanwhile. Tests that read only the main job's outputs take
``smoke_main``, a copy made as soon as the main job is done, and run while `reports/all` is built; only the
tests of `reports/all` itself (``smoke_project``) wait for the whole build."""

from __future__ import annotations

import compileall
import contextlib
import os
import shutil
import signal
import socket
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
import pytest
import torch
import yaml
from filelock import FileLock

from orbis2.config.params import load_config
from orbis2.config.training import TrainConfig
from orbis2.data.video import write_video
from orbis2.stage import freeze_imports

ROOT = Path(__file__).resolve().parents[1]

# One compute thread per pytest-xdist worker and per process a test starts, documented commands included: the
# workers, the smoke build and the readers of the smoke project keep both cores busy, and a second thread per
# process only contends (the readers' commands ran 2.2x faster on one thread each). Snakemake, which sets each
# job's OMP_NUM_THREADS to its rule's threads (capped at --cores), reads the session's profile, which caps them at
# one (tests/snakemake_profile): two smoke `action` jobs run side by side took 1.4-1.7x the CPU with two threads
# each as with one (three pairs).
os.environ["OMP_NUM_THREADS"] = "1"
os.environ["SNAKEMAKE_PROFILE"] = str(ROOT / "tests" / "snakemake_profile")
torch.set_num_threads(1)


# Slurm's client tools installed where no controller answers (a machine that once ran tools/slurm_local.sh, an
# image with the packages): Snakemake's Slurm executor plugin, which every `snakemake` run imports, then waits 10 s
# at import for `scontrol show config` to time out, and the suite starts a few hundred of them. The first pytest
# process asks `sinfo` once; where nothing answers, every process of the session finds shims first on its PATH
# that fail at once, as the real tools would after their timeout, and the Slurm tests skip.
SLURM_STATE = "ORBIS2_TEST_SLURM"  # "up" or "down", the first process's answer, inherited by the xdist workers
SLURM_TOOLS = ("sinfo", "scontrol", "squeue", "sacct", "sbatch", "srun", "scancel", "salloc")
SLURMCTLD_PORT = 6817  # Slurm's default where slurm.conf sets no SlurmctldPort


def controller_listens() -> bool | None:
    """Whether anything listens where slurm.conf puts the controller (each SlurmctldHost's address, else its name,
    at SlurmctldPort's first port); None without a readable slurm.conf (a configless cluster: ask `sinfo`). Where
    nothing listens, `sinfo` takes 9 s to give up, at the start of every session; a refused connection says so
    at once."""
    try:
        text = Path(os.environ.get("SLURM_CONF", "/etc/slurm/slurm.conf")).read_text()
    except OSError:
        return None
    hosts, port = [], SLURMCTLD_PORT
    for line in text.splitlines():
        key, _, value = line.split("#")[0].partition("=")
        key, value = key.strip().lower(), value.strip()
        if key in ("slurmctldhost", "controlmachine"):
            name, _, address = value.partition("(")
            hosts.append(address.rstrip(")") or name)
        elif key == "slurmctldport":
            port = int(value.split("-")[0])
    for host in hosts:
        with contextlib.suppress(OSError):
            socket.create_connection((host, port), timeout=2).close()
            return True
    return False if hosts else None


def slurm_answers() -> bool:
    """Whether a Slurm controller answers `sinfo` here (asked once per session, unless nothing listens where
    slurm.conf puts it)."""
    if SLURM_STATE not in os.environ:
        up = False
        if shutil.which("sinfo") and controller_listens() is not False:
            with contextlib.suppress(subprocess.TimeoutExpired):
                up = subprocess.run(["sinfo", "-h"], capture_output=True, timeout=20).returncode == 0
        os.environ[SLURM_STATE] = "up" if up else "down"
    return os.environ[SLURM_STATE] == "up"


SLURM_SHIMS = pytest.StashKey[Path]()


def compile_package() -> None:
    """Write the bytecode of src/ once (``compileall``), where the environment keeps Python from writing it
    (``PYTHONDONTWRITEBYTECODE``, as on the CI machine): the session starts about 300 Python processes that import
    orbis2 (the smoke DAG's stages, Snakemake, the commands tests run), and without the files each compiles the
    modules it imports anew, 0.1-0.25 s of CPU for a stage's 50. Python reads the files whatever that setting,
    and compiles a module anew wherever its source is newer than its file."""
    compileall.compile_dir(ROOT / "src", quiet=1)


def pytest_configure(config: pytest.Config) -> None:
    """Compile the package's bytecode once for the session where Python writes none; shadow Slurm's client tools
    where they are installed but no controller answers."""
    if sys.dont_write_bytecode:  # up-to-date files are left as they are: the workers find nothing to do
        compile_package()
    if slurm_answers() or not shutil.which("scontrol") or "orbis2-no-slurm-" in os.environ["PATH"]:
        return
    shims = Path(tempfile.mkdtemp(prefix="orbis2-no-slurm-"))
    for tool in SLURM_TOOLS:
        (shims / tool).write_text(f"#!/bin/sh\necho '{tool}: no Slurm controller answers here "
                                  f"(tests/conftest.py)' >&2\nexit 1\n")
        (shims / tool).chmod(0o755)
    os.environ["PATH"] = f"{shims}{os.pathsep}{os.environ['PATH']}"
    config.stash[SLURM_SHIMS] = shims


@pytest.fixture(autouse=True)
def _scheduling_class_kept():
    """Every test leaves its process in the scheduling class it found: one left in the real-time class (SVT-AV1's
    encoder, run as root, did that) would pass it on to every later test of its worker and to what they start,
    and run ahead of the smoke build until the build starved."""
    before = os.sched_getscheduler(0)
    yield
    assert os.sched_getscheduler(0) == before, "the test left its process in another scheduling class"


@pytest.fixture(scope="session")
def smoke_cfg():
    return load_config(ROOT / "params.yaml", "smoke")


def train_config(**values) -> TrainConfig:
    """A training config for unit tests: ``values`` over plain settings (AdamW, no weight decay, clipping or EMA).

    TrainConfig has no defaults (params.yaml sets every field); tests that train tiny
    models name what they vary and take the rest from here.
    """
    plain = dict(weight_decay=0.0, decay_biases_and_norms=False, betas=(0.9, 0.999), optimizer="adamw",
                 warmup_steps=0, min_lr_ratio=0.1, grad_clip=None, ema_decay=None, mixed_precision="bf16", tf32=True,
                 activation_checkpointing=0, checkpoint_policy="full", compile=False, log_every=10, eval_every=0,
                 checkpoint_every=500, seed=0, num_workers=0, micro_batch_size=None)
    return TrainConfig(**{**plain, **values})


def moving_pattern(n: int, width: int, height: int, seed: int = 0) -> np.ndarray:
    """Frames of a textured pattern drifting sideways: real content for codecs and readers."""
    rng = np.random.default_rng(seed)
    base = rng.integers(0, 255, (height, width * 2, 3), dtype=np.uint8)
    base = np.repeat(np.repeat(base[::8, ::8], 8, 0), 8, 1)[:height, : width * 2]
    return np.stack([np.ascontiguousarray(base[:, i : i + width]) for i in range(n)])


@pytest.fixture
def make_video(tmp_path):
    def make(name: str, n: int, fps: float, width: int = 160, height: int = 96, folder: Path | None = None) -> Path:
        path = (folder or tmp_path) / name
        path.parent.mkdir(parents=True, exist_ok=True)
        write_video(path, moving_pattern(n, width, height), fps)
        return path

    return make


def project_copy(dest: Path) -> Path:
    """Tracked and untracked-but-not-ignored files, as a fresh clone would have them, in a new git repo
    whose params.yaml selects the smoke profile."""
    files = subprocess.run(["git", "ls-files", "-co", "--exclude-standard"], cwd=ROOT, capture_output=True,
                           text=True, check=True).stdout.split()
    for name in files:
        if (ROOT / name).is_file():
            (dest / name).parent.mkdir(parents=True, exist_ok=True)
            shutil.copy2(ROOT / name, dest / name)
    params = yaml.safe_load((dest / "params.yaml").read_text())
    params["profile"] = "smoke"
    (dest / "params.yaml").write_text(yaml.safe_dump(params, sort_keys=False))
    for cmd in (["git", "init", "-q"], ["git", "add", "-A"], ["git", "commit", "-qm", "copy"]):
        subprocess.run(cmd, cwd=dest, check=True, capture_output=True)
    return dest


def project_env(root: Path) -> dict[str, str]:
    """The environment of a command run in a project copy: its own MLflow store and a new invocation id."""
    env = {**os.environ, "MLFLOW_TRACKING_URI": f"sqlite:///{root / 'mlflow.db'}"}
    env.pop("ORBIS2_PIPELINE_ID", None)
    return env


def run(cmd: list[str], cwd: Path) -> str:
    proc = subprocess.run(cmd, cwd=cwd, env=project_env(cwd), capture_output=True, text=True, timeout=3600)
    assert proc.returncode == 0, f"{' '.join(cmd)} failed:\n{proc.stdout[-3000:]}\n{proc.stderr[-3000:]}"
    return proc.stdout + proc.stderr


SMOKE = "smoke_project"  # the fixture, and its folder in the session's shared temporary folder
SMOKE_MAIN = "smoke_main"  # the fixture of the main job's copy (the build's FOLDER/main)
READERS = (SMOKE_MAIN, SMOKE)  # in the order they run: the main job's readers first
BUILD_TIMEOUT_S = 3600
# The build is the session's critical path: its readers wait for it, while every other test can run at any time.
# The tests run at a lower priority than the build (a third of its jobs' weight while both want the cores), so
# that the build's readers do not wait for it at the end with a core idle. The build stays in the tests' session
# (its own process group, not its own session): Linux's autogroup shares the cores between sessions first, and
# niceness counts only within one.
TEST_NICENESS = 5
BUILDER = pytest.StashKey[subprocess.Popen]()  # the build, in the process that started it


def reads(item: pytest.Item) -> str | None:
    """Which of the smoke project's fixtures a test needs (the whole build wins), or None."""
    names = getattr(item, "fixturenames", ())
    return next((fixture for fixture in reversed(READERS) if fixture in names), None)


def shared_temp(config: pytest.Config) -> Path:
    """The session's temporary folder, the same for every xdist worker (each has its own below it)."""
    base = config._tmp_path_factory.getbasetemp()
    return base.parent if os.environ.get("PYTEST_XDIST_WORKER") else base


@pytest.hookimpl(trylast=True)  # after -k / -m deselection
def pytest_collection_modifyitems(config: pytest.Config, items: list[pytest.Item]) -> None:
    """The smoke project's readers run last, the main job's before the whole build's: the other tests run while
    it is built."""
    items[:] = [item for fixture in (None, *READERS) for item in items if reads(item) == fixture]


def pytest_collection_finish(session: pytest.Session) -> None:
    """Freeze what collection imported, as a stage does (:func:`orbis2.stage.freeze_imports`), and start the smoke
    project's build if a test to run reads it (once per session, whichever xdist worker gets here first); the
    tests then run below the build's priority."""
    freeze_imports()
    config = session.config
    if config.option.collectonly or not any(reads(item) for item in session.items):
        return
    folder = shared_temp(config) / SMOKE
    with FileLock(str(folder) + ".lock"):
        if not folder.exists():
            folder.mkdir()
            with open(folder / "build.log", "w") as log:
                config.stash[BUILDER] = subprocess.Popen(
                    [sys.executable, str(ROOT / "tests" / "smoke_build.py"), str(folder)], cwd=ROOT, stdout=log,
                    stderr=subprocess.STDOUT, process_group=0)  # not a session: one scheduling group with the tests
    os.nice(TEST_NICENESS)  # this process and what it starts from now on; the build, started above, keeps 0


def pytest_unconfigure(config: pytest.Config) -> None:
    """Every test has run: a build still going (an interrupted session) is stopped with its jobs."""
    if SLURM_SHIMS in config.stash:
        shutil.rmtree(config.stash[SLURM_SHIMS], ignore_errors=True)
    proc = config.stash.get(BUILDER, None)
    if proc is not None and proc.poll() is None:
        os.killpg(proc.pid, signal.SIGTERM)
        proc.wait(timeout=60)


def wait_for_build(config: pytest.Config, marker: str) -> Path:
    """The build's folder once it has written ``marker``; the build's failure, or a timeout, fails the test."""
    folder = shared_temp(config) / SMOKE
    started = time.monotonic()
    while not (folder / marker).exists():
        if (folder / "failed").exists():
            pytest.fail(f"the smoke project's build failed:\n{(folder / 'failed').read_text()[-6000:]}")
        if time.monotonic() - started > BUILD_TIMEOUT_S:
            pytest.fail(f"the smoke project was not built within {BUILD_TIMEOUT_S} s: {folder / 'build.log'}")
        time.sleep(2)
    return folder


@pytest.fixture(scope="session")
def smoke_main(request) -> Path:
    """A fresh copy run through the README's main job (`snakemake --cores 2`) at the smoke scale, copied aside
    before `reports/all` starts (tests/smoke_build.py). Tests copy it before they change anything: several
    workers read it at once."""
    return wait_for_build(request.config, "main_built") / "main"


@pytest.fixture(scope="session")
def smoke_project(request) -> Path:
    """A fresh copy run as the README says, at the smoke scale: the main job, then every ablation
    (tests/smoke_build.py). Tests copy it before they change anything: several workers read it at once."""
    return wait_for_build(request.config, "built") / "project"
