"""Generation speed and peak memory of a rollout (paper Table 5).

On CUDA the peak is the allocator's ``max_memory_allocated`` after a reset, the
number the paper's VRAM column reports. On CPU it is the process's peak
resident set size during the measured calls only. ``resource.getrusage``'s
``ru_maxrss`` cannot serve: it is a lifetime high-water mark that no call
resets, so anything the process touched earlier (data loading, a bigger model)
would hide the rollout's own peak. Linux resets the kernel's high-water mark
(``VmHWM``) when "5" is written to ``/proc/self/clear_refs``; where that file is
not writable (some containers and kernels), a background thread samples
``VmRSS`` every few milliseconds instead, which can miss a spike shorter than
its period. The resident size before the calls is reported too, so the growth
caused by the rollout is visible beside the model's resident weights.
"""

from __future__ import annotations

import statistics
import threading
import time
from pathlib import Path
from typing import Callable

import torch

PROC_STATUS = Path("/proc/self/status")
CLEAR_REFS = Path("/proc/self/clear_refs")
SAMPLE_PERIOD_S = 0.002


def _status_kb(field: str) -> float:
    """A ``kB`` field of ``/proc/self/status`` (Linux only: the CPU peak needs it)."""
    try:
        text = PROC_STATUS.read_text()
    except OSError as err:
        raise RuntimeError(f"measuring CPU memory needs Linux's {PROC_STATUS}: {err}") from err
    for line in text.splitlines():
        if line.startswith(field + ":"):
            return float(line.split()[1])
    raise RuntimeError(f"{PROC_STATUS} has no {field} line")


def rss_mb() -> float:
    """Current resident set size of this process in MiB."""
    return _status_kb("VmRSS") / 1024.0


class PeakRss:
    """Peak resident set size between ``start`` and ``stop``: kernel high-water mark, else sampling."""

    def __init__(self) -> None:
        self._thread: threading.Thread | None = None
        self._done = threading.Event()
        self._peak_kb = 0.0
        self.method = ""

    def start(self) -> None:
        try:
            CLEAR_REFS.write_text("5")
        except OSError:
            self.method = "sampled_vmrss"
            self._done.clear()
            self._peak_kb = _status_kb("VmRSS")
            self._thread = threading.Thread(target=self._sample, daemon=True)
            self._thread.start()
        else:
            self.method = "vmhwm_reset"

    def _sample(self) -> None:
        while not self._done.wait(SAMPLE_PERIOD_S):
            self._peak_kb = max(self._peak_kb, _status_kb("VmRSS"))

    def stop(self) -> float:
        """The peak in MiB since ``start``."""
        if self._thread is None:
            return _status_kb("VmHWM") / 1024.0
        self._done.set()
        self._thread.join()
        self._thread = None
        return max(self._peak_kb, _status_kb("VmRSS")) / 1024.0


def _timed(fn: Callable[[], int], sync: Callable[[], None]) -> tuple[int, float]:
    sync()
    begin = time.perf_counter()
    frames = fn()
    sync()
    seconds = time.perf_counter() - begin
    if isinstance(frames, bool) or not isinstance(frames, int) or frames <= 0:
        raise ValueError(f"the rollout function must return the number of frames it generated, got {frames!r}")
    return frames, seconds


def measure(fn: Callable[[], int], warmup: int = 1, repeats: int = 3, device: torch.device | str | None = None) -> dict:
    """Median frames per second of ``fn`` over ``repeats`` calls and the peak memory they reach.

    ``fn`` runs one rollout and returns how many frames it generated. Warm-up
    calls (caches, lazy allocation, kernel selection) are neither timed nor
    counted in the peak. ``device`` picks CUDA peak allocation; anything else
    measures the CPU process.
    """
    if warmup < 0 or repeats < 1:
        raise ValueError(f"need warmup >= 0 and repeats >= 1, got warmup={warmup}, repeats={repeats}")
    dev = torch.device(device) if device is not None else torch.device("cpu")
    cuda = dev.type == "cuda"
    sync = (lambda: torch.cuda.synchronize(dev)) if cuda else (lambda: None)

    for _ in range(warmup):
        _timed(fn, sync)

    result: dict = {"rss_before_mb": rss_mb()}
    if cuda:
        sync()
        torch.cuda.reset_peak_memory_stats(dev)
        result["cuda_allocated_before_mb"] = torch.cuda.memory_allocated(dev) / 2**20
        tracker = None
    else:
        tracker = PeakRss()
        tracker.start()
    try:
        runs = [_timed(fn, sync) for _ in range(repeats)]
    finally:
        peak = tracker.stop() if tracker is not None else torch.cuda.max_memory_allocated(dev) / 2**20

    fps = statistics.median(frames / seconds for frames, seconds in runs)
    result.update(
        fps=fps,
        seconds_per_frame=1.0 / fps,
        frames=runs[-1][0],
        peak_memory_mb=peak,
        memory_kind="cuda_max_allocated" if cuda else "cpu_peak_rss",
        repeats=repeats,
    )
    if tracker is not None:
        result["memory_method"] = tracker.method
    return result
