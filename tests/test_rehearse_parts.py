"""Opt-in: tools/rehearse_parts.py on the Slurm cluster this machine answers to (tools/slurm_local.sh start): the
town, the shards and the latent cache in 4 parts as Slurm array jobs, a town part killed and resumed, the result
equal to one part's. Skipped unless ``sinfo`` answers; ``ORBIS2_SLURM_TEST_DIR``: a folder every node sees."""

import json
import os
import subprocess
import sys
import tempfile
from pathlib import Path

import pytest
from test_slurm import _slurm_answers

from conftest import ROOT

pytestmark = [pytest.mark.slow, pytest.mark.skipif(not _slurm_answers(), reason="no Slurm cluster answers `sinfo`")]


def test_the_data_path_in_parts_through_slurm_arrays_equals_one_part():
    with tempfile.TemporaryDirectory(dir=os.environ.get("ORBIS2_SLURM_TEST_DIR")) as tmp:
        out = Path(tmp) / "rehearsal.json"
        proc = subprocess.run([sys.executable, str(ROOT / "tools/rehearse_parts.py"), "--dir", str(Path(tmp) / "run"),
                               "--parts", "4", "--train", "24", "--json", str(out)], capture_output=True, text=True,
                              timeout=3600, env={**os.environ, "PYTHONPATH": str(ROOT / "src")})
        assert proc.returncode == 0, proc.stdout[-3000:] + proc.stderr[-3000:]
        result = json.loads(out.read_text())
    assert all(d["equal"] for d in result["digests"].values())
    killed = result["killed"]
    assert 0 < killed["logged_at_kill"] < killed["episodes_in_part"] == killed["distinct_after_resume"]
    assert killed["rendered_after_resume"] == killed["episodes_in_part"] - killed["logged_at_kill"]
    tasks = [a["tasks"] for a in result["arrays"]["run1"] + result["arrays"]["run2"]]
    assert tasks.count(4) >= 3  # the town's parts, the shards' and the latent cache's: an array of 4 each
