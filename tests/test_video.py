"""Videos people watch are VP9 (browsers play it), dataset episodes stay mp4v; GIF thumbnails."""

from __future__ import annotations

import pytest
from PIL import Image

from orbis2.data.video import VideoError, codec_of, read_video, write_gif, write_video

from conftest import moving_pattern


@pytest.mark.parametrize("suffix", [".mp4", ".webm"])
def test_playable_video_is_vp9_and_decodes(tmp_path, suffix):
    frames = moving_pattern(12, 64, 48)
    path = tmp_path / f"rollout{suffix}"
    assert write_video(path, frames, 10, playable=True) == 12
    assert codec_of(path) == "VP90"
    back = read_video(path)
    assert back.shape == (12, 48, 64, 3)
    assert abs(back.astype(float) - frames.astype(float)).mean() < 12  # lossy, but the same pictures


def test_dataset_video_stays_mp4v(tmp_path):
    path = tmp_path / "episode.mp4"
    write_video(path, moving_pattern(5, 64, 48), 10)
    assert codec_of(path) == "FMP4"  # how OpenCV names MPEG-4 Part 2 when reading it back


def test_playable_video_refuses_a_container_browsers_do_not_play(tmp_path):
    with pytest.raises(VideoError, match=r"rollout\.avi: .*\.mp4 or \.webm"):
        write_video(tmp_path / "rollout.avi", moving_pattern(3, 64, 48), 10, playable=True)
    assert not (tmp_path / "rollout.avi").exists()


def test_gif_thumbnail_is_scaled_and_loops(tmp_path):
    path = tmp_path / "rollout.gif"
    assert write_gif(path, moving_pattern(6, 640, 360), 10, width=320) == 6
    with Image.open(path) as gif:
        assert gif.size == (320, 180) and gif.n_frames == 6 and gif.info["loop"] == 0
        assert gif.info["duration"] == 100
