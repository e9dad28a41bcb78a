"""Published results (docs/results/<profile>/) match today's params.yaml, or say that they are stale;
the publishing tool copies a run's outputs and records how it was made."""

import json
import shutil
import subprocess
import sys
from pathlib import Path

import pandas as pd
import pytest

from orbis2.config.params import load_params

from conftest import ROOT

sys.path.insert(0, str(ROOT / "tools"))
from publish_results import git_state, params_digest, profile_params, same_params  # noqa: E402

PUBLISHED = sorted((ROOT / "docs/results").glob("*/run.json"))


@pytest.mark.parametrize("record", PUBLISHED, ids=lambda p: p.parent.name)
def test_published_params_are_todays_or_marked_stale(record):
    published = json.loads(record.read_text())
    today = profile_params(load_params(ROOT / "params.yaml"), published["profile"])
    assert published["params_sha256"] == params_digest(published["params"])
    assert same_params(published["params"], today) or published["stale"], (
        f"{record}: made with other params than today's params.yaml; publish a new run "
        f"(python tools/publish_results.py) or mark it: python tools/publish_results.py --mark-stale "
        f"{published['profile']} --why '...'")


def test_a_setting_added_since_counts_as_the_same_only_at_its_off_value():
    published = {"profile": "default", "data": {"fps": 10}}
    assert same_params(published, {**published, "official_weights": None})
    assert not same_params(published, {**published, "official_weights": "data/official"})
    assert not same_params(published, {**published, "data": {"fps": 5}})
    assert not same_params({**published, "old": None}, published)  # a setting removed since: not the same
    assert same_params(published, {**published, "data": {"fps": 10, "micro_batch_size": None}})  # at any depth
    assert not same_params(published, {**published, "data": {"fps": 10, "micro_batch_size": 8}})
    assert same_params(published, {**published, "data": {"fps": 10, "model": {}}})  # no overrides: the same
    assert not same_params(published, {**published, "data": {"fps": 10, "model": {"patch_size": 8}}})


def test_what_the_run_wrote_itself_is_no_uncommitted_change(tmp_path):
    """dvc.lock, DVC's .gitignore files and params.yaml's profile taken from `--config profile=...` are the run's
    own writing; an edited setting or source file is an uncommitted change, named whole."""
    def git(*args):
        subprocess.run(["git", *args], cwd=tmp_path, check=True, capture_output=True)
    params = (ROOT / "params.yaml").read_text()
    (tmp_path / "params.yaml").write_text(params)
    (tmp_path / "data").mkdir()
    git("init", "-q")
    git("add", "-A")
    git("-c", "user.name=t", "-c", "user.email=t@t", "commit", "-qm", "x")
    (tmp_path / "params.yaml").write_text(params.replace("\nprofile: default\n", "\nprofile: smoke\n", 1))
    (tmp_path / "dvc.lock").write_text("schema: '2.0'\n")
    (tmp_path / "data/.gitignore").write_text("/latents\n")
    assert git_state(tmp_path)["uncommitted"] == []
    (tmp_path / "params.yaml").write_text(params.replace("\nprofile: default\n", "\nprofile: smoke\nparts: 2\n", 1)
                                          .replace("\nparts: 1\n", "\n", 1))
    (tmp_path / "stage.py").write_text("")
    assert git_state(tmp_path)["uncommitted"] == ["params.yaml", "stage.py"]


def test_every_published_folder_links_what_it_holds():
    for record in PUBLISHED:
        folder = record.parent
        page = (folder / "README.md").read_text()
        for name in ("summary.md", "stage_times.csv", "run.json", "main_table.csv"):
            assert (folder / name).is_file() and f"]({name})" in page, (folder, name)


def fake_run(root: Path, profile: str = "smoke") -> Path:
    (root / "reports").mkdir(parents=True)
    (root / "logs/benchmarks").mkdir(parents=True)
    (root / "params.yaml").write_text((ROOT / "params.yaml").read_text())
    (root / "reports/summary.md").write_text(f"# Summary\n\n## Setup\n\n- profile: {profile}\n- seed: 0\n")
    (root / "reports/main_table.csv").write_text("model,fvd_val\nhierarchical,1.0\n")
    for rule, seconds in (("town", 12.5), ("shards", 3.0)):
        (root / f"logs/benchmarks/{rule}.tsv").write_text(f"s\tmax_rss\n1\t2\n{seconds}\t100\n")
    return root


def publish(*args: str, cwd: Path) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, str(ROOT / "tools/publish_results.py"), *args], cwd=cwd,
                          capture_output=True, text=True)


def test_publish_copies_the_run_and_records_it(tmp_path):
    root = fake_run(tmp_path / "run")
    proc = publish("--root", str(root), "--out", str(tmp_path / "results"), cwd=tmp_path)
    assert proc.returncode == 0, proc.stderr
    folder = tmp_path / "results/smoke"
    record = json.loads((folder / "run.json").read_text())
    assert record["profile"] == "smoke" and record["stale"] is None
    assert record["params"] == profile_params(load_params(root / "params.yaml"), "smoke")
    assert (folder / "main_table.csv").read_text() == (root / "reports/main_table.csv").read_text()
    times = (folder / "stage_times.csv").read_text().splitlines()
    assert times[1:] == ["town,12.5,100.0", "shards,3.0,100.0"] or times[1:] == ["shards,3.0,100.0", "town,12.5,100.0"]
    assert "0.3 min in all over 2 stages" in (folder / "README.md").read_text()

    proc = publish("--out", str(tmp_path / "results"), "--mark-stale", "smoke", "--why", "detail steps changed",
                   cwd=tmp_path)
    assert proc.returncode == 0, proc.stderr
    assert json.loads((folder / "run.json").read_text())["stale"] == "detail steps changed"
    assert "> **Stale**: detail steps changed" in (folder / "README.md").read_text()


def test_publish_refuses_a_project_without_a_finished_run(tmp_path):
    proc = publish("--root", str(tmp_path), "--out", str(tmp_path / "results"), cwd=tmp_path)
    assert proc.returncode != 0 and "run the main job first" in proc.stderr
    assert not (tmp_path / "results").exists()


def test_two_published_runs_compare_figure_by_figure(tmp_path):
    """tools/compare_runs.py reads every headline figure of a published folder; a run against itself differs
    nowhere, and a moved figure shows its difference and, where the intervals part, says so."""
    from compare_runs import Run, comparison

    smoke = ROOT / "docs/results/smoke"
    run = Run(smoke)
    assert {"FVD val: hierarchical", "first frame PSNR, gap (dB): hierarchical val",
            "steering turn, latents (deg): original", "claim 8: the hierarchy's FVD is below repeating the last "
            "frame's on every split"} <= {*run.figures, *run.verdicts}
    page = comparison(run, Run(smoke))
    rows = [line for line in page.splitlines() if line.startswith("| ") and " | " in line]
    figures = [row for row in rows if row.count("|") == 6 and not row.startswith("| figure")]
    assert figures and all(row.split(" | ")[3] in ("+0", "-0") and row.endswith("|  |") for row in figures)
    assert all(row.split(" | ")[1] == row.split(" | ")[2].rstrip(" |") for row in rows
               if row.startswith("| claim"))

    moved = tmp_path / "moved"
    shutil.copytree(smoke, moved)
    table = pd.read_csv(moved / "main_table.csv")
    table.loc[table["model"] == "hierarchical", ["fvd_val", "fvd_val_low", "fvd_val_high"]] = [1.0, 0.5, 1.5]
    table.to_csv(moved / "main_table.csv", index=False)
    proc = subprocess.run([sys.executable, str(ROOT / "tools/compare_runs.py"), str(smoke), str(moved), "--out",
                           str(tmp_path / "page.md")], capture_output=True, text=True)
    assert proc.returncode == 0, proc.stderr
    row = next(line for line in (tmp_path / "page.md").read_text().splitlines()
               if line.startswith("| FVD val: hierarchical"))
    assert row.endswith("| apart |") and f"{1.0 - run.figures['FVD val: hierarchical'][0]:+.4g}" in row
