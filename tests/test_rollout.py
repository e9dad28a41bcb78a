"""Rollouts: window bookkeeping against hand-computed tables, conditioning wiring, the CLI."""

from __future__ import annotations

import csv
from pathlib import Path

import numpy as np
import pytest
import torch
from PIL import Image

from orbis2.cli import main
from orbis2.config.params import load_config
from orbis2.config.sections import DataConfig
from orbis2.data.video import codec_of, read_video
from orbis2.models.files import save_predictor, save_tokenizer
from orbis2.models.stdit import build_stdit, build_stdit_from
from orbis2.models.tokenizer import build_abstract_tokenizer, build_detail_tokenizer
from orbis2.rollout import (
    cascaded_rollout,
    detail_frames_per_step,
    first_context_end,
    flat_rollout,
    rollout_schedule,
    steering_sequences,
)

ROOT = Path(__file__).resolve().parents[1]
DATA = load_config(ROOT / "params.yaml", "smoke").data
RATES = {"abstract_hz": DATA.abstract_hz, "detail_hz": DATA.detail_hz}  # the rollout's: params.yaml's data section

# (detail context, detail target, abstract context, abstract target, steering), worked out by hand.
TABLE_10HZ = [  # fps 10: detail stride 1, abstract stride 5, last context frame 20
    ((16, 17, 18, 19, 20), (21, 22, 23, 24, 25), (0, 5, 10, 15, 20), 25, (20, 21, 22, 23, 24)),
    ((21, 22, 23, 24, 25), (26, 27, 28, 29, 30), (5, 10, 15, 20, 25), 30, (25, 26, 27, 28, 29)),
    ((26, 27, 28, 29, 30), (31, 32, 33, 34, 35), (10, 15, 20, 25, 30), 35, (30, 31, 32, 33, 34)),
]
TABLE_20HZ = [  # fps 20: detail stride 2, abstract stride 10, last context frame 40
    ((32, 34, 36, 38, 40), (42, 44, 46, 48, 50), (0, 10, 20, 30, 40), 50, tuple(range(40, 50))),
    ((42, 44, 46, 48, 50), (52, 54, 56, 58, 60), (10, 20, 30, 40, 50), 60, tuple(range(50, 60))),
    ((52, 54, 56, 58, 60), (62, 64, 66, 68, 70), (20, 30, 40, 50, 60), 70, tuple(range(60, 70))),
]


def hierarchy(fps: int) -> DataConfig:
    """The paper's two rates and windows (10 Hz detail 5+5, 2 Hz abstract 5+1) over a native rate of ``fps``."""
    return DataConfig(width=128, height=72, fps=fps, source="town", detail_hz=10, abstract_hz=2, detail_window=10,
                      detail_context=5, abstract_window=6, abstract_context=5)


@pytest.mark.parametrize("fps, context_end, table", [(10, 20, TABLE_10HZ), (20, 40, TABLE_20HZ)])
def test_schedule_matches_hand_table(fps, context_end, table):
    data = hierarchy(fps)
    assert first_context_end(data) == context_end
    schedule = rollout_schedule(data, context_end, len(table))
    got = [(s.detail_context, s.detail_target, s.abstract_context, s.abstract_target, s.steering) for s in schedule]
    assert got == table


def test_schedule_later_start_shifts_everything_and_early_start_fails():
    data = hierarchy(10)
    shifted = rollout_schedule(data, 27, 2)
    assert shifted[1].abstract_context == (12, 17, 22, 27, 32) and shifted[1].abstract_target == 37
    with pytest.raises(ValueError, match="needs >= 20"):
        rollout_schedule(data, 19, 1)


def test_steering_sequences_sample_the_schedule():
    data = hierarchy(10)
    schedule = rollout_schedule(data, 20, 2)
    speed, yaw = np.arange(40.0), -np.arange(40.0)
    seq = steering_sequences(schedule, speed, yaw, (2.0, 1.0))
    assert seq.shape == (2, 5, 2)
    assert seq[1, :, 0].tolist() == [12.5, 13.0, 13.5, 14.0, 14.5]
    assert seq[0, :, 1].tolist() == [-20.0, -21.0, -22.0, -23.0, -24.0]


# --------------------------------------------------------------------------- stub models


def _exact_velocity(x, tau, x0):
    """The velocity whose Euler step lands on ``x0`` at tau = 0: (x_tau - x0) / tau on target frames."""
    n_ctx = int((tau[0] == 0).sum())
    v = torch.zeros_like(x)
    t = tau[:, n_ctx:, None, None, None]
    v[:, n_ctx:] = (x[:, n_ctx:] - x0) / t
    return v, n_ctx


class AbstractStub:
    """Predicts last context latent + 1; records rates and steering."""

    def __init__(self):
        self.calls = []

    def __call__(self, x, tau, frame_rate=None, steering=None):
        n_ctx = n_ctx_of(tau)
        v, _ = _exact_velocity(x, tau, x[:, n_ctx - 1: n_ctx] + 1)
        self.calls.append({"rate": frame_rate, "steering": steering, "context": x[:, :n_ctx].clone()})
        return v


class DetailStub:
    """Target frame j = subgoal slot + j; records the conditioning and the context."""

    def __init__(self):
        self.calls = []

    def __call__(self, x, tau, frame_rate=None, cond_frames=None, cond_mask=None):
        n_ctx = n_ctx_of(tau)
        offsets = torch.arange(x.shape[1] - n_ctx, dtype=x.dtype)[None, :, None, None, None]
        v, _ = _exact_velocity(x, tau, cond_frames[:, -1:] + offsets)
        self.calls.append({"rate": frame_rate, "cond": cond_frames.clone(), "mask": cond_mask,
                           "context": x[:, :n_ctx].clone()})
        return v


def n_ctx_of(tau):
    return int((tau[0] == 0).sum())


def _ramp(n, shape=(2, 3, 4)):
    """[1, n, *shape] with frame i filled with the value i."""
    return torch.arange(n, dtype=torch.float32)[None, :, None, None, None].expand(1, n, *shape).clone()


def test_cascaded_rollout_pushes_subgoals_and_places_conditioning():
    abstract, detail = AbstractStub(), DetailStub()
    steps, nfe = 3, 4
    steering = torch.randn(1, steps, 5, 2)
    seen = []
    details, subgoals = cascaded_rollout(abstract, detail, _ramp(5) + 100, _ramp(5), steps, torch.Generator(),
                                         abstract_nfe=nfe, detail_nfe=nfe, **RATES, steering=steering,
                                         on_step=seen.append)
    assert seen == [0, 1, 2]
    assert details.shape == (1, 15, 2, 3, 4) and subgoals.shape == (1, 3, 2, 3, 4)
    # Subgoal k = last abstract context + 1, and it becomes context: 5, 6, 7 (not 5, 5, 5).
    torch.testing.assert_close(subgoals[0, :, 0, 0, 0], torch.tensor([5.0, 6.0, 7.0]))
    assert abstract.calls[nfe]["context"][0, :, 0, 0, 0].tolist() == [1, 2, 3, 4, 5]
    for k in range(steps):
        first_abstract, first_detail = abstract.calls[k * nfe], detail.calls[k * nfe]
        assert first_abstract["rate"] == 2.0 and first_detail["rate"] == 10.0
        torch.testing.assert_close(first_abstract["steering"], steering[:, k])
        assert tuple(first_detail["mask"]) == (4, 9)  # the conditioned slots, passed as slots
        cond = first_detail["cond"][0, :, 0, 0, 0]
        expected = torch.zeros(10)
        expected[4], expected[9] = 4 + k, 5 + k  # last abstract context, then the subgoal
        torch.testing.assert_close(cond, expected)
        torch.testing.assert_close(details[0, 5 * k: 5 * k + 5, 0, 0, 0], 5 + k + torch.arange(5.0))
    # The detail window slid by 5: step 1's context is step 0's output.
    torch.testing.assert_close(detail.calls[nfe]["context"], details[:, :5])


def test_the_detail_frames_per_step_follow_from_the_rates():
    """params.yaml's rates give the detail predictor's new frames; Exp. 5's 10-Hz top of 5 frames gives the same."""
    assert detail_frames_per_step(DATA.detail_hz, DATA.abstract_hz) == DATA.detail_window - DATA.detail_context == 5
    assert detail_frames_per_step(10.0, 10.0, 5) == 5 and detail_frames_per_step(10, 5) == 2
    with pytest.raises(ValueError, match="is 2.5 detail frames per step"):
        detail_frames_per_step(10, 4)
    with pytest.raises(ValueError, match="is 2.5 detail frames per step"):
        cascaded_rollout(AbstractStub(), DetailStub(), _ramp(5), _ramp(5), 1, torch.Generator(), abstract_hz=4,
                         detail_hz=10)


def test_cascaded_rollout_with_given_subgoals_skips_the_top_and_conditions_on_them():
    abstract, detail = AbstractStub(), DetailStub()
    given = torch.tensor([40.0, 50.0, 60.0])[None, :, None, None, None].expand(1, 3, 2, 3, 4)
    details, tops = cascaded_rollout(abstract, detail, _ramp(5) + 100, _ramp(5), 3, torch.Generator(),
                                     abstract_nfe=2, detail_nfe=2, **RATES, subgoals=given)
    assert abstract.calls == []  # the top predictor never runs
    torch.testing.assert_close(tops, given)
    for k in range(3):
        cond = detail.calls[2 * k]["cond"][0, :, 0, 0, 0]
        assert (cond[4], cond[9]) == ((4.0, 40.0, 50.0)[k], (40.0, 50.0, 60.0)[k])  # given subgoals become context
        torch.testing.assert_close(details[0, 5 * k: 5 * k + 5, 0, 0, 0], given[0, k, 0, 0, 0] + torch.arange(5.0))
    with pytest.raises(ValueError, match="subgoals must hold 3 frames"):
        cascaded_rollout(abstract, detail, _ramp(5), _ramp(5), 3, torch.Generator(), **RATES,
                         subgoals=given[:, :2])


def test_flat_rollout_slides_the_same_window():
    def model(x, tau, frame_rate=None):
        n_ctx = n_ctx_of(tau)
        offsets = 1 + torch.arange(x.shape[1] - n_ctx, dtype=x.dtype)[None, :, None, None, None]
        return _exact_velocity(x, tau, x[:, n_ctx - 1: n_ctx] + offsets)[0]

    out = flat_rollout(model, _ramp(5), steps=3, frames_per_step=2, nfe=3, frame_rate=10, generator=torch.Generator())
    torch.testing.assert_close(out[0, :, 0, 0, 0], torch.arange(5.0, 11.0))


def test_cascaded_rollout_smoke_models_shapes_and_determinism():
    torch.manual_seed(0)
    abstract = build_stdit("smoke", latent_channels=4, causal=True, steering=True).eval()
    detail = build_stdit("smoke", latent_channels=6, causal=False, abstract_channels=4).eval()
    for model in (abstract, detail):  # DiT init zeroes the output layer: perturb it so samples depend on the input
        torch.nn.init.normal_(model.final_layer.linear.weight, std=0.1)
    d_ctx, a_ctx = torch.randn(2, 5, 6, 4, 5), torch.randn(2, 5, 4, 2, 3)
    steering = torch.randn(2, 2, 5, 2)

    def run(seed):
        return cascaded_rollout(abstract, detail, d_ctx, a_ctx, 2, torch.Generator().manual_seed(seed),
                                abstract_nfe=2, detail_nfe=2, **RATES, steering=steering)

    (d1, a1), (d2, a2), (d3, _) = run(0), run(0), run(1)
    assert d1.shape == (2, 10, 6, 4, 5) and a1.shape == (2, 2, 4, 2, 3)
    assert torch.equal(d1, d2) and torch.equal(a1, a2)
    assert not torch.equal(d1, d3)
    with pytest.raises(ValueError, match="steering must be"):
        cascaded_rollout(abstract, detail, d_ctx, a_ctx, 3, torch.Generator(), abstract_nfe=1, detail_nfe=1,
                         **RATES, steering=steering)


class SteeredStub:
    """Predicts last context latent + 1, plus the mean steering value when steered."""

    def __call__(self, x, tau, frame_rate=None, steering=None):
        n_ctx = n_ctx_of(tau)
        shift = 0.0 if steering is None else float(steering.mean())
        return _exact_velocity(x, tau, x[:, n_ctx - 1: n_ctx] + 1 + shift)[0]


@pytest.mark.parametrize("guidance", [0.0, 1.0, 3.0])
def test_steering_guidance_extrapolates_the_steered_prediction(guidance):
    """Known answer: the unsteered subgoal is last + 1, the steered one last + 1.5; guidance w lands on
    last + 1 + 0.5 w (the velocities are exact, so Euler reaches the guided target)."""
    steering = torch.full((1, 2, 5, 2), 0.5)
    _, tops = cascaded_rollout(SteeredStub(), DetailStub(), _ramp(5) + 100, _ramp(5), 2, torch.Generator(),
                               abstract_nfe=3, detail_nfe=2, **RATES, steering=steering, steering_guidance=guidance)
    step = 1 + 0.5 * guidance
    torch.testing.assert_close(tops[0, :, 0, 0, 0], torch.tensor([4 + step, 4 + 2 * step]))


def test_steering_guidance_on_a_steered_predictor_one_is_plain_and_zero_is_unsteered():
    torch.manual_seed(0)
    abstract = build_stdit_from({"preset": "smoke", "steering_shift": True, "latent_channels": 4, "causal": True,
                                 "steering": True}).eval()
    detail = build_stdit("smoke", latent_channels=6, causal=False, abstract_channels=4).eval()
    for module in (abstract.final_layer.linear, abstract.steering.out, abstract.steering_shift.embed,
                   detail.final_layer.linear):  # zero at init: perturb so that samples depend on the steering
        torch.nn.init.normal_(module.weight, std=0.1)
    d_ctx, a_ctx = torch.randn(2, 5, 6, 4, 5), torch.randn(2, 5, 4, 2, 3)
    steering = torch.randn(2, 2, 5, 2)

    def run(guidance, steer=steering, kv_cache=True):
        return cascaded_rollout(abstract, detail, d_ctx, a_ctx, 2, torch.Generator().manual_seed(0), abstract_nfe=2,
                                detail_nfe=2, **RATES, steering=steer, steering_guidance=guidance,
                                kv_cache=kv_cache)[1]

    plain, free = run(1.0), run(1.0, steer=None)
    assert torch.equal(run(1.0), plain) and not torch.allclose(plain, free)
    torch.testing.assert_close(run(0.0), free, rtol=0, atol=1e-6)
    guided = run(2.0)
    torch.testing.assert_close(guided, run(2.0, kv_cache=False), rtol=1e-4, atol=1e-5)
    assert (guided - free).norm() > (plain - free).norm()  # extrapolated beyond the steered rollout


# --------------------------------------------------------------------------- CLI


@pytest.fixture(scope="module")
def checkpoints(tmp_path_factory):
    """Random-weight smoke tokenizers and predictors, saved the way the training stages save them."""
    root = tmp_path_factory.mktemp("ckpt")
    torch.manual_seed(0)
    paths = {"detail_tok": root / "detail_tok.pt", "abstract_tok": root / "abstract_tok.pt",
             "abstract": root / "abstract.pt", "detail": root / "detail.pt"}
    save_tokenizer(paths["detail_tok"], "detail", build_detail_tokenizer("smoke"), 4.0, {"preset": "smoke"})
    save_tokenizer(paths["abstract_tok"], "abstract", build_abstract_tokenizer("smoke", teacher_dim=32),
                   3.45, {"preset": "smoke", "teacher_dim": 32, "compress": True})
    abstract_build = {"preset": "smoke", "latent_channels": 16, "causal": True, "steering": True}
    detail_build = {"preset": "smoke", "latent_channels": 16, "causal": False, "abstract_channels": 16}
    save_predictor(paths["abstract"], build_stdit_from(abstract_build), abstract_build,
                   {"steering": {"scale": [10.0, 0.2]}})  # what the action stage records
    save_predictor(paths["detail"], build_stdit_from(detail_build), detail_build, {})
    return paths


def _args(video, out, ckpt, *extra):
    return ["rollout", "--video", str(video), "--out", str(out), "--params", str(ROOT / "params.yaml"),
            "--profile", "smoke", "--detail-tokenizer", str(ckpt["detail_tok"]),
            "--abstract-tokenizer", str(ckpt["abstract_tok"]), "--abstract-predictor", str(ckpt["abstract"]),
            "--detail-predictor", str(ckpt["detail"]), "--abstract-nfe", "1", "--detail-nfe", "1",
            "--device", "cpu", *map(str, extra)]


def _write_csv(path, header, rows):
    with open(path, "w", newline="") as handle:
        writer = csv.writer(handle)
        writer.writerow(header)
        writer.writerows(rows)
    return path


def _expect_exit_2(argv, capsys, *fragments):
    with pytest.raises(SystemExit) as exit_info:
        main(argv)
    assert exit_info.value.code == 2
    err = capsys.readouterr().err
    assert "Traceback" not in err
    for fragment in fragments:
        assert fragment in err, err
    return err


def test_cli_rejects_a_video_too_short_for_the_context(make_video, tmp_path, checkpoints, capsys):
    video = make_video("short.mp4", 20, 10)  # 21 frames needed: 2 s + 1 frame
    _expect_exit_2(_args(video, tmp_path / "o.mp4", checkpoints), capsys, str(video), "needs 21 frames",
                   "longer video")


def test_cli_rejects_a_trajectory_with_bad_columns(make_video, tmp_path, checkpoints, capsys):
    video = make_video("v.mp4", 25, 10)
    traj = _write_csv(tmp_path / "traj.csv", ["time", "v", "w"], [[0, 1, 0], [1, 1, 0]])
    _expect_exit_2(_args(video, tmp_path / "o.mp4", checkpoints, "--trajectory", traj), capsys, str(traj),
                   "missing column")


def test_cli_rejects_missing_and_mismatched_checkpoints(make_video, tmp_path, checkpoints, capsys):
    video = make_video("v.mp4", 25, 10)
    missing = tmp_path / "nope" / "predictor.pt"
    _expect_exit_2(_args(video, tmp_path / "o.mp4", checkpoints) + ["--detail-predictor", str(missing)], capsys,
                   str(missing), "not found")
    other = tmp_path / "other.pt"
    build = {"preset": "smoke", "latent_channels": 16, "causal": False, "abstract_channels": 16}
    save_predictor(other, build_stdit_from(build), build, {"tokenizers": {"detail": {"checksum": "0" * 64}}})
    _expect_exit_2(_args(video, tmp_path / "o.mp4", checkpoints) + ["--detail-predictor", str(other)], capsys,
                   str(other), "--detail-tokenizer")


def test_cli_end_to_end_writes_mp4_and_gif(make_video, tmp_path, checkpoints, capsys):
    video = make_video("drive.mp4", 50, 20)  # 20 fps source, resampled to the profile's 10 fps
    traj = _write_csv(tmp_path / "traj.csv", ["timestamp", "speed", "yaw_rate"],
                      [[t / 10, 5.0, 0.2] for t in range(40)])
    out = tmp_path / "out" / "rollout.mp4"
    main(_args(video, out, checkpoints, "--trajectory", traj, "--seconds", 1, "--side-by-side",
               "--yaw-rate-scale", 1.5))
    assert "steered by" in capsys.readouterr().out
    assert codec_of(out) == "VP90"  # plays in a browser
    frames = read_video(out)
    assert frames.shape == (5 + 10, 72, 256, 3)  # 5 context + 2 steps of 5, real | generated
    # The 25-frame video has no real frame 30: shown black, up to the lossy codec's filtering at the edge it
    # shares with the generated half.
    assert frames[-1, :, :120].max() < 10 and frames[-1, :, :128].mean() < 2
    with Image.open(out.with_suffix(".gif")) as gif:
        assert gif.n_frames == 15 and gif.size == (256, 72)


def test_cli_refuses_an_output_browsers_cannot_play(tmp_path, checkpoints, capsys):
    _expect_exit_2(_args(tmp_path / "v.mp4", tmp_path / "o.avi", checkpoints), capsys,
                   f"--out {tmp_path / 'o.avi'}: the video is written as VP9, in .mp4 or .webm")
    assert not list(tmp_path.iterdir())


@pytest.mark.parametrize("flag, value, fragment", [
    ("--seconds", "nan", "--seconds nan: not a finite number"),
    ("--seconds", "inf", "--seconds inf: not a finite number"),
    ("--seconds", "0", "--seconds 0: the rollout length must be > 0"),
    ("--seconds", "-3", "--seconds -3: the rollout length must be > 0"),
    ("--abstract-nfe", "0", "--abstract-nfe 0: needs at least 1"),
    ("--detail-nfe", "-1", "--detail-nfe -1: needs at least 1"),
    ("--speed-scale", "nan", "--speed-scale nan: not a finite number"),
    ("--steering-guidance", "-1", "--steering-guidance -1: must be >= 0"),
])
def test_cli_rejects_bad_numbers_in_one_line(tmp_path, checkpoints, capsys, flag, value, fragment):
    err = _expect_exit_2(_args(tmp_path / "v.mp4", tmp_path / "o.mp4", checkpoints) + [flag, value], capsys,
                         fragment)
    assert len(err.strip().splitlines()) == 1
    assert not list(tmp_path.iterdir())


def test_cli_rejects_a_trajectory_shorter_than_the_rollout_unless_held(make_video, tmp_path, checkpoints, capsys):
    video = make_video("drive.mp4", 25, 10)
    rows = [[t / 10, 5.0, 0.1] for t in range(25)]
    traj = _write_csv(tmp_path / "traj.csv", ["timestamp", "speed", "yaw_rate"], rows)
    out = tmp_path / "out" / "o.mp4"
    _expect_exit_2(_args(video, out, checkpoints, "--trajectory", traj, "--seconds", 1), capsys, str(traj),
                   "ends at 2.4 s but this rollout needs steering up to 3 s", "--hold-last")
    assert not out.exists()
    main(_args(video, out, checkpoints, "--trajectory", traj, "--seconds", 1, "--hold-last"))
    assert out.is_file()


def test_cli_rejects_missing_corrupt_and_other_profile_checkpoints(make_video, tmp_path, checkpoints, capsys):
    video = make_video("v.mp4", 25, 10)
    _expect_exit_2(_args(tmp_path / "none.mp4", tmp_path / "o.mp4", checkpoints), capsys,
                   f"{tmp_path / 'none.mp4'}: does not exist")
    corrupt = tmp_path / "corrupt.pt"
    corrupt.write_bytes(checkpoints["detail_tok"].read_bytes()[:5000])
    _expect_exit_2(_args(video, tmp_path / "o.mp4", checkpoints) + ["--detail-tokenizer", str(corrupt)], capsys,
                   f"{corrupt}: not a checkpoint this version can read")
    # The smoke checkpoints under the default profile: other frame size, other predictor preset.
    _expect_exit_2(_args(video, tmp_path / "o.mp4", checkpoints) + ["--profile", "default"], capsys,
                   f"{checkpoints['detail_tok']}: made for 128x72 frames but profile default uses 256x160",
                   "pass --profile smoke")
    assert not list(tmp_path.glob("o.*"))
