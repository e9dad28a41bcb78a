"""Build the session's smoke project: a fresh copy of the repository run through the main job and `reports/all`.

Started in the background by conftest as soon as a collected test needs it, so that the DAG runs while the
other tests do; the tests that read it wait for it (``conftest.smoke_project``). Usage:
``python tests/smoke_build.py FOLDER``; writes FOLDER/project, then FOLDER/built or, on failure,
FOLDER/failed with the failing command's output; FOLDER/build.log has the Snakemake runs' output.

The DAG is the README's (`snakemake --cores 2`, then `reports/all`) with one scheduling change: the jobs
get one thread each (Snakemake sets ``OMP_NUM_THREADS`` to a job's threads), so that the DAG's independent
stages run side by side. At the smoke scale a stage's tensors are too small for a second thread to pay; the
stages compute the same things (the numbers differ from a two-thread run in the last bits of float sums).
``eval_fvd_hierarchical`` keeps the two threads the README's run gives it: docs/evaluate.md's worked example
reruns that stage by hand, which reads the real-data I3D statistics the DAG's run cached, and checks its
figures bit for bit against `orbis2 evaluate`'s, and I3D's float sums depend on the thread count.
"""

from __future__ import annotations

import os
import sys
import traceback
from pathlib import Path

from conftest import project_copy, run

JOBS = str(max(2, os.cpu_count() or 2))  # jobs side by side, one thread each
TWO_THREADS = "eval_fvd_hierarchical"


def build(folder: Path) -> None:
    root = folder / "project"
    root.mkdir(parents=True)
    project_copy(root)
    threads = [f"{rule}={2 if rule == TWO_THREADS else 1}" for rule in run(["snakemake", "--list-rules"], root).split()]
    for target in ([], ["reports/all"]):
        print(run(["snakemake", *target, "--cores", JOBS, "--set-threads", *threads], root), flush=True)


if __name__ == "__main__":
    out = Path(sys.argv[1])
    try:
        build(out)
    except BaseException:
        (out / "failed").write_text(traceback.format_exc())
        raise
    (out / "built").touch()
