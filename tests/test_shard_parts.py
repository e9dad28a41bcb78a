"""Shards in parts: any number of parts gives the same samples in the same order as one, a part stopped at any
point resumes without writing again what it finished, and ends with the bytes of a run never stopped."""

import dataclasses
import json
import subprocess
import sys

import pytest
from test_shards import make_raw

from orbis2.data import shards as shards_module
from orbis2.data.parts import WORK_KEY, part_name, part_slice
from orbis2.data.shards import PART_LOG, iter_samples, load_manifest, shard_paths, write_shards

from conftest import ROOT, project_copy, run

EPISODES = (("train", 7, 64), ("val", 2, 40), ("probe", 2, 40))


@pytest.fixture(scope="module")
def raw(tmp_path_factory, smoke_cfg):
    root = tmp_path_factory.mktemp("parts") / "raw"
    make_raw(root, smoke_cfg, EPISODES)
    return root


@pytest.fixture(scope="module")
def cfg(smoke_cfg):
    return dataclasses.replace(smoke_cfg.shards, max_shard_mb=0.2)  # several shards per part


@pytest.fixture(scope="module")
def whole(raw, smoke_cfg, cfg, tmp_path_factory):
    out = tmp_path_factory.mktemp("whole") / "shards"
    return out, write_shards(raw, out, smoke_cfg.data, cfg)


def samples(root, manifest):
    """Every split's samples in manifest order: [(key, {member: bytes})]."""
    return {split: [(s["__key__"], {k: v for k, v in s.items() if not k.startswith("__")})
                    for path in shard_paths(root, split) for s in iter_samples(path)]
            for split in manifest["splits"]}


def test_part_slices_cover_every_item_once():
    for count in (0, 1, 5, 64, 1001):
        for parts in (1, 2, 3, 7, 64):
            taken = [i for p in range(parts) for i in range(count)[part_slice(count, p, parts)]]
            assert taken == list(range(count))
    with pytest.raises(ValueError, match="outside"):
        part_slice(10, 3, 3)


@pytest.mark.parametrize("parts", [2, 3, 8])  # 8: more parts than the val and probe episodes
def test_any_parts_same_samples_in_the_same_order(raw, smoke_cfg, cfg, whole, parts, tmp_path):
    root, manifest = whole
    out = tmp_path / "shards"
    split_manifest = write_shards(raw, out, smoke_cfg.data, cfg, parts=parts)
    assert samples(out, split_manifest) == samples(root, manifest)
    for split, info in manifest["splits"].items():
        assert split_manifest["splits"][split]["samples"] == info["samples"]
        assert split_manifest["splits"][split]["frames"] == info["frames"]
    assert len(split_manifest["splits"]["train"]["shards"]) >= len(manifest["splits"]["train"]["shards"])
    assert sorted(p.name for p in (tmp_path / "shards.parts").iterdir()) == sorted([
        WORK_KEY, *(part_name(i, parts) for i in range(parts))])


class Killed(BaseException):
    """Stands for SIGKILL: nothing after it runs (not an Exception, so no handler catches it)."""


@pytest.mark.parametrize("when", ["mid-shard", "after-a-shard", "torn-log"])
def test_a_stopped_part_resumes_where_it_stopped(raw, smoke_cfg, cfg, whole, when, tmp_path, monkeypatch):
    root, manifest = whole
    out = tmp_path / "shards"
    encoded = []
    real_jpeg, real_close = shards_module._jpeg, shards_module.ShardWriter._close_shard

    def jpeg(frame, params):
        encoded.append(1)
        if when == "mid-shard" and len(encoded) == 100:  # in the 4th clip, the 2nd shard open
            raise Killed
        return real_jpeg(frame, params)

    def close(self):
        real_close(self)
        if when != "mid-shard" and len(self.shards) == 2 and self.prefix == "train":
            raise Killed

    monkeypatch.setattr(shards_module, "_jpeg", jpeg)
    monkeypatch.setattr(shards_module.ShardWriter, "_close_shard", close)
    with pytest.raises(Killed):
        write_shards(raw, out, smoke_cfg.data, cfg, parts=2)
    part0 = tmp_path / "shards.parts" / part_name(0, 2)
    logged = [json.loads(line) for line in (part0 / PART_LOG).read_text().splitlines()]
    in_place = sum(e["frames"] for e in logged if e.get("shard"))
    assert in_place > 0 and not (tmp_path / "shards").exists()
    if when == "mid-shard":
        assert list(part0.rglob("*.partial"))  # the shard being written when it stopped
    if when == "torn-log":  # stopped while appending the line of the second shard: that shard is written again
        lines = (part0 / PART_LOG).read_text().splitlines()
        (part0 / PART_LOG).write_text("\n".join(lines[:-1]) + "\n" + lines[-1][:20])
        in_place -= logged[-1]["frames"]

    monkeypatch.setattr(shards_module.ShardWriter, "_close_shard", real_close)
    before = len(encoded)
    resumed = write_shards(raw, out, smoke_cfg.data, cfg, parts=2)
    total = sum(info["frames"] for info in manifest["splits"].values())
    assert len(encoded) - before == total - in_place  # what was in place is not encoded again
    assert not list(part0.rglob("*.partial"))
    assert resumed == write_shards(raw, tmp_path / "fresh", smoke_cfg.data, cfg, parts=2)  # names, sizes, hashes
    assert samples(out, resumed) == samples(root, manifest)


def test_a_work_folder_of_other_inputs_is_not_resumed(raw, smoke_cfg, cfg, tmp_path):
    out, work = tmp_path / "shards", tmp_path / "work"
    write_shards(raw, out, smoke_cfg.data, cfg, parts=2, work=work)
    other = dataclasses.replace(cfg, jpeg_quality=cfg.jpeg_quality - 10)
    manifest = write_shards(raw, out, smoke_cfg.data, other, parts=2, work=work)
    assert json.loads((work / WORK_KEY).read_text())["shards"]["jpeg_quality"] == cfg.jpeg_quality - 10
    fresh = write_shards(raw, tmp_path / "fresh", smoke_cfg.data, other)
    assert samples(out, manifest) == samples(tmp_path / "fresh", fresh)


def test_the_smoke_dag_in_3_parts_writes_the_smoke_shards(smoke_main, tmp_path):
    """`snakemake data/shards --config parts=3` (three `shards_part` jobs and the gather) on the smoke build's
    raw town: the same samples, in the same order, as the smoke build's one-part shards. (The smoke build itself
    runs the documented one part.)"""
    root = project_copy(tmp_path / "project")
    (root / "data/raw").mkdir(parents=True)
    (root / "data/raw/town").symlink_to(smoke_main / "data/raw/town")
    log = run(["snakemake", "--cores", "2", "data/shards", "--config", "parts=3"], root)
    assert log.count("rule shards_part:") == 3 and "rule town:" not in log
    assert sorted(p.name for p in (root / "data/shard_parts").iterdir()) == [
        f"{part_name(i, 3)}.json" for i in range(3)]
    ours, theirs = (load_manifest(r / "data/shards") for r in (root, smoke_main))
    assert samples(root / "data/shards", ours) == samples(smoke_main / "data/shards", theirs)


def test_the_scale_page_is_written_from_the_published_measurement(tmp_path):
    """docs/scale.md is what tools/scale_plan.py writes from benchmarks/bench_shards.py's published figures (and
    benchmarks/bench_latent_parts.py's, once published)."""
    published, latents = (ROOT / "docs/results/scale" / name for name in ("bench_shards.json", "bench_latents.json"))
    command = ["tools/scale_plan.py", str(published.relative_to(ROOT))]
    command += ["--latents", str(latents.relative_to(ROOT))] if latents.is_file() else []
    subprocess.run([sys.executable, *command, "--out", str(tmp_path / "scale.md")], cwd=ROOT, check=True,
                   capture_output=True)
    assert (tmp_path / "scale.md").read_text() == (ROOT / "docs/scale.md").read_text(), (
        f"docs/scale.md is stale: python {' '.join(command)} --out docs/scale.md")
    bench = json.loads(published.read_text())
    assert bench["peak_ratio"] < 1.1 and bench["frames_scaled"] == bench["scale"] * bench["frames_1x"]
    if latents.is_file():
        bench = json.loads(latents.read_text())
        assert bench["peak_ratio"] < 1.1 and bench["frames_scaled"] == bench["scale"] * bench["frames_1x"]
