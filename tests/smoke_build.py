"""Build the session's smoke project: a fresh copy of the repository run through the main job and `reports/all`.

Started in the background by conftest as soon as a collected test needs it, so that the DAG runs while the
other tests do; the tests that read it wait for it (``conftest.smoke_project``). Usage:
``python tests/smoke_build.py FOLDER``; writes FOLDER/project; once the main job is done, a copy of it as
FOLDER/main and then FOLDER/main_built (its readers start while `reports/all` runs); at the end FOLDER/built
or, on failure, FOLDER/failed with the failing command's output; FOLDER/build.log has the Snakemake runs'
output.

The DAG is the README's (`snakemake --cores 2`, then `reports/all`) with one scheduling change: the jobs
get one thread each (the session's Snakemake profile, tests/snakemake_profile, set by conftest), so that the
DAG's independent stages run side by side. At the smoke scale a stage's tensors are too small for a second
thread to pay; the stages compute the same things (the numbers differ from a two-thread run in the last bits
of float sums).
"""

from __future__ import annotations

import os
import shutil
import sys
import traceback
from pathlib import Path

from conftest import project_copy, run

JOBS = str(max(2, os.cpu_count() or 2))  # jobs side by side, one thread each


def build(folder: Path) -> None:
    root = folder / "project"
    root.mkdir(parents=True)
    project_copy(root)
    print(run(["snakemake", "--cores", JOBS], root), flush=True)
    # a copy: `reports/all` goes on writing into the project (dvc.lock, the MLflow store) while its readers read
    shutil.copytree(root, folder / "main", symlinks=True)
    (folder / "main_built").touch()
    print(run(["snakemake", "reports/all", "--cores", JOBS], root), flush=True)


if __name__ == "__main__":
    out = Path(sys.argv[1])
    try:
        build(out)
    except BaseException:
        (out / "failed").write_text(traceback.format_exc())
        raise
    (out / "built").touch()
