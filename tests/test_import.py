"""User videos into the raw layout: resampling, odometry CSVs, and every bad input."""

import json
import subprocess
import sys

import numpy as np
import pytest

from orbis2.data.episodes import RawIndex, read_odometry
from orbis2.data.importer import ImportProblem, import_videos
from orbis2.data.video import VideoError, read_video

from conftest import ROOT


def write_csv(path, t, speed, yaw_rate, header="timestamp,speed,yaw_rate"):
    rows = [header] + [f"{a},{b},{c}" for a, b, c in zip(t, speed, yaw_rate)]
    path.write_text("\n".join(rows) + "\n")


def run_import(folder, out, cfg, skip_bad=False):
    return import_videos(folder, out, cfg.data, cfg.import_, skip_bad)


def test_resamples_resizes_and_interpolates_odometry(tmp_path, make_video, smoke_cfg):
    src = tmp_path / "videos"
    video = make_video("drive.mp4", 90, fps=30, folder=src)  # 3 s at 30 fps -> 30 frames at 10 fps
    t = np.linspace(0, 3.0, 31)
    write_csv(video.with_suffix(".csv"), t, 5 + t, 0.1 * np.ones_like(t))
    make_video("silent.mp4", 60, fps=20, folder=src)  # no CSV: unconditional
    out = tmp_path / "raw"
    index, skipped = run_import(src, out, smoke_cfg)
    assert not skipped and [e.frames for e in index.episodes] == [30, 30]
    frames = read_video(index.episodes[0].video(out))
    assert frames.shape == (30, smoke_cfg.data.height, smoke_cfg.data.width, 3)
    odo = read_odometry(index.episodes[0].odometry(out))
    np.testing.assert_allclose(odo["speed"], 5 + np.arange(30) / 10, atol=1e-9)
    # integrated pose: constant yaw rate 0.1 rad/s -> yaw grows by 0.01 per frame
    np.testing.assert_allclose(np.diff(odo["yaw"]), 0.01, atol=1e-9)
    assert index.episodes[0].has_odometry and not index.episodes[1].has_odometry
    assert np.isnan(read_odometry(index.episodes[1].odometry(out))["speed"]).all()
    assert RawIndex.read(out).episodes[1].origin.endswith("silent.mp4")


def test_split_subfolders(tmp_path, make_video, smoke_cfg):
    make_video("a.mp4", 30, fps=10, folder=tmp_path / "v" / "train")
    make_video("b.mp4", 30, fps=10, folder=tmp_path / "v" / "val")
    index, _ = run_import(tmp_path / "v", tmp_path / "raw", smoke_cfg)
    assert [e.split for e in index.episodes] == ["train", "val"]


def bad_inputs(tmp_path, make_video):
    """Each case: (folder with one bad video, text the message must contain)."""
    cases = {}
    d = tmp_path / "unreadable"
    d.mkdir()
    (d / "x.mp4").write_bytes(b"this is not a video")
    cases["unreadable"] = (d, "cannot open")
    d = tmp_path / "truncated"
    good = make_video("t.mp4", 60, fps=10, folder=d)
    good.write_bytes(good.read_bytes()[: len(good.read_bytes()) // 2])
    cases["truncated"] = (d, "t.mp4")
    d = tmp_path / "empty"
    d.mkdir()
    (d / "e.mp4").write_bytes(b"")
    cases["zero frames"] = (d, "e.mp4")
    d = tmp_path / "short"
    make_video("s.mp4", 12, fps=10, folder=d)
    cases["shorter than a window"] = (d, "shorter than one training window")
    d = tmp_path / "rate"
    make_video("r.mp4", 60, fps=25, folder=d)
    cases["frame rate"] = (d, "not an integer multiple")
    d = tmp_path / "columns"
    v = make_video("c.mp4", 30, fps=10, folder=d)
    write_csv(v.with_suffix(".csv"), [0, 1, 2], [1, 1, 1], [0, 0, 0], header="timestamp,velocity,yaw_rate")
    cases["csv columns"] = (d, "missing column(s) ['speed']")
    d = tmp_path / "monotonic"
    v = make_video("m.mp4", 30, fps=10, folder=d)
    write_csv(v.with_suffix(".csv"), [0, 2, 1, 3], [1] * 4, [0] * 4)
    cases["timestamps"] = (d, "strictly increasing")
    return cases


def test_every_bad_input_stops_with_a_clear_message(tmp_path, make_video, smoke_cfg):
    for name, (folder, text) in bad_inputs(tmp_path, make_video).items():
        out = tmp_path / f"out_{name.replace(' ', '_')}"
        with pytest.raises((ImportProblem, VideoError)) as err:
            run_import(folder, out, smoke_cfg)
        assert text in str(err.value), name
        assert str(folder) in str(err.value), f"{name}: message must name the file"


def test_skip_bad_reports_and_keeps_the_good(tmp_path, make_video, smoke_cfg):
    src = tmp_path / "mixed"
    make_video("good.mp4", 40, fps=10, folder=src)
    make_video("rate.mp4", 60, fps=25, folder=src)
    (src / "zz.mp4").write_bytes(b"garbage")
    out = tmp_path / "raw"
    index, skipped = run_import(src, out, smoke_cfg, skip_bad=True)
    assert [e.frames for e in index.episodes] == [40]
    assert sorted(s.path.rsplit("/", 1)[1] for s in skipped) == ["rate.mp4", "zz.mp4"]
    assert sorted(p.name for p in (out / "train").iterdir()) == ["import_train_00000.mp4",
                                                                 "import_train_00000.parquet"]


def test_stage_exits_nonzero_and_leaves_nothing(tmp_path, make_video):
    """The stage script: a bad video -> exit 2, message on stderr, no data/raw/import written."""
    src = tmp_path / "bad"
    make_video("r.mp4", 60, fps=25, folder=src)
    (tmp_path / "params.yaml").write_text((ROOT / "params.yaml").read_text())
    env = {"MLFLOW_TRACKING_URI": f"sqlite:///{tmp_path / 'mlflow.db'}", "PATH": "/usr/bin:/bin"}
    proc = subprocess.run([sys.executable, str(ROOT / "stages/import.py"), "--profile", "smoke", "--videos", str(src)],
                          cwd=tmp_path, capture_output=True, text=True, env=env)
    assert proc.returncode == 2, proc.stderr
    assert "r.mp4" in proc.stderr and "Traceback" not in proc.stderr
    assert not (tmp_path / "data" / "raw" / "import").exists()
    assert not list((tmp_path / "data" / "raw").glob(".import*"))
    proc = subprocess.run([sys.executable, str(ROOT / "stages/import.py"), "--profile", "smoke", "--videos", str(src),
                           "--skip-bad"], cwd=tmp_path, capture_output=True, text=True, env=env)
    assert proc.returncode == 2 and "every video was skipped" in proc.stderr
    make_video("ok.mp4", 30, fps=10, folder=src)
    proc = subprocess.run([sys.executable, str(ROOT / "stages/import.py"), "--profile", "smoke", "--videos", str(src),
                           "--skip-bad"], cwd=tmp_path, capture_output=True, text=True, env=env)
    assert proc.returncode == 0, proc.stderr
    skipped = json.loads((tmp_path / "data/raw/import/skipped.json").read_text())
    assert [s["path"].rsplit("/", 1)[1] for s in skipped] == ["r.mp4"]
