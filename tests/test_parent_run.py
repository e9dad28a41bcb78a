"""The parent run as a one-minute read (orbis2.eval.report.parent), on the published smoke run's tables."""

from __future__ import annotations

import numpy as np
import pandas as pd
import pytest

from orbis2.eval.protocols.rollout_fvd import gallery_frames
from orbis2.eval.report.parent import MAX_METRICS, intervals, parent_metrics, plot_intervals, write_stage_times

from conftest import ROOT

TABLES = [ROOT / "docs/results/smoke" / f"{name}.csv" for name in ("main_table", "steering", "speed", "conditioning")]


def test_few_headline_metrics_under_the_docs_names():
    metrics = parent_metrics(TABLES)
    assert 8 <= len(metrics) <= MAX_METRICS
    main = pd.read_csv(TABLES[0]).set_index("model")
    assert metrics["main_table/hierarchical/fvd_heldout"] == pytest.approx(main.loc["hierarchical", "fvd_heldout"],
                                                                           rel=5e-4)  # 4 significant digits
    assert all(float(f"{v:.4g}") == v for v in metrics.values())
    assert "main_table/repeat_last_detail/fvd_heldout" in metrics and "steering/original/ade" in metrics
    assert not any(k.endswith(("_low", "_high", "_n")) or k.startswith("time/") for k in metrics)
    assert all(k.count("/") == 2 for k in metrics)  # <table>/<row>/<column>: no probe target in the row's name


def test_every_interval_is_one_row_and_one_panel(tmp_path):
    found = intervals(TABLES)
    conditioning = pd.read_csv(TABLES[3])
    assert (found["table"] == "conditioning").sum() == len(conditioning)
    row = found[(found.table == "main_table") & (found.row == "hierarchical") & (found.measure == "fvd_heldout")]
    assert row[["low", "high", "n"]].iloc[0].tolist() == pytest.approx(
        pd.read_csv(TABLES[0]).set_index("model").loc["hierarchical", ["fvd_heldout_low", "fvd_heldout_high",
                                                                       "fvd_heldout_n"]].tolist())
    assert (found["low"] <= found["high"]).all()
    assert plot_intervals(found, tmp_path / "forest.png").read_bytes().startswith(b"\x89PNG")
    times = pd.read_csv(write_stage_times({"town": 3.0, "shards": 9.5}, tmp_path / "times.csv"))
    assert times["stage"].tolist() == ["shards", "town"]


def test_the_gallery_shows_real_beside_generated_at_a_watchable_size():
    real = np.zeros((3, 72, 128, 3), np.uint8)
    generated = np.full((3, 72, 128, 3), 200, np.uint8)
    frames = gallery_frames(real, generated)
    assert frames.shape == (3, 288, 1024, 3)  # x4: the smoke profile's 72-px frames, at least 256 px tall
    assert (frames[:, :, :512] == 0).all() and (frames[:, :, 512:] == 200).all()
    assert gallery_frames(real[:, :64], generated[:, :64]).shape[1] == 256
    three = gallery_frames(real, np.full_like(real, 100), generated)  # real | tokenizer | model
    assert three.shape == (3, 288, 1536, 3) and (three[:, :, 512:1024] == 100).all()
