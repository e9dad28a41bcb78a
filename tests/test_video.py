"""Videos people watch are VP9 (browsers play it), dataset episodes stay mp4v; GIF thumbnails; reading the
codecs datasets ship (AV1 through PyAV), lying headers, resampling by timestamps."""

from __future__ import annotations

import numpy as np
import pytest
from PIL import Image
from test_datasets import encode

from orbis2.data.video import (
    VideoError,
    codec_of,
    count_frames,
    iter_timed_frames,
    probe,
    read_resampled,
    read_video,
    write_gif,
    write_video,
)

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


@pytest.mark.parametrize("codec, suffix", [("libsvtav1", ".webm"), ("libx265", ".mp4")])
def test_av1_and_hevc_decode_with_their_timestamps(tmp_path, codec, suffix):
    """AV1 (which OpenCV's wheels open but decode to nothing) and HEVC at 25 fps: every frame, at k / 25 s."""
    frames = moving_pattern(30, 64, 48)
    path = encode(tmp_path / f"clip{suffix}", frames, 25, codec)
    times, decoded = zip(*iter_timed_frames(path))
    np.testing.assert_allclose(times, np.arange(30) / 25, atol=1e-6)
    assert abs(np.stack(decoded).astype(float) - frames.astype(float)).mean() < 20  # lossy, the same pictures
    resampled = read_resampled(path, 10, (32, 24))
    assert resampled.frames.shape == (12, 24, 32, 3) and resampled.max_error_s == pytest.approx(0.02)


def test_a_header_without_a_duration_is_counted_by_decoding(tmp_path):
    path = encode(tmp_path / "streamed.webm", moving_pattern(20, 64, 48), 10, "libvpx-vp9", live=True)
    assert probe(path).frames == 0  # OpenCV reports about -2.3e17 for this header
    assert count_frames(path) == 20
