"""User videos into the raw layout: resampling, odometry CSVs, and every bad input."""

import json
import os
import shutil
import subprocess
import sys

import numpy as np
import pytest

from orbis2.data.episodes import RawIndex, read_odometry
from orbis2.data.importer import ImportProblem, episode_stem, import_videos
from orbis2.data.video import VideoError, read_video

from conftest import ROOT


def write_csv(path, t, speed, yaw_rate, header="timestamp,speed,yaw_rate"):
    rows = [header] + [f"{a},{b},{c}" for a, b, c in zip(t, speed, yaw_rate)]
    path.write_text("\n".join(rows) + "\n")


def run_import(folder, out, cfg, skip_bad=False):
    return import_videos(folder, out, cfg.data, cfg.import_, skip_bad)


def test_resamples_resizes_and_interpolates_odometry(tmp_path, make_video, smoke_cfg):
    src = tmp_path / "videos"
    video = make_video("drive.mp4", 90, fps=30, folder=src / "train")  # 3 s at 30 fps -> 30 frames at 10 fps
    t = np.linspace(0, 3.0, 31)
    write_csv(video.with_suffix(".csv"), t, 5 + t, 0.1 * np.ones_like(t))
    make_video("silent.mp4", 60, fps=20, folder=src / "val")  # no CSV: unconditional
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


@pytest.mark.parametrize("fps", [23.976, 24, 25, 29.97, 30, 50, 60])
def test_any_source_rate_is_resampled_by_timestamps(tmp_path, make_video, smoke_cfg, fps):
    """Each slot k / 10 s takes the nearest source frame; the odometry is read at that frame's own time."""
    src = tmp_path / "videos"
    n = round(3.2 * fps)
    video = make_video("drive.mp4", n, fps=fps, width=200, height=48, folder=src / "train")
    t = np.linspace(0, 3.3, 34)
    write_csv(video.with_suffix(".csv"), t, 5 + t, 0.1 * np.ones_like(t))
    make_video("v.mp4", 30, fps=10, width=64, height=48, folder=src / "val")
    index, skipped = run_import(src, tmp_path / "raw", smoke_cfg)
    episode = index.episodes[0]
    slots = np.arange(int((n - 1) / fps * 10 + 1e-6) + 1) / 10
    nearest = np.round(slots * fps) / fps  # the source frame closest to each slot
    assert not skipped and episode.frames == len(slots)
    assert episode.source_fps == pytest.approx(fps, rel=1e-3)
    assert episode.timing_error_ms == pytest.approx(np.abs(nearest - slots).max() * 1000, abs=0.01)
    assert episode.timing_error_ms <= 500 / fps + 1e-6
    source_t = read_odometry(episode.odometry(tmp_path / "raw"))["speed"] - 5  # speed 5 + t: the time it was read at
    np.testing.assert_allclose(source_t * fps, np.round(source_t * fps), atol=1e-4)  # a source frame's own time
    assert np.abs(source_t - slots).max() <= 0.5 / fps + 1e-6  # the nearest one (either, on a tie)


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
    make_video("r.mp4", 20, fps=5, folder=d)
    cases["frame rate"] = (d, "slower than 10")
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
    make_video("good.mp4", 40, fps=10, folder=src / "train")
    make_video("rate.mp4", 20, fps=5, folder=src / "train")
    (src / "train" / "zz.mp4").write_bytes(b"garbage")
    make_video("v.mp4", 30, fps=10, folder=src / "val")
    out = tmp_path / "raw"
    index, skipped = run_import(src, out, smoke_cfg, skip_bad=True)
    assert [e.frames for e in index.episodes] == [40, 30]
    assert sorted(s.path.rsplit("/", 1)[1] for s in skipped) == ["rate.mp4", "zz.mp4"]
    stem = episode_stem(src, "train", src / "train" / "good.mp4")  # named by its path: not by what was skipped
    assert sorted(p.name for p in (out / "train").iterdir()) == [f"{stem}.mp4", f"{stem}.parquet"]
    assert [e.stem for e in index.episodes] == [stem, episode_stem(src, "val", src / "val" / "v.mp4")]


def test_an_episode_is_named_by_its_path_in_the_input_folder(tmp_path):
    names = {episode_stem(tmp_path, "train", tmp_path / "train" / f"{n}.mp4") for n in ("a", "b", "c")}
    assert len(names) == 3 and all(n.startswith("import_train_") and len(n) == len("import_train_") + 12
                                   for n in names)
    assert episode_stem(tmp_path, "train", tmp_path / "train/a.mp4") == episode_stem(
        tmp_path / "elsewhere", "train", tmp_path / "elsewhere/train/a.mp4")  # the folder's own place is not in it


def stage_env(tmp_path):
    """A bare environment for a stage script (this checkout's sources first when PYTHONPATH says so)."""
    env = {"MLFLOW_TRACKING_URI": f"sqlite:///{tmp_path / 'mlflow.db'}", "PATH": "/usr/bin:/bin"}
    if "PYTHONPATH" in os.environ:
        env["PYTHONPATH"] = os.environ["PYTHONPATH"]
    return env


def test_stage_exits_nonzero_and_leaves_nothing(tmp_path, make_video):
    """The stage script: a bad video -> exit 2, message on stderr, no data/raw/import written."""
    src = tmp_path / "bad"
    src.mkdir()
    (src / "r.mp4").write_bytes(b"not a video")
    (tmp_path / "params.yaml").write_text((ROOT / "params.yaml").read_text())
    env = stage_env(tmp_path)
    proc = subprocess.run([sys.executable, str(ROOT / "stages/import.py"), "--profile", "smoke", "--videos", str(src)],
                          cwd=tmp_path, capture_output=True, text=True, env=env)
    assert proc.returncode == 2, proc.stderr
    assert "r.mp4" in proc.stderr and "Traceback" not in proc.stderr
    assert not (tmp_path / "data" / "raw" / "import").exists()
    assert not list((tmp_path / "data" / "raw").glob(".import*"))
    proc = subprocess.run([sys.executable, str(ROOT / "stages/import.py"), "--profile", "smoke", "--videos", str(src),
                           "--skip-bad"], cwd=tmp_path, capture_output=True, text=True, env=env)
    assert proc.returncode == 2 and "every video was skipped" in proc.stderr
    (src / "train").mkdir()
    (src / "train" / "r.mp4").write_bytes(b"not a video")
    make_video("ok.mp4", 30, fps=10, folder=src / "train")
    make_video("ok.mp4", 30, fps=10, folder=src / "val")
    proc = subprocess.run([sys.executable, str(ROOT / "stages/import.py"), "--profile", "smoke", "--videos", str(src),
                           "--skip-bad"], cwd=tmp_path, capture_output=True, text=True, env=env)
    assert proc.returncode == 0, proc.stderr
    skipped = json.loads((tmp_path / "data/raw/import/skipped.json").read_text())
    assert [(s["path"].rsplit("/", 1)[1], s["reason"]) for s in skipped] == [("r.mp4", "video")]
    assert "2 videos imported, 1 skipped (1 video)" in proc.stdout + proc.stderr
    proc = subprocess.run([sys.executable, str(ROOT / "stages/import.py"), "--profile", "smoke", "--videos", str(src),
                           "--skip-bad", "--strict"], cwd=tmp_path, capture_output=True, text=True, env=env)
    assert proc.returncode == 2 and "r.mp4: cannot open" in proc.stderr


def odometry_case(tmp_path, make_video, name, text):
    """A folder with one 3-s video at 10 fps and the CSV ``text`` beside it."""
    folder = tmp_path / name
    video = make_video("v.mp4", 30, fps=10, folder=folder / "train")
    video.with_suffix(".csv").write_bytes(text if isinstance(text, bytes) else text.encode())
    return folder


ROWS = "\n".join(f"{t / 10},{5 + t / 10},0.01" for t in range(31))


@pytest.mark.parametrize("name, text, expected", [
    ("bom", b"\xef\xbb\xbftimestamp,speed,yaw_rate\n" + ROWS.encode(), "byte-order mark"),
    ("trailing commas", "timestamp,speed,yaw_rate,\n" + ROWS.replace("\n", ",\n") + ",", "trailing comma"),
    ("rows with a trailing comma", "timestamp,speed,yaw_rate\n" + ROWS.replace("\n", ",\n"), "trailing comma"),
    ("milliseconds", "timestamp,speed,yaw_rate\n" + "\n".join(f"{t * 100},5,0" for t in range(31)),
     "must be in seconds"),
    ("epoch seconds", "timestamp,speed,yaw_rate\n" + "\n".join(f"{1.7e9 + t / 10},5,0" for t in range(31)),
     "seconds from the first video frame"),
    ("negative speed", "timestamp,speed,yaw_rate\n0,5,0\n1,-2,0\n3,5,0", "negative speed -2 at data row 2"),
    ("km/h", "timestamp,speed,yaw_rate\n0,50,0\n1,120,0\n3,130,0", "convert it to m/s"),
    ("degrees/s", "timestamp,speed,yaw_rate\n0,5,0\n1,5,30\n3,5,0", "convert it to rad/s"),
], ids=lambda value: value if isinstance(value, str) and "\n" not in value and len(value) < 30 else "")
def test_csv_that_would_be_misread_is_refused(tmp_path, make_video, smoke_cfg, name, text, expected):
    folder = odometry_case(tmp_path, make_video, name.replace(" ", "_").replace("/", "_"), text)
    out = tmp_path / "raw"
    with pytest.raises(ImportProblem) as err:
        run_import(folder, out, smoke_cfg)
    assert expected in str(err.value) and str(folder / "train" / "v.csv") in str(err.value)


def test_a_missing_split_stops_the_import(tmp_path, make_video, smoke_cfg):
    make_video("a.mp4", 30, fps=10, folder=tmp_path / "v" / "train")
    with pytest.raises(ImportProblem, match=r"no val videos; training needs both: put videos into .*v/train/ and "):
        run_import(tmp_path / "v", tmp_path / "raw", smoke_cfg)
    make_video("flat.mp4", 30, fps=10, folder=tmp_path / "flat")
    with pytest.raises(ImportProblem, match="a folder without split sub-folders imports everything as train"):
        run_import(tmp_path / "flat", tmp_path / "raw", smoke_cfg)
    (tmp_path / "v" / "val").mkdir()
    (tmp_path / "v" / "val" / "broken.mp4").write_bytes(b"garbage")  # val exists, but its only video is skipped
    with pytest.raises(ImportProblem, match="(?s)no val videos.*skipped: .*broken.mp4: cannot open"):
        run_import(tmp_path / "v", tmp_path / "raw", smoke_cfg, skip_bad=True)


def test_the_dag_watches_every_video_file(tmp_path, make_video, monkeypatch):
    """A video added to a split sub-folder must change the import rule's inputs (a folder's mtime does not)."""
    from test_dag import snakemake_rules

    for name in ("Snakefile", "params.yaml", "registry.yaml"):
        (tmp_path / name).write_text((ROOT / name).read_text())
    shutil.copytree(ROOT / "rules", tmp_path / "rules")
    video = make_video("a.mp4", 30, fps=10, folder=tmp_path / "data" / "videos" / "train")
    video.with_suffix(".csv").write_text("timestamp,speed,yaw_rate\n0,1,0\n3,1,0\n")
    make_video("b.mp4", 30, fps=10, folder=tmp_path / "data" / "videos" / "val")
    monkeypatch.chdir(tmp_path)
    deps = snakemake_rules(tmp_path, videos_as_folder=False)["import"]["deps"]
    assert {"data/videos/train/a.mp4", "data/videos/train/a.csv", "data/videos/val/b.mp4"} <= deps


def run_stage(tmp_path, videos):
    (tmp_path / "params.yaml").write_text((ROOT / "params.yaml").read_text())
    return subprocess.run([sys.executable, str(ROOT / "stages/import.py"), "--profile", "smoke", "--videos",
                           str(videos)], cwd=tmp_path, capture_output=True, text=True, env=stage_env(tmp_path))


def test_stage_refuses_a_non_utf8_name_and_its_own_output(tmp_path, make_video):
    src = tmp_path / "videos"
    make_video("ok.mp4", 30, fps=10, folder=src / "train")
    (src / "val").mkdir()
    bad = src / "val" / os.fsdecode(b"caf\xe9.mp4")  # Latin-1 name: OpenCV crashed the process on it
    bad.write_bytes((src / "train" / "ok.mp4").read_bytes())
    proc = run_stage(tmp_path, src)
    assert proc.returncode == 2, proc.stderr
    assert "caf\\xe9.mp4: the file name is not valid UTF-8" in proc.stderr and "Traceback" not in proc.stderr
    assert not (tmp_path / "data" / "raw" / "import").exists()
    # --videos inside the output, which the stage replaces: refused before anything is deleted.
    inside = tmp_path / "data" / "raw" / "import" / "train"
    make_video("mine.mp4", 30, fps=10, folder=inside)
    proc = run_stage(tmp_path, tmp_path / "data" / "raw" / "import")
    assert proc.returncode == 2 and "lies inside the import output" in proc.stderr, proc.stderr
    assert (inside / "mine.mp4").is_file()
