"""Speed and memory measurement: frames per second from known sleeps, peak memory from a known allocation."""

from __future__ import annotations

import time
from pathlib import Path

import numpy as np
import pytest
import torch

from orbis2.eval.protocols import speed

ALLOC_BYTES = 300 * 2**20


def sleeper(seconds: float, frames: int):
    def fn() -> int:
        time.sleep(seconds)
        return frames

    return fn


def allocate() -> int:
    block = np.ones(ALLOC_BYTES, dtype=np.uint8)  # every page written, so resident
    time.sleep(0.05)  # long enough for the sampling fallback to see it
    assert block[-1] == 1
    return 1


def nothing() -> int:
    return 1


def test_fps_from_known_sleep():
    result = speed.measure(sleeper(0.05, 10), warmup=1, repeats=3)
    # 10 frames in >= 0.05 s: at most 200 fps; scheduling delays only lower it
    assert 20.0 < result["fps"] <= 200.0
    assert result["seconds_per_frame"] == pytest.approx(1.0 / result["fps"])
    assert result["repeats"] == 3 and result["frames"] == 10
    assert result["memory_kind"] == "cpu_peak_rss"
    assert result["rss_before_mb"] > 0


def test_rejects_a_function_that_does_not_count_frames():
    with pytest.raises(ValueError, match="number of frames"):
        speed.measure(lambda: None, warmup=0, repeats=1)


@pytest.mark.parametrize("clear_refs_writable", [True, False], ids=["vmhwm_reset", "sampled_vmrss"])
def test_peak_memory_sees_an_allocation(monkeypatch, tmp_path, clear_refs_writable):
    if not speed.PROC_STATUS.exists():
        pytest.skip("CPU peak memory needs Linux /proc")
    if not clear_refs_writable:
        monkeypatch.setattr(speed, "CLEAR_REFS", Path(tmp_path / "missing" / "clear_refs"))
    elif not _writable(speed.CLEAR_REFS):
        pytest.skip("this kernel does not let the process reset its high-water mark")
    big = speed.measure(allocate, warmup=1, repeats=1)
    small = speed.measure(nothing, warmup=1, repeats=1)
    expected = "vmhwm_reset" if clear_refs_writable else "sampled_vmrss"
    assert big["memory_method"] == small["memory_method"] == expected
    growth_big = big["peak_memory_mb"] - big["rss_before_mb"]
    growth_small = small["peak_memory_mb"] - small["rss_before_mb"]
    assert growth_big > 200.0
    assert growth_small < 100.0


def _writable(path: Path) -> bool:
    try:
        path.write_text("5")
    except OSError:
        return False
    return True


@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs a CUDA device")
def test_cuda_peak_memory_sees_an_allocation():
    def allocate_cuda() -> int:
        block = torch.ones(ALLOC_BYTES, dtype=torch.uint8, device="cuda")
        return int(block[-1].item())

    result = speed.measure(allocate_cuda, warmup=1, repeats=2, device="cuda")
    assert result["memory_kind"] == "cuda_max_allocated"
    assert result["peak_memory_mb"] - result["cuda_allocated_before_mb"] >= 299.0
