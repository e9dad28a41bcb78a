"""Opt-in: tools/rehearse_parts.py on the Slurm cluster this machine answers to (tools/slurm_local.sh start): the
town, the shards and the latent cache in 4 parts, one Slurm job each, a town part killed and resumed, the result
equal to one part's. Skipped unless ``sinfo`` answers; ``ORBIS2_SLURM_TEST_DIR``: a folder every node sees."""

import json
import os
import subprocess
import sys
import tempfile
from pathlib import Path

import pytest

from conftest import ROOT, slurm_answers

pytestmark = [pytest.mark.slow, pytest.mark.skipif(not slurm_answers(), reason="no Slurm cluster answers `sinfo`")]


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
    # run 1: assets and the town's 4 parts at least; run 2: the killed part, the gathers, the shards' and the
    # latent cache's parts, both tokenizers
    assert result["slurm"]["run1"]["jobs"] >= 5 and result["slurm"]["run2"]["jobs"] >= 1 + 3 + 4 + 4 + 2
