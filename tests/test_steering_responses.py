"""Scale-free steering responses: paired per start, intervals over clips, known answers."""

import json

import cv2
import numpy as np
import pytest
import torch

from orbis2.eval.protocols.steering import (
    choose_guidance,
    image_turns,
    latent_turns,
    mode_record,
    ordering_steps,
    steering_responses,
    turn_record,
)
from orbis2.eval.records import SteeringRecord
from orbis2.models.deviations import translate_columns

from conftest import ROOT


def scores(turn, path, ade=1.0, n=16):
    return {"ade": np.full(n, ade), "turn_deg": np.asarray(turn, float), "commanded_turn_deg": np.full(n, 10.0),
            "path_length": np.asarray(path, float)}


def per_sample(turn_lo, turn_hi, path_lo, path_hi):
    base = scores(np.full(16, 10.0), np.full(16, 20.0))
    return {"original": {"learned": base},
            "yaw_rate_x0.5": {"learned": scores(turn_lo, np.full(16, 20.0))},
            "yaw_rate_x1.5": {"learned": scores(turn_hi, np.full(16, 20.0))},
            "speed_x0.5": {"learned": scores(np.full(16, 10.0), path_lo)},
            "speed_x1.5": {"learned": scores(np.full(16, 10.0), path_hi)}}


def test_a_model_that_follows_the_commands_shows_both_responses():
    rng = np.random.default_rng(0)
    clips = np.repeat([f"c{i}" for i in range(8)], 2)
    turn = 10.0 + rng.normal(0, 3, 16)  # per-start spread shared by both modes (paired)
    path = 20.0 * np.exp(rng.normal(0, 0.2, 16))
    out = steering_responses(per_sample(turn - 5.0, turn + 5.0, path * 0.5, path * 1.5), "learned", clips, 0)
    assert out["turn_response_deg"]["estimate"] == pytest.approx(10.0)
    assert out["turn_response_deg"]["low"] == pytest.approx(10.0)  # paired: the start-to-start spread cancels
    assert out["path_ratio"]["estimate"] == pytest.approx(3.0) and out["path_ratio"]["low"] == pytest.approx(3.0)


def test_a_model_that_ignores_the_commands_shows_none():
    rng = np.random.default_rng(1)
    clips = np.repeat([f"c{i}" for i in range(8)], 2)
    out = steering_responses(per_sample(rng.normal(10, 3, 16), rng.normal(10, 3, 16), np.full(16, 20.0),
                                        np.full(16, 20.0)), "learned", clips, 0)
    assert out["turn_response_deg"]["low"] < 0 < out["turn_response_deg"]["high"]
    assert out["path_ratio"]["estimate"] == pytest.approx(1.0)


def test_the_ordering_steps_are_paired_per_start():
    rng = np.random.default_rng(2)
    clips = list(np.repeat([f"c{i}" for i in range(8)], 2))
    turn = 10.0 + rng.normal(0, 3, 16)  # per-start spread shared by every mode

    def modes(lower, upper):
        return {"yaw_rate_x0.5": scores(turn - lower, np.ones(16)), "original": scores(turn, np.ones(16)),
                "yaw_rate_x1.5": scores(turn + upper, np.ones(16))}

    follows = ordering_steps(modes(4.0, 6.0), clips, 0)
    assert list(follows) == ["original - yaw_rate_x0.5", "yaw_rate_x1.5 - original"]
    assert follows["original - yaw_rate_x0.5"]["low"] == pytest.approx(4.0)
    assert follows["yaw_rate_x1.5 - original"]["estimate"] == pytest.approx(6.0)
    saturates = ordering_steps(modes(4.0, 0.0), clips, 0)["yaw_rate_x1.5 - original"]
    assert saturates["low"] == pytest.approx(0.0) and saturates["high"] == pytest.approx(0.0)
    assert ordering_steps({"original": scores(turn, np.ones(16))}, clips, 0) == {}
    responses = steering_responses({m: {"learned": v} for m, v in modes(4.0, 6.0).items()}, "learned", clips, 0)
    assert responses["turn_steps_deg"] == follows


def test_mode_record_puts_the_main_instrument_first_with_intervals():
    clips = np.repeat([f"c{i}" for i in range(8)], 2)
    record = mode_record({"learned": scores(np.full(16, 5.0), np.ones(16), ade=0.5),
                          "opencv": scores(np.full(16, 1.0), np.ones(16), ade=3.0)}, list(clips), 1.0, 1.5, 0)
    assert record["ade"] == 0.5 and record["instruments"]["opencv"]["ade"] == 3.0
    assert record["ade_low"] == record["ade_high"] == 0.5 and record["yaw_rate_scale"] == 1.5


def test_latent_turns_read_a_known_sideways_drift():
    # Detail latents that drift 1 column right per frame on a 64-column grid, 90 degree camera: each
    # frame turns atan(1 / 32) left. The second video is commanded to turn right: its own direction counts positive.
    base = torch.sin(torch.linspace(0, 24, 64) + torch.randn(2, 3, 4, 1, generator=torch.Generator().manual_seed(0)))
    frames = torch.stack([translate_columns(base, torch.full((2,), float(t))) for t in range(21)], dim=1)
    yaw = np.full(20, 0.4)
    out = latent_turns(frames[:, :1], frames[:, 1:], [(np.ones(20), yaw), (np.ones(20), -yaw)], fps=10.0,
                       hfov_deg=90.0)
    per_frame = np.degrees(np.arctan(1 / 32))
    np.testing.assert_allclose(out["turn_deg"], [20 * per_frame, -20 * per_frame], atol=1e-4)
    np.testing.assert_allclose(out["commanded_turn_deg"], np.degrees([0.8, 0.8]))
    record = turn_record({"real": out, "yaw_rate_x0.5": out,
                          "yaw_rate_x1.5": {k: 2 * v for k, v in out.items()}}, ["a", "b"], seed=0)
    assert record["modes"]["real"]["commanded_turn_deg"] == pytest.approx(np.degrees(0.8))
    assert record["commanded_turn_response_deg"] == pytest.approx(np.degrees(0.8))


def test_image_turns_read_a_known_pan():
    # A camera panning left across a textured panorama: content moves 2 pixels right per frame on a 112-pixel
    # wide, 90-degree image (1.14 columns of the 64 it is read at), so each frame turns atan(2 / 56) left.
    # The second video is commanded to turn right: its own direction counts positive, so the pan reads negative.
    rng = np.random.default_rng(0)
    panorama = cv2.GaussianBlur(rng.uniform(0, 255, (64, 240)).astype(np.float32), (0, 0), 2.0)
    frames = np.stack([panorama[:, 60 - 2 * t: 172 - 2 * t] for t in range(11)])
    video = np.repeat(np.clip(frames, 0, 255).astype(np.uint8)[..., None], 3, axis=-1)
    yaw = np.full(10, 0.4)
    out = image_turns([video, video], [(np.ones(10), yaw), (np.ones(10), -yaw)], fps=10.0, hfov_deg=90.0)
    expected = 10 * np.degrees(np.arctan(2 / 56))
    np.testing.assert_allclose(out["turn_deg"], [expected, -expected], rtol=0.03)
    np.testing.assert_allclose(out["commanded_turn_deg"], np.degrees([0.4, 0.4]))
    still = image_turns([np.repeat(video[:1], 11, axis=0)], [(np.ones(10), yaw)], fps=10.0, hfov_deg=90.0)
    assert abs(still["turn_deg"][0]) < 1e-6


def test_choose_guidance_takes_the_smallest_scale_that_resolves_both_steps():
    written = json.loads((ROOT / "tests/fixtures/records/steering.json").read_text())

    def record(low_lower, low_upper):
        doc = json.loads(json.dumps(written))
        steps = doc["responses"]["learned"]["turn_steps_deg"]
        steps["original - yaw_rate_x0.5"]["low"], steps["yaw_rate_x1.5 - original"]["low"] = low_lower, low_upper
        return SteeringRecord.model_validate(doc)

    records = {1.0: record(5.0, -0.9), 2.0: record(8.5, 3.3), 3.0: record(9.0, 4.0)}
    result = choose_guidance(records, "learned", material=2.0, split="val")
    assert result.chosen == 2.0 and result.resolved and result.split == "val"
    assert result.smaller_step_low_deg == {"1.0": -0.9, "2.0": 3.3, "3.0": 4.0}
    # None resolves: the scale with the largest smaller lower bound, flagged unresolved.
    result = choose_guidance(records, "learned", material=5.0, split="val")
    assert result.chosen == 3.0 and not result.resolved
    without = json.loads(json.dumps(written))
    without["responses"]["learned"].pop("turn_steps_deg")
    with pytest.raises(ValueError, match="lacks the yaw-rate modes"):
        choose_guidance({1.0: SteeringRecord.model_validate(without)}, "learned", 2.0, "val")
