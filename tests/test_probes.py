"""Linear probes: depth bins and losses, mIoU, that the probe learns, the data loaders, the feature extractors."""

from __future__ import annotations

import dataclasses

import cv2
import numpy as np
import pytest
import torch

from orbis2.data.episodes import EpisodeRecord, RawIndex, write_labels, write_odometry
from orbis2.data.probes import (
    ProbeDataError,
    ProbeFrame,
    cityscapes_frames,
    cityscapes_train_ids,
    kitti_eigen_frames,
    split_by_episode,
    town_probe_frames,
)
from orbis2.data.shards import write_shards
from orbis2.data.video import write_video
from orbis2.errors import OrbisError
from orbis2.eval.metrics.probe_heads import (
    ProbeConfig,
    bin_centres,
    binned_depth_loss,
    confusion_matrix,
    decode_depth,
    depth_rmse,
    depth_to_bin,
    iou_per_class,
    mean_iou,
)
from orbis2.eval.protocols.probe import (
    predictor_features,
    probe_on_features,
    run_probe,
    teacher_features,
    tokenizer_features,
)
from orbis2.models.files import load_predictor, load_tokenizer, save_predictor, save_tokenizer
from orbis2.models.stdit import build_stdit_from
from orbis2.models.tokenizer import build_abstract_tokenizer, build_detail_tokenizer

from conftest import moving_pattern

# --------------------------------------------------------------------------- depth bins and losses


def test_depth_from_one_hot_logits_is_the_bin_centre():
    centres = bin_centres(256, 80.0)
    assert centres[0] == pytest.approx(80 / 512) and centres[-1] == pytest.approx(80 - 80 / 512)
    logits = torch.full((1, 256, 2, 2), -1e4)
    for k, (i, j) in zip((0, 37, 128, 255), ((0, 0), (0, 1), (1, 0), (1, 1))):
        logits[0, k, i, j] = 1e4
    np.testing.assert_allclose(decode_depth(logits, centres)[0].flatten(), centres[[0, 37, 128, 255]], rtol=1e-6)
    assert depth_to_bin(torch.tensor([0.1, 40.0, 80.0]), 256, 80.0).tolist() == [0, 128, 255]


def test_binned_cross_entropy_prefers_the_right_bin():
    depth = torch.full((1, 1, 1), 20.0)
    target = int(depth_to_bin(depth, 256, 80.0))
    right, wrong = torch.zeros(1, 256, 1, 1), torch.zeros(1, 256, 1, 1)
    right[0, target], wrong[0, target + 40] = 5.0, 5.0
    assert binned_depth_loss(right, depth, 80.0) < binned_depth_loss(wrong, depth, 80.0)


def test_invalid_depth_pixels_do_not_count():
    torch.manual_seed(0)
    logits = torch.randn(1, 256, 2, 3)
    depth = torch.tensor([[[10.0, 0.0, float("nan")], [float("inf"), 95.0, 30.0]]])
    base = binned_depth_loss(logits, depth, 80.0)
    other_invalid = torch.tensor([[[10.0, float("nan"), 0.0], [200.0, float("inf"), 30.0]]])
    assert binned_depth_loss(logits, other_invalid, 80.0) == pytest.approx(float(base))
    valid_changed = depth.clone()
    valid_changed[0, 1, 2] = 60.0
    assert binned_depth_loss(logits, valid_changed, 80.0) != pytest.approx(float(base))
    assert float(binned_depth_loss(logits, torch.zeros(1, 2, 3), 80.0)) == 0.0  # nothing valid: no signal
    rmse = depth_rmse(torch.full((2, 2, 3), 12.0), torch.cat([depth, torch.zeros(1, 2, 3)]), 80.0)
    assert rmse[0] == pytest.approx(np.sqrt((2**2 + 18**2) / 2)) and torch.isnan(rmse[1])


# --------------------------------------------------------------------------- mIoU


def test_miou_perfect_hand_computed_and_absent_classes():
    labels = torch.tensor([[0, 0, 1, 255], [2, 2, 1, 1]])
    assert mean_iou(confusion_matrix(labels.clamp(max=2), labels, 19)) == 1.0
    # true 0 -> predicted 0, 0, 1; true 1 -> 1, 1, 1: class 0 IoU 2/3, class 1 IoU 3/4, class 2 absent.
    confusion = confusion_matrix(torch.tensor([0, 0, 1, 1, 1, 1, 2]), torch.tensor([0, 0, 0, 1, 1, 1, 255]), 3)
    assert confusion.tolist() == [[2, 1, 0], [0, 3, 0], [0, 0, 0]]
    assert iou_per_class(confusion) == pytest.approx({0: 2 / 3, 1: 3 / 4})
    assert mean_iou(confusion) == pytest.approx(17 / 24)
    predicted_only = torch.tensor([[0, 5, 0], [0, 0, 0], [0, 0, 0]])  # class 1 predicted, never labelled
    assert iou_per_class(predicted_only) == {0: 0.0, 1: 0.0}


# --------------------------------------------------------------------------- the probe learns


def _synthetic(n: int, seed: int, h: int = 3, w: int = 4, classes: int = 4) -> tuple[torch.Tensor, list[ProbeFrame]]:
    """Features = one-hot class + depth / 10 + noise on an h x w grid; labels 4x finer (the head's upsampling)."""
    g = torch.Generator().manual_seed(seed)
    cls = torch.randint(0, classes, (n, h, w), generator=g)
    depth = torch.rand(n, 1, 1, generator=g) * 40 + 5 + 4.0 * torch.arange(h).float()[None, :, None]
    depth = depth.expand(n, h, w)
    onehot = torch.nn.functional.one_hot(cls, 8).permute(0, 3, 1, 2).float()
    features = torch.cat([onehot, depth[:, None] / 10], 1) + 0.05 * torch.randn(n, 9, h, w, generator=g)

    def up(t: torch.Tensor) -> np.ndarray:
        return t.repeat_interleave(4, 1).repeat_interleave(4, 2).numpy()

    frames = [ProbeFrame(np.zeros((4 * h, 4 * w, 3), np.uint8), up(cls)[i].astype(np.uint8), up(depth)[i],
                         f"s{seed}_{i}", f"e{i}") for i in range(n)]
    return features, frames


FAST = ProbeConfig(seg_epochs=60, depth_epochs=60, batch_size=8, lr=0.1)


def test_probe_learns_linear_features_and_not_random_ones():
    train_x, train_frames = _synthetic(16, 0)
    test_x, test_frames = _synthetic(8, 1)
    good = probe_on_features(train_x, train_frames, test_x, test_frames, FAST)
    noise = torch.Generator().manual_seed(2)
    bad = probe_on_features(torch.randn(train_x.shape, generator=noise), train_frames,
                            torch.randn(test_x.shape, generator=noise), test_frames, FAST)
    seg, depth = good["segmentation"], good["depth"]
    assert seg["miou"] > 0.85 and seg["classes"] == [0, 1, 2, 3]
    assert seg["train_frames"] == 16 and seg["test_frames"] == 8 and depth["test_frames"] == 8
    assert bad["segmentation"]["miou"] < 0.45 and bad["segmentation"]["val_loss"] > 2 * seg["val_loss"]
    assert depth["rmse"] < 5.0 and bad["depth"]["rmse"] > 2 * depth["rmse"]
    assert good["features"] == {"channels": 9, "height": 3, "width": 4}
    again = probe_on_features(train_x, train_frames, test_x, test_frames, FAST)
    assert again == good  # deterministic given the seed


def test_run_probe_skips_a_task_without_labels():
    """Colour encodes the class, the feature fn pools the image; no depth anywhere -> depth is None."""
    palette = np.array([[255, 0, 0], [0, 255, 0], [0, 0, 255]], np.uint8)

    def frames(seed: int, n: int) -> list[ProbeFrame]:
        rng = np.random.default_rng(seed)
        out = []
        for i in range(n):
            cls = rng.integers(0, 3, (2, 3)).repeat(8, 0).repeat(8, 1)
            out.append(ProbeFrame(palette[cls], cls.astype(np.uint8), np.full(cls.shape, np.nan, np.float32),
                                  f"{seed}/{i}", f"{seed}"))
        return out

    def pool(images: torch.Tensor) -> torch.Tensor:
        return torch.nn.functional.avg_pool2d(images, 8)

    cfg = dataclasses.replace(FAST, upsample=8)
    result = run_probe(pool, frames(0, 8), frames(1, 4), cfg)
    assert result["depth"] is None and result["segmentation"]["miou"] > 0.9
    assert result["features"] == {"channels": 3, "height": 2, "width": 3}


# --------------------------------------------------------------------------- Cityscapes and KITTI


def _write_cityscapes(root, split="val", city="aachen", name="aachen_000000_000019"):
    image = moving_pattern(1, 64, 32)[0]
    label = np.zeros((32, 64), np.uint8)  # rows 0-7 unlabeled (id 0)
    label[8:, :32], label[8:, 32:] = 7, 26  # road left, car right
    (root / "leftImg8bit" / split / city).mkdir(parents=True, exist_ok=True)
    (root / "gtFine" / split / city).mkdir(parents=True, exist_ok=True)
    cv2.imwrite(str(root / "leftImg8bit" / split / city / f"{name}_leftImg8bit.png"), image[..., ::-1])
    cv2.imwrite(str(root / "gtFine" / split / city / f"{name}_gtFine_labelIds.png"), label)
    return image


def test_cityscapes_train_id_table():
    ids = np.array([0, 1, 6, 7, 8, 9, 11, 23, 24, 26, 29, 31, 33, 34, 255])
    assert cityscapes_train_ids(ids).tolist() == [255, 255, 255, 0, 1, 255, 2, 10, 11, 13, 255, 16, 18, 255, 255]


def test_cityscapes_loader_maps_and_resizes(tmp_path):
    image = _write_cityscapes(tmp_path)
    _write_cityscapes(tmp_path, city="bonn", name="bonn_000000_000019")
    frames = cityscapes_frames(tmp_path, "val", (32, 18))
    assert [f.episode for f in frames] == ["aachen", "bonn"]
    frame = frames[0]
    assert frame.image.shape == (18, 32, 3) and frame.semantic.shape == (18, 32) and frame.depth.shape == (18, 32)
    assert set(np.unique(frame.semantic)) == {0, 13, 255} and np.isnan(frame.depth).all()
    # 64x32 covers 32x18 at scale 0.5625 (36x18), then 2 columns are cropped from each side.
    assert frame.semantic[0, 0] == 255 and frame.semantic[-1, 0] == 0 and frame.semantic[-1, -1] == 13
    assert (frame.semantic[:, :16] != 13).all() and (frame.semantic[5:, 16:] == 13).all()
    expected = cv2.resize(image, (36, 18), interpolation=cv2.INTER_AREA)[:, 2:34]
    assert np.abs(frame.image.astype(int) - expected).max() <= 1
    assert len(cityscapes_frames(tmp_path, "val", (32, 18), limit=1)) == 1


def test_cityscapes_errors_name_the_path(tmp_path):
    with pytest.raises(ProbeDataError, match="leftImg8bit/val.*expected layout"):
        cityscapes_frames(tmp_path, "val", (32, 18))
    _write_cityscapes(tmp_path)
    (tmp_path / "gtFine/val/aachen/aachen_000000_000019_gtFine_labelIds.png").unlink()
    with pytest.raises(ProbeDataError, match="aachen_000000_000019_gtFine_labelIds.png: Cityscapes label"):
        cityscapes_frames(tmp_path, "val", (32, 18))


DRIVE = "2011_09_26/2011_09_26_drive_0002_sync"


def _write_kitti(raw, depth_folder, frame=69):
    image_dir = raw / DRIVE / "image_02" / "data"
    depth_dir = depth_folder / "proj_depth" / "groundtruth" / "image_02"
    image_dir.mkdir(parents=True, exist_ok=True)
    depth_dir.mkdir(parents=True, exist_ok=True)
    cv2.imwrite(str(image_dir / f"{frame:010d}.png"), moving_pattern(1, 96, 32)[0])
    depth = np.zeros((32, 96), np.uint16)
    depth[16:, :48] = 3000  # 11.71875 m in the lower left; no measurement elsewhere
    cv2.imwrite(str(depth_dir / f"{frame:010d}.png"), depth)


def test_kitti_loader_decodes_and_resizes_depth(tmp_path):
    raw = tmp_path / "raw"
    _write_kitti(raw, raw / DRIVE)  # annotations merged into the raw tree
    split = tmp_path / "test_files.txt"
    split.write_text(f"{DRIVE} 69 l\n\n")
    (frame,) = kitti_eigen_frames(raw, split, (48, 27))
    assert frame.image.shape == (27, 48, 3) and frame.depth.dtype == np.float32
    assert (frame.semantic == 255).all() and frame.episode == "2011_09_26_drive_0002_sync"
    assert set(np.unique(frame.depth)) == {0.0, 3000 / 256}
    # 96x32 covers 48x27 at scale 0.84375 (81x27), crop 16 columns from the left: the measured block
    # (source columns < 48) ends at output column 40 - 16 = 24, the lower half starts at row 14.
    assert (frame.depth[15:, :23] == 3000 / 256).all() and (frame.depth[:12] == 0).all()
    assert (frame.depth[:, 26:] == 0).all()
    # data_depth_annotated.zip as extracted, in its own root
    _write_kitti(tmp_path / "raw2", tmp_path / "annotated" / "val" / "2011_09_26_drive_0002_sync")
    (other,) = kitti_eigen_frames(tmp_path / "raw2", split, (48, 27), depth_root=tmp_path / "annotated")
    np.testing.assert_array_equal(other.depth, frame.depth)


def test_kitti_errors_name_the_path(tmp_path):
    raw = tmp_path / "raw"
    _write_kitti(raw, raw / DRIVE)
    split = tmp_path / "eigen.txt"
    split.write_text(f"{DRIVE} 70 l\n")
    with pytest.raises(ProbeDataError, match="0000000070.png: KITTI image listed"):
        kitti_eigen_frames(raw, split, (48, 27))
    (raw / DRIVE / "proj_depth/groundtruth/image_02/0000000069.png").unlink()
    split.write_text(f"{DRIVE} 69 l\n")
    with pytest.raises(ProbeDataError, match="groundtruth/image_02/0000000069.png: KITTI depth map not found"):
        kitti_eigen_frames(raw, split, (48, 27))
    split.write_text(f"{DRIVE} 69\n")
    with pytest.raises(ProbeDataError, match="eigen.txt:1"):
        kitti_eigen_frames(raw, split, (48, 27))
    with pytest.raises(ProbeDataError, match="missing_root: KITTI root not found"):
        kitti_eigen_frames(tmp_path / "missing_root", split, (48, 27))


# --------------------------------------------------------------------------- feature extractors


@pytest.fixture(scope="module")
def models(tmp_path_factory):
    """Smoke tokenizers and predictors with random adaLN weights, so every block changes the tokens."""
    root = tmp_path_factory.mktemp("probe_models")
    torch.manual_seed(0)
    save_tokenizer(root / "abstract_tok.pt", "abstract", build_abstract_tokenizer("smoke", teacher_dim=32), 3.0,
                   {"preset": "smoke", "teacher_dim": 32, "compress": True})
    save_tokenizer(root / "detail_tok.pt", "detail", build_detail_tokenizer("smoke"), 2.0, {"preset": "smoke"})
    tokenizers = {kind: load_tokenizer(root / f"{kind}_tok.pt") for kind in ("abstract", "detail")}
    windows = {"abstract": {"window": 6, "context": 5}, "detail": {"window": 10, "context": 5}}
    builds = {"abstract": {"preset": "smoke", "latent_channels": 16, "causal": True},
              "detail": {"preset": "smoke", "latent_channels": 16, "causal": False, "abstract_channels": 16}}
    predictors = {}
    for level, build in builds.items():
        model = build_stdit_from(build)
        for block in model.blocks:
            torch.nn.init.normal_(block.adaLN_modulation[-1].weight, std=0.05)
        meta = {"level": level, "frame_rate": 2.0 if level == "abstract" else 10.0, "window": windows[level],
                "tokenizers": {level: {"checksum": tokenizers[level].checksum}}}
        save_predictor(root / f"{level}.pt", model, build, meta)
        predictors[level] = load_predictor(root / f"{level}.pt")
    images = torch.rand(3, 3, 72, 128, generator=torch.Generator().manual_seed(1)) * 2 - 1
    return tokenizers, predictors, images


def test_tokenizer_features_are_the_raw_or_normalised_latent(models):
    tokenizers, _, images = models
    features = tokenizer_features(tokenizers["abstract"])(images)
    assert features.shape == (3, 16, 9, 16)
    with torch.no_grad():
        expected = tokenizers["abstract"].model.encode(images)
    torch.testing.assert_close(features, expected)
    torch.testing.assert_close(tokenizer_features(tokenizers["abstract"], normalized=True)(images), expected * 3.0)


def test_teacher_features_resize_to_the_requested_input(models):
    _, _, images = models
    teacher = torch.nn.Conv2d(3, 5, 4, stride=4)  # any frozen module mapping images to a patch map
    assert teacher_features(teacher)(images).shape == (3, 5, 18, 32)
    assert teacher_features(teacher, size=(36, 64))(images).shape == (3, 5, 9, 16)


@pytest.mark.parametrize("level", ["abstract", "detail"])
def test_predictor_features_null_context_protocol(models, level):
    tokenizers, predictors, images = models
    predictor, tokenizer = predictors[level], tokenizers[level]
    last = predictor_features(predictor, tokenizer, block=1)(images)
    assert last.shape == (3, 64, 9, 16)
    # each image's features depend on that image only
    torch.testing.assert_close(predictor_features(predictor, tokenizer, block=1)(images[1:2]), last[1:2])
    assert not torch.allclose(predictor_features(predictor, tokenizer, block=2)(images), last)
    # by hand: the scaled latent tiled over every predicted slot, tau = 0, last slot's tokens
    slots = 1 if level == "abstract" else 5
    z = tokenizer.normalize(tokenizer.model.encode(images))
    x = z[:, None].repeat(1, slots, 1, 1, 1)
    cond = {}
    if level == "detail":
        cond = {"cond_frames": torch.zeros(3, slots, 16, 9, 16), "cond_mask": torch.zeros(3, slots, dtype=torch.bool)}
    with torch.no_grad():
        expected = predictor.model(x, torch.zeros(3, slots), frame_rate=predictor.meta["frame_rate"],
                                   features_from_block=1, **cond)[:, -1]
        if level == "detail":  # the tiling matters: the image in the last slot only gives other features
            alone = x.clone()
            alone[:, :-1] = 0
            other = predictor.model(alone, torch.zeros(3, slots), frame_rate=10.0, features_from_block=1, **cond)
            assert not torch.allclose(other[:, -1], expected, atol=1e-4)
    torch.testing.assert_close(last, expected)


def test_predictor_features_refuse_the_wrong_tokenizer(models):
    tokenizers, predictors, _ = models
    with pytest.raises(OrbisError, match="pass the detail tokenizer"):
        predictor_features(predictors["detail"], tokenizers["abstract"], block=1)
    wrong = dataclasses.replace(tokenizers["abstract"], checksum="f" * 64)
    with pytest.raises(OrbisError, match="pass the tokenizer it was trained with"):
        predictor_features(predictors["abstract"], wrong, block=1)
    with pytest.raises(OrbisError, match="slots = 6"):
        predictor_features(predictors["detail"], tokenizers["detail"], block=1, slots=6)


# --------------------------------------------------------------------------- town ground truth


def test_town_probe_frames_from_shards(tmp_path, smoke_cfg):
    data = smoke_cfg.data
    records = []
    (tmp_path / "raw" / "probe").mkdir(parents=True)
    for e in range(3):
        stem = f"ep_probe_{e:05d}"
        write_video(tmp_path / "raw" / "probe" / f"{stem}.mp4", moving_pattern(40, data.width, data.height, e),
                    data.fps)
        k = np.arange(40, dtype=float)
        write_odometry(tmp_path / "raw" / "probe" / f"{stem}.parquet", data.fps, k, -k, None)
        label_frames = [0, 10, 20, 30]
        depth = np.full((4, data.height, data.width), 7.5 + e, np.float32)
        depth[:, 0] = np.inf  # the sky
        semantic = np.full((4, data.height, data.width), e, np.uint8)
        write_labels(tmp_path / "raw" / "probe" / f"{stem}.labels.npz", label_frames, depth, semantic)
        records.append(EpisodeRecord("probe", stem, 40, True, False, label_frames, origin="test"))
    RawIndex("test", data.fps, data.width, data.height, None, records).write(tmp_path / "raw")
    write_shards(tmp_path / "raw", tmp_path / "shards", data, smoke_cfg.shards)

    frames = town_probe_frames(tmp_path / "shards")
    assert len(frames) == 12 and len({f.source for f in frames}) == 12
    assert frames[1].source == "ep_probe_00000_0000/0010" and frames[1].episode == "ep_probe_00000"
    assert frames[5].image.shape == (data.height, data.width, 3) and (frames[5].semantic == 1).all()
    assert frames[5].depth.dtype == np.float32 and np.isinf(frames[5].depth[0]).all()
    assert (frames[5].depth[1:] == 8.5).all()
    small = town_probe_frames(tmp_path / "shards", size=(64, 36))
    assert small[0].image.shape == (36, 64, 3) and small[0].depth.shape == (36, 64)

    train, test = split_by_episode(frames, test_fraction=0.25)
    assert len(test) == 4 and len(train) == 8
    assert not {f.episode for f in train} & {f.episode for f in test}
    assert split_by_episode(frames, 0.25) == (train, test)
    with pytest.raises(ProbeDataError, match="at least 2 episodes"):
        split_by_episode(frames[:4])
