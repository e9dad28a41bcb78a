"""`orbis2 evaluate`: known answers on video folders (identical sets, shuffled pairs), the protocols, bad input."""

import csv
import json
import runpy
import sqlite3

import numpy as np
import pytest
import torch
from torch import nn

from orbis2.cli import main
from orbis2.config.params import load_config
from orbis2.data.video import read_video, write_video
from orbis2.errors import OrbisError
from orbis2.eval import records
from orbis2.eval.evaluate_records import EvaluateRecord
from orbis2.eval.protocols.evaluate import (
    EvaluateError,
    Protocol,
    context_frames,
    evaluate_pairs,
    format_table,
    pairs_from_folders,
    pairs_from_manifest,
    protocol,
)
from orbis2.eval.protocols.evaluate_steering import add_steering
from orbis2.eval.protocols.evaluate_videos import read_rollout_folder
from orbis2.kinematics import integrate_controls

from conftest import ROOT, run

FPS, CONTEXT, FRAMES = 10, 3, 32  # 3 context frames, then 3.2 s of continuation
PROTO = Protocol("test", seconds=1.6, long_seconds=3.2, chunk_seconds=1.6, bootstrap_reps=20, seed=0, floor_splits=5)


@pytest.fixture(autouse=True)
def small_i3d_input(monkeypatch):
    """Resize to 32x32 instead of 224x224 for the stand-in below: the same code path, a fiftieth of the work."""
    monkeypatch.setattr("orbis2.eval.metrics.fvd.I3D_SIZE", 32)


class PooledPixels(nn.Module):
    """Stand-in for I3D (fast, deterministic): colour means over a coarse space-time grid, 48 features."""

    def __init__(self):
        super().__init__()
        self.anchor = nn.Parameter(torch.zeros(()))

    def forward(self, video: torch.Tensor) -> torch.Tensor:
        return nn.functional.adaptive_avg_pool3d(video, (4, 2, 2)).flatten(1) + self.anchor


def scene(seed: int, frames: int) -> np.ndarray:
    """A drive-like clip [T, 48, 64, 3]: a random colour gradient sliding sideways, one bright block moving."""
    rng = np.random.default_rng(seed)
    y, x = np.mgrid[0:48, 0:64]
    colours, speed = rng.uniform(30, 220, (2, 3)), rng.uniform(0.5, 2.0)
    video = []
    for t in range(frames):
        mix = ((x + speed * t) % 64 / 63.0)[..., None]
        frame = colours[0] * (1 - mix) + colours[1] * mix
        r, c = int(8 + rng.integers(0, 2) + t % 20), int(10 + 1.5 * t) % 50
        frame[r : r + 10, c : c + 10] = 250
        video.append(frame)
    return np.clip(np.stack(video), 0, 255).astype(np.uint8)


def write_set(root, n=8, noise=0.0, shuffle=False):
    """Real videos (context + truth) and generated continuations in two folders, paired by name."""
    rng = np.random.default_rng(1)
    order = rng.permutation(n) if shuffle else np.arange(n)
    for i in range(n):
        real = scene(i, CONTEXT + FRAMES)
        write_video(root / "real" / f"{i:02d}.mkv", real, FPS, lossless=True)
        fake = scene(int(order[i]), CONTEXT + FRAMES)[CONTEXT:].astype(np.float64)
        fake = np.clip(fake + rng.normal(0, noise, fake.shape), 0, 255).astype(np.uint8) if noise else fake
        write_video(root / "generated" / f"{i:02d}.mkv", fake.astype(np.uint8), FPS, lossless=True)
    return pairs_from_folders(root / "generated", root / "real")


def test_lossless_videos_read_back_bit_for_bit(tmp_path):
    frames = scene(0, 5)
    write_video(tmp_path / "a.mkv", frames, FPS, lossless=True)
    assert np.array_equal(read_video(tmp_path / "a.mkv"), frames)


def test_identical_folders_score_zero_beside_a_positive_floor(tmp_path):
    record = evaluate_pairs(write_set(tmp_path), CONTEXT, PROTO, PooledPixels(), "sha")
    assert abs(record.fvd.fvd) < 1e-6
    assert record.fvd.low == pytest.approx(0, abs=1e-6) and record.fvd.high == pytest.approx(0, abs=1e-6)
    floor = record.references.real_floor
    assert floor.fvd > 1.0 and floor.half_splits == 5
    assert record.references.repeat_last.fvd > 0.1  # a still frame is not the continuation
    assert [c.fvd for c in record.chunked.chunks] == pytest.approx([0, 0], abs=1e-6)
    assert record.pairing.matched == 8
    assert not any("shuffled" in w for w in record.warnings)
    assert any("rank-deficient" in w for w in record.warnings)  # 8 videos cannot resolve much
    card = record.protocol
    assert (card.fps, card.context_frames, card.videos, card.clips, card.i3d_frames) == (10, 3, 8, 8, 16)
    assert "protocol:" in format_table(record)


def test_noisy_rollouts_score_above_zero_and_shuffled_pairs_are_detected(tmp_path):
    noisy = evaluate_pairs(write_set(tmp_path / "noisy", noise=20), CONTEXT, PROTO, PooledPixels(), "sha")
    assert noisy.fvd.fvd > 1e-3 and noisy.pairing.matched == 8
    shuffled = evaluate_pairs(write_set(tmp_path / "shuffled", shuffle=True), CONTEXT, PROTO, PooledPixels(), "sha")
    assert abs(shuffled.fvd.fvd) < 1e-6  # FVD compares sets: the same set in any order scores the same
    assert shuffled.pairing.matched <= 2
    assert "look shuffled" in shuffled.warnings[0]


def test_manifest_groups_rows_by_clip_and_context_frames_can_lead_the_rollouts(tmp_path):
    pairs = write_set(tmp_path)
    for pair in pairs:  # rollouts that repeat the context before the continuation
        write_video(pair.generated, scene(int(pair.name), CONTEXT + FRAMES), FPS, lossless=True)
    with (tmp_path / "manifest.csv").open("w", newline="") as f:
        writer = csv.writer(f)
        writer.writerow(["name", "generated", "real", "clip", "context_frames"])
        writer.writerows([p.name, f"generated/{p.name}.mkv", f"real/{p.name}.mkv", f"ep{int(p.name) // 2}", CONTEXT]
                         for p in pairs)
    from_manifest = pairs_from_manifest(tmp_path / "manifest.csv")
    assert context_frames(from_manifest, None, tmp_path / "manifest.csv") == CONTEXT
    with pytest.raises(EvaluateError, match="pass --context-frames"):
        context_frames(pairs, None, None)
    record = evaluate_pairs(from_manifest, CONTEXT, PROTO, PooledPixels(), "sha", generated_has_context=True)
    assert abs(record.fvd.fvd) < 1e-6
    assert (record.fvd.clips, record.fvd.videos, record.protocol.clips) == (4, 8, 4)
    assert record.pairing.matched == 8
    # without the flag the context frames are scored as if generated: the first frames no longer match
    shifted = evaluate_pairs(from_manifest, CONTEXT, PROTO, PooledPixels(), "sha")
    assert shifted.fvd.fvd > 1e-3


def test_paper_protocol_needs_its_six_seconds(tmp_path):
    class Ev:
        fvd_bootstrap_reps, seed, floor_splits, seconds, long_seconds, chunk_seconds = 20, 0, 5, 1.6, 3.2, 1.6

    paper = protocol("paper", Ev)
    assert (paper.seconds, paper.long_seconds, paper.chunk_seconds) == (6.0, 16.0, 4.0)
    assert len(paper.chunks(10)[0]) == 4
    short = Protocol("short", 1.6, 6.4, 1.6, 20, 0, 5)
    assert "no chunked FVD" in evaluate_pairs(write_set(tmp_path / "s"), CONTEXT, short, PooledPixels(),
                                              "sha").warnings[-1]
    with pytest.raises(EvaluateError, match="6 s = 60 frames"):
        evaluate_pairs(write_set(tmp_path), CONTEXT, paper, PooledPixels(), "sha")


def test_bad_input_stops_with_the_file_and_the_fix(tmp_path, capsys):
    write_set(tmp_path)
    (tmp_path / "real" / "03.mkv").unlink()
    with pytest.raises(SystemExit) as exit_info:
        main(["evaluate", "--generated", str(tmp_path / "generated"), "--real", str(tmp_path / "real"),
              "--context-frames", "3"])
    assert exit_info.value.code == 2
    err = capsys.readouterr().err
    assert "real: no real video named '03'" in err and "name each real video" in err
    (tmp_path / "bad.csv").write_text("name,generated\na,generated/00.mkv\n")
    with pytest.raises(EvaluateError, match=r"bad.csv: missing column\(s\) \['real'\]"):
        pairs_from_manifest(tmp_path / "bad.csv")
    short = write_set(tmp_path / "short")
    write_video(short[0].real, scene(0, CONTEXT + 10), FPS, lossless=True)
    with pytest.raises(EvaluateError, match="00.mkv: 13 frames, but the protocol needs"):
        evaluate_pairs(short, CONTEXT, PROTO, PooledPixels(), "sha")


def test_a_short_rollout_among_long_ones_is_refused_by_name(tmp_path):
    """One 20-frame rollout among 32-frame ones would drop every rollout's chunked FVD and FVD-slope."""
    pairs = write_set(tmp_path)
    write_video(pairs[5].generated, scene(5, 20), FPS, lossless=True)
    with pytest.raises(EvaluateError, match=r"generated/05.mkv \(20 frames\): shorter than the 32 generated frames"
                                            r" the other rollouts are scored on \(FVD, chunked FVD and FVD-slope\)"):
        evaluate_pairs(pairs, CONTEXT, PROTO, PooledPixels(), "sha")


class LeftArc:
    """Stand-in instrument: reads every video as a 10 m/s left arc at 0.3 rad/s (the interface's [T, 2] positions)."""

    def __call__(self, frames, K):
        return integrate_controls(np.full(len(frames) - 1, 10.0), np.full(len(frames) - 1, 0.3), 1 / FPS)[:len(frames)]


def test_trajectories_give_steering_ade_and_the_signed_turn(tmp_path):
    pairs = write_set(tmp_path)
    for n, pair in enumerate(pairs):  # half command the arc the instrument reads, half its mirror image
        yaw = 0.3 if n % 2 == 0 else -0.3
        pair.generated.with_suffix(".csv").write_text(
            "timestamp,speed,yaw_rate\n" + "".join(f"{t / FPS:.2f},10.0,{yaw}\n" for t in range(FRAMES)))
    pairs = pairs_from_folders(tmp_path / "generated", tmp_path / "real")
    assert all(p.trajectory is not None for p in pairs)
    record = evaluate_pairs(pairs, CONTEXT, PROTO, PooledPixels(), "sha")
    record = add_steering(record, pairs, PROTO, False, LeftArc(), "left-arc", 90.0)
    steering = record.steering
    commanded = np.degrees(0.3 * 15 / FPS) / 2  # end-point angle of the 1.5-s arc: half its heading change
    assert steering.commanded_turn_deg.estimate == pytest.approx(commanded, rel=1e-6)
    assert steering.turn_deg.estimate == pytest.approx(0.0, abs=1e-6)  # +turn for half, -turn for the rest
    assert steering.ade_m.estimate > 0.5 and steering.ade_m.low <= steering.ade_m.high
    assert "steering (left-arc)" in format_table(record)
    pairs[0].trajectory.write_text("timestamp,speed,yaw_rate\n0,10,0.3\n0.5,10,0.3\n")
    with pytest.raises(EvaluateError, match="00.csv: covers 0-0.5 s, but the scored window needs 0-1.5 s"):
        add_steering(record, pairs, PROTO, False, LeftArc(), "left-arc", 90.0)


def test_a_written_record_reads_back_and_rewrites_byte_for_byte(tmp_path, monkeypatch):
    """The record `orbis2 evaluate --out` writes (here with steering scores and trajectories) validates strictly and
    dumps to the same bytes, so a published record keeps its hash; a renamed key stops the read naming it."""
    pairs = write_set(tmp_path / "set")
    for pair in pairs:
        pair.generated.with_suffix(".csv").write_text(
            "timestamp,speed,yaw_rate\n" + "".join(f"{t / FPS:.2f},10.0,0.3\n" for t in range(FRAMES)))
    pairs = pairs_from_folders(tmp_path / "set/generated", tmp_path / "set/real")
    steered = add_steering(evaluate_pairs(pairs, CONTEXT, PROTO, PooledPixels(), "sha"), pairs, PROTO, False,
                           LeftArc(), "left-arc", 90.0)
    records.write_record(tmp_path / "steered.json", steered)
    monkeypatch.setattr("orbis2.eval.protocols.evaluate_videos.load_i3d", lambda path: PooledPixels())
    (tmp_path / "i3d.pt").write_bytes(b"stand-in")
    main(["evaluate", "--generated", str(tmp_path / "set/generated"), "--real", str(tmp_path / "set/real"),
          "--context-frames", str(CONTEXT), "--i3d", str(tmp_path / "i3d.pt"), "--params", str(ROOT / "params.yaml"),
          "--profile", "smoke", "--instrument", "opencv", "--out", str(tmp_path / "cli.json")])
    for name in ("steered.json", "cli.json"):
        written = (tmp_path / name).read_text()
        record = EvaluateRecord.model_validate_json(written)
        records.write_record(tmp_path / f"again_{name}", record)
        assert (tmp_path / f"again_{name}").read_text() == written
    assert steered.steering is not None and steered.videos[0].trajectory.endswith("00.csv")
    doc = json.loads((tmp_path / "cli.json").read_text())
    doc["pairing"]["matches"] = doc["pairing"].pop("matched")
    (tmp_path / "renamed.json").write_text(json.dumps(doc))
    with pytest.raises(OrbisError, match=r"renamed.json \(written by stage evaluate\) is not a EvaluateRecord: "
                                         r"pairing.matched: missing key; pairing.matches: unknown key"):
        records.from_json(EvaluateRecord, tmp_path / "renamed.json", "evaluate")


def run_stage(argv, monkeypatch, tmp_path):
    """stages/evaluate.py's main in this process (so the stand-in I3D is used), tracked in a store under tmp_path."""
    monkeypatch.setenv("MLFLOW_TRACKING_URI", f"sqlite:///{tmp_path / 'mlflow.db'}")
    monkeypatch.delenv("ORBIS2_PIPELINE_ID", raising=False)
    monkeypatch.setattr("orbis2.eval.protocols.evaluate_videos.load_i3d", lambda path: PooledPixels())
    monkeypatch.chdir(tmp_path)
    (tmp_path / "i3d.pt").write_bytes(b"stand-in")
    stage = runpy.run_path(str(ROOT / "stages/evaluate.py"), run_name="evaluate_stage")
    stage["main"](["--params", str(ROOT / "params.yaml"), "--profile", "smoke", "--i3d", "i3d.pt", *argv])


def test_the_evaluate_stage_scores_a_rollout_folder_and_logs_one_run(tmp_path, monkeypatch):
    """data/rollouts/<name>/ with its options file -> the record of the same code, the table, the figure, one run."""
    folder = tmp_path / "data/rollouts/mine"
    pairs = write_set(folder, noise=20)
    (folder / "evaluate.yaml").write_text(f"context_frames: {CONTEXT}\nsplit: turns\n")
    run_stage(["--rollouts", "data/rollouts/mine"], monkeypatch, tmp_path)
    out = tmp_path / "reports/evaluate/mine"
    record = records.from_json(EvaluateRecord, out / "fvd.json", "evaluate_mine")
    smoke = protocol("orbis2", load_config(ROOT / "params.yaml", "smoke").evaluation)
    assert (record.protocol.seconds, record.protocol.context_frames) == (smoke.seconds, CONTEXT)
    expected = evaluate_pairs(pairs, CONTEXT, smoke, PooledPixels(), record.protocol.i3d_sha256, split="turns")
    assert record.fvd.fvd == pytest.approx(expected.fvd.fvd) and record.fvd.fvd > 1e-3
    assert record.fvd.draws == pytest.approx(expected.fvd.draws)
    table = (out / "table.txt").read_text()
    assert table.splitlines()[0] == format_table(record).splitlines()[0] and "protocol: protocol=orbis2" in table
    assert (out / "fvd.png").read_bytes()[:4] == b"\x89PNG"
    with sqlite3.connect(tmp_path / "mlflow.db") as con:
        runs = dict(con.execute("select name, run_uuid from runs where name like 'evaluate_%'"))
        metrics = dict(con.execute("select key, value from metrics where run_uuid = ?", (runs["evaluate_mine"],)))
    assert list(runs) == ["evaluate_mine"] and metrics["fvd"] == pytest.approx(record.fvd.fvd)

    (folder / "evaluate.yaml").write_text("context_frame: 3\n")
    with pytest.raises(SystemExit) as exit_info:
        run_stage(["--rollouts", "data/rollouts/mine"], monkeypatch, tmp_path)
    assert exit_info.value.code == 2


def test_a_folder_without_rollouts_or_with_a_misspelt_option_names_the_fix(tmp_path):
    (tmp_path / "empty").mkdir()
    with pytest.raises(EvaluateError, match="empty: holds neither manifest.csv nor the folders generated/ and real/"):
        read_rollout_folder(tmp_path / "empty")
    write_set(tmp_path / "mine")
    (tmp_path / "mine/evaluate.yaml").write_text("context_frame: 3\n")
    with pytest.raises(EvaluateError, match=r"evaluate.yaml: unknown option\(s\) \['context_frame'\]"):
        read_rollout_folder(tmp_path / "mine")


def test_the_rule_reads_the_folder_and_the_instrument_only_for_trajectories(tmp_path):
    """`snakemake -n reports/evaluate/<name>/fvd.json` plans the stage on data/rollouts/<name>/, with the learned
    instrument (and the stage that trains it) only when the rollouts come with trajectories."""
    for name in ("Snakefile", "params.yaml", "params.schema.yaml", "registry.yaml", "rules", "src", "stages"):
        (tmp_path / name).symlink_to(ROOT / name)  # what the DAG reads; outputs and rollouts stay in tmp_path
    pairs = write_set(tmp_path / "data/rollouts/plain", n=2)
    write_set(tmp_path / "data/rollouts/steered", n=2)
    for pair in pairs:
        (tmp_path / "data/rollouts/steered/generated" / f"{pair.name}.csv").write_text("timestamp,speed,yaw_rate\n")
    out = run(["snakemake", "-n", "-p", "--cores", "1", "reports/evaluate/plain/fvd.json",
               "reports/evaluate/steered/fvd.json"], tmp_path)
    commands = [line.removeprefix("Shell command: ") for line in out.splitlines()
                if line.startswith("Shell command: python stages/")]
    evaluate = {line.split("--rollouts data/rollouts/")[1].split()[0]: line
                for line in commands if line.startswith("python stages/evaluate.py")}
    assert "--assets data/assets --fvd reports/evaluate/plain/fvd.json --table reports/evaluate/plain/table.txt" \
        in evaluate["plain"]
    assert "--instrument data/inverse_dynamics --fvd reports/evaluate/steered/fvd.json" in evaluate["steered"]
    assert any(line.startswith("python stages/inverse_dynamics.py") for line in commands)
