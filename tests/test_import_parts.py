"""The import in parts: any number of parts gives the same episodes, a stopped import resumes without reading
again the videos it finished, a changed video is imported again, and frames stream from decoder to writer with
the bytes the whole-video path gives."""

import os
import re
import shutil
import subprocess
import sys

import numpy as np
import pytest
from test_import import stage_env, write_csv

from orbis2.data import importer
from orbis2.data.episodes import RawIndex, read_odometry
from orbis2.data.importer import episode_stem, import_videos
from orbis2.data.parts import part_name
from orbis2.data.video import read_resampled, write_video

from conftest import ROOT, project_copy, run


@pytest.fixture
def videos(tmp_path, make_video):
    """Seven videos in train, two in val, at 25 and 30 fps, most with odometry."""
    src = tmp_path / "videos"
    for split, count in (("train", 7), ("val", 2)):
        for i in range(count):
            fps = 25 if i % 2 else 30
            video = make_video(f"drive_{i}.mp4", int(3.2 * fps), fps=fps, folder=src / split)
            if i != 3:
                t = np.linspace(0, 3.0, 31)
                write_csv(video.with_suffix(".csv"), t, 5 + t + i, 0.05 * i * np.ones_like(t))
    return src


def episodes(root, index):
    """Every episode's record and file bytes, in index order."""
    return [(e, (root / e.split / f"{e.stem}.mp4").read_bytes(), (root / e.split / f"{e.stem}.parquet").read_bytes())
            for e in index.episodes]


@pytest.mark.parametrize("parts", [2, 3, 12])  # 12: more parts than videos
def test_any_parts_same_episodes(videos, smoke_cfg, tmp_path, parts):
    whole, _ = import_videos(videos, tmp_path / "one", smoke_cfg.data, smoke_cfg.import_, False)
    split, _ = import_videos(videos, tmp_path / "many", smoke_cfg.data, smoke_cfg.import_, False, parts=parts)
    assert episodes(tmp_path / "many", split) == episodes(tmp_path / "one", whole)
    assert len(whole.episodes) == 9


class Killed(BaseException):
    """Stands for SIGKILL: nothing after it runs."""


def test_a_stopped_import_resumes_and_a_changed_video_is_imported_again(videos, smoke_cfg, tmp_path,
                                                                         monkeypatch):
    """Killed after a video's files were written but before its outcome was recorded: the restart reads only
    that video and those after it."""
    calls, kill_at = [], [5]
    real = importer.import_one

    def import_one(video, *args):
        calls.append(video.name)
        if len(calls) == kill_at[0]:
            kill_at[0] = 0
            real(video, *args)  # its files are written, its outcome not yet recorded
            raise Killed
        return real(video, *args)

    monkeypatch.setattr(importer, "import_one", import_one)
    with pytest.raises(Killed):
        import_videos(videos, tmp_path / "raw", smoke_cfg.data, smoke_cfg.import_, False, parts=2)
    calls.clear()
    resumed, _ = import_videos(videos, tmp_path / "raw", smoke_cfg.data, smoke_cfg.import_, False, parts=2)
    assert len(calls) == 9 - 4  # the four recorded are not read again; the fifth is redone
    fresh, _ = import_videos(videos, tmp_path / "fresh", smoke_cfg.data, smoke_cfg.import_, False, parts=2)
    assert episodes(tmp_path / "raw", resumed) == episodes(tmp_path / "fresh", fresh)

    # A part stopped, then started again after a video changed: that video alone is imported again.
    work = tmp_path / "work"
    for part in range(2):
        importer.import_part(videos, work, smoke_cfg.data, smoke_cfg.import_, False, part, 2)
    changed = videos / "train" / "drive_2.csv"
    write_csv(changed, np.linspace(0, 3.0, 31), 9 * np.ones(31), np.zeros(31))
    os.utime(changed, ns=(changed.stat().st_atime_ns, changed.stat().st_mtime_ns + 10**9))
    calls.clear()
    written = [importer.import_part(videos, work, smoke_cfg.data, smoke_cfg.import_, False, part, 2)
               for part in range(2)]
    assert calls == ["drive_2.mp4"]
    importer.gather_import(videos, written, tmp_path / "again", smoke_cfg.data)
    stem = episode_stem(videos, "train", videos / "train" / "drive_2.mp4")
    assert np.allclose(read_odometry(tmp_path / "again/train" / f"{stem}.parquet")["speed"], 9)
    calls.clear()  # gathered: the parts' episodes were moved out, so asking for the parts again imports again
    importer.import_part(videos, work, smoke_cfg.data, smoke_cfg.import_, False, 0, 2)
    assert len(calls) == 4


def test_streamed_import_writes_the_frames_of_the_whole_video_path(videos, smoke_cfg, tmp_path):
    """No CSV: every resampled frame is written, byte for byte what writing read_resampled's frames gives."""
    index, _ = import_videos(videos, tmp_path / "raw", smoke_cfg.data, smoke_cfg.import_, False)
    video = videos / "train" / "drive_3.mp4"
    stem = episode_stem(videos, "train", video)
    frames = read_resampled(video, smoke_cfg.data.fps, (smoke_cfg.data.width, smoke_cfg.data.height)).frames
    write_video(tmp_path / "whole.mp4", frames, smoke_cfg.data.fps)
    assert (tmp_path / "raw/train" / f"{stem}.mp4").read_bytes() == (tmp_path / "whole.mp4").read_bytes()
    assert next(e for e in index.episodes if e.stem == stem).frames == len(frames)


def parts_then_gather(stage: list[str], parts: int, cwd, env, manifests) -> str:
    """Run a data stage's command once per part (``--part I``, what the DAG's part jobs run), each leaving its part
    manifest in ``manifests``, then without ``--part`` (the gather); the gather's output."""
    for part in range(parts):
        proc = subprocess.run([*stage, "--parts", str(parts), "--part", str(part)], cwd=cwd, capture_output=True,
                              text=True, env=env)
        assert proc.returncode == 0, proc.stderr
        assert (manifests / f"{part_name(part, parts)}.json").is_file()
    proc = subprocess.run([*stage, "--parts", str(parts)], cwd=cwd, capture_output=True, text=True, env=env)
    assert proc.returncode == 0, proc.stderr
    return proc.stdout


def test_the_stage_in_parts_then_the_gather(videos, smoke_cfg, tmp_path):
    """`stages/import.py --part I --parts 2` for each part (what the DAG's `import_part` jobs run), then the stage
    without --part (the gather, which finds both parts done): the episodes a one-part library import writes; and
    Snakemake plans one `import_part` job per part."""
    env = stage_env(tmp_path)
    (tmp_path / "params.yaml").write_text((ROOT / "params.yaml").read_text())
    stage = [sys.executable, str(ROOT / "stages/import.py"), "--profile", "smoke", "--videos", str(videos)]
    out = parts_then_gather(stage, 2, tmp_path, env, tmp_path / "data/import_parts")
    assert "9 videos imported in 2 parts" in out
    whole, _ = import_videos(videos, tmp_path / "one", smoke_cfg.data, smoke_cfg.import_, False)
    gathered = RawIndex.read(tmp_path / "data/raw/import")
    assert episodes(tmp_path / "data/raw/import", gathered) == episodes(tmp_path / "one", whole)

    root = project_copy(tmp_path / "project")
    shutil.copytree(videos, root / "data/videos")
    plan = run(["snakemake", "--dry-run", "data/raw/import", "--config", "parts=3"], root)
    assert re.findall(r"^(?:local)?rule (\w+):", plan, re.MULTILINE).count("import_part") == 3
