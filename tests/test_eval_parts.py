"""The FVD pass in parts: any number of parts gives the record and media of one pass, to the bit; the DAG schedules
one job per part only when ``parts`` > 1; a batch's noise depends on the seed and its index alone."""

import json
import re
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import torch
import yaml

from orbis2.errors import OrbisError
from orbis2.eval.protocols.rollout_fvd import read_outcome
from orbis2.eval.protocols.systems import batch_generator

from conftest import project_env, run

SYSTEM = "hierarchical"  # the main job's


def test_a_batch_draws_the_same_noise_whoever_runs_it():
    draws = {(seed, batch): torch.randn(4, generator=batch_generator("cpu", seed, batch)) for seed in (0, 31)
             for batch in (0, 1, 2)}
    assert torch.equal(draws[31, 1], torch.randn(4, generator=batch_generator("cpu", 31, 1)))
    assert len({tuple(d.tolist()) for d in draws.values()}) == len(draws)  # every (seed, batch) its own stream


def test_a_damaged_batch_outcome_is_named_with_the_fix(tmp_path):
    path = tmp_path / "000001.npz"
    np.savez(path, **{"fake/0-20": np.ones((2, 400)), "generated_psnr": np.ones(2)})
    assert read_outcome(path)["fake/0-20"].shape == (2, 400)
    data = bytearray(path.read_bytes())
    data[len(data) // 2] ^= 1
    path.write_bytes(data)
    with pytest.raises(OrbisError, match="000001.npz: unreadable .* delete it and run the stage again"):
        read_outcome(path)


def test_the_fvd_pass_in_parts_equals_one_pass(smoke_main, tmp_path):
    """In a copy of the smoke project's main job, on a short and the long split with one rollout a batch (2
    batches a split): `--part 1 --parts 2` (what one of the DAG's `eval_fvd_<system>_part` jobs runs) and the gather
    `--parts 2`, which makes part 0's batch itself and reads part 1's back, as a killed part resumes at its batch;
    then, from nothing, one pass."""
    root = Path(shutil.copytree(smoke_main, tmp_path / "project", symlinks=True))
    params = yaml.safe_load((root / "params.yaml").read_text())
    params["evaluation"]["smoke"].update(batch_size=1, fvd_splits=["val", "turns"])
    (root / "params.yaml").write_text(yaml.safe_dump(params, sort_keys=False))
    stage = [sys.executable, "stages/eval_fvd.py", SYSTEM, "--profile", "smoke"]

    out = run([*stage, "--parts", "2", "--part", "1"], root)
    assert "part 0001-of-0002: rollouts {'val': 1, 'turns': 1}" in out
    manifest = json.loads((root / f"data/eval_parts/{SYSTEM}/0001-of-0002.json").read_text())
    assert manifest["rollouts"] == {"val": 1, "turns": 1}  # batch 1 of each split, kept a file each
    work = root / manifest["outcomes"]
    assert sorted(p.name for p in (work / "val").iterdir()) == ["000001.npz"]
    made = (work / "val/000001.npz").stat().st_mtime_ns
    run([*stage, "--parts", "2", "--fvd", "two.json", "--media", "two"], root)
    assert sorted(p.name for p in (work / "val").iterdir()) == ["000000.npz", "000001.npz"]
    assert (work / "val/000001.npz").stat().st_mtime_ns == made  # read back, not made again
    shutil.rmtree(work)  # one pass from nothing
    run([*stage, "--parts", "1", "--fvd", "one.json", "--media", "one"], root)

    assert (root / "one.json").read_bytes() == (root / "two.json").read_bytes()
    one, two = sorted((root / "one").iterdir()), sorted((root / "two").iterdir())
    assert [p.name for p in one] == [p.name for p in two] and len(one) == 5  # 2 mp4, 2 gif, the grid
    assert all(a.read_bytes() == b.read_bytes() for a, b in zip(one, two))
    record = json.loads((root / "one.json").read_text())
    assert {s: r["videos"] for s, r in record["fvd"].items()} == {"val": 2, "turns": 2} and record["chunked"]


def test_the_dag_runs_one_job_per_part_only_above_one_part(smoke_main, tmp_path):
    """`--config parts=3`: three part jobs before each system's gather, which passes --parts 3; at parts=1 the gather
    alone."""
    root = Path(shutil.copytree(smoke_main, tmp_path / "project", symlinks=True))

    def planned(*config: str) -> str:
        proc = subprocess.run(["snakemake", "-n", "-p", "--cores", "2", "--forcerun", f"eval_fvd_{SYSTEM}",
                               "--config", *config, "--", f"reports/eval/fvd_{SYSTEM}.json"], cwd=root,
                              capture_output=True, text=True, env=project_env(root))
        assert proc.returncode == 0, proc.stderr[-3000:]
        return proc.stdout

    three = planned("parts=3")
    parts = re.findall(rf"python stages/eval_fvd.py {SYSTEM} --parts 3 .* --part (\d) ", three)
    assert sorted(parts) == ["0", "1", "2"]
    assert f"python stages/eval_fvd.py eval_fvd_{SYSTEM} --parts 3 " in three
    one = planned("parts=1")
    assert f"python stages/eval_fvd.py {SYSTEM} --parts" not in one
    assert f"python stages/eval_fvd.py eval_fvd_{SYSTEM} --parts 1 " in one


def test_a_part_job_runs_its_own_system_where_a_cluster_job_step_runs_it(smoke_main, tmp_path):
    """A part job as a cluster executor's job step runs it (Snakemake again, `--mode subprocess`, the one job), for
    a system that is not the Snakefile loop's last: the step evaluates the rule's command anew, so a loop variable in
    it would name the last system (a job step on Slurm once ran flat_abstract_full's part with hierarchical's
    models)."""
    root = Path(shutil.copytree(smoke_main, tmp_path / "project", symlinks=True))
    params = yaml.safe_load((root / "params.yaml").read_text())
    params["evaluation"]["smoke"].update(fvd_splits=["val"])
    (root / "params.yaml").write_text(yaml.safe_dump(params, sort_keys=False))
    part = "0001-of-0002"
    proc = subprocess.run(["snakemake", "--target-jobs", f"eval_fvd_{SYSTEM}_part:part={part}", "--allowed-rules",
                           f"eval_fvd_{SYSTEM}_part", "--cores", "1", "--force", "--mode", "subprocess",
                           "--config", "parts=2"], cwd=root, capture_output=True, text=True, env=project_env(root))
    assert proc.returncode == 0, proc.stdout[-3000:] + proc.stderr[-3000:]
    manifest = json.loads((root / f"data/eval_parts/{SYSTEM}/{part}.json").read_text())
    assert set(manifest["rollouts"]) == {"val"} and f"eval_fvd_{SYSTEM}-" in manifest["outcomes"]
