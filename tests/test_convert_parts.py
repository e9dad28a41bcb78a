"""The dataset converters in parts: any number of parts writes the files and the report of one part, byte for
byte; a part killed mid-item converts again only that item; a changed source is converted again."""

import json
import os

import pytest
from test_datasets import bdd_tree, nuplan_tree, opendv_tree, physicalai_tree

from orbis2.cli import main
from orbis2.data.datasets import DatasetError, bdd100k, nuplan, opendv, physicalai_av
from orbis2.data.parts import part_name


def files(root):
    """Every file under ``root`` (relative path: bytes; a link: where it points; the report with ``root`` as OUT)."""
    def content(path):
        if path.is_symlink():
            return os.readlink(path)
        return path.read_bytes().replace(str(root).encode(), b"OUT") if path.suffix == ".json" else path.read_bytes()

    return {p.relative_to(root).as_posix(): content(p) for p in sorted(root.rglob("*")) if p.is_file()}


def bdd(tmp_path):
    root = bdd_tree(tmp_path / "bdd100k", {f"b1c66a42-{n:08d}": {} if n != 2 else None for n in range(5)},
                    n_frames=30)
    return lambda out, **parts: bdd100k.convert(root, out, **parts)


def nuplan_logs(tmp_path):
    for n in range(3):
        nuplan_tree(tmp_path / "nuplan-v1.1", seconds=3.0, log=f"2021.06.09.17.23.18_veh-38_0077{n}_01140")
    return lambda out, **parts: nuplan.convert(tmp_path / "nuplan-v1.1/splits/mini", [tmp_path / "nuplan-v1.1" /
                                                                                        "sensor_blobs"], out, "val",
                                               clip_seconds=1.0, **parts)


def physicalai(tmp_path):
    root = physicalai_tree(tmp_path / "av")
    return lambda out, **parts: physicalai_av.convert(root, out, **parts)


def opendv_videos(tmp_path):
    meta = opendv_tree(tmp_path / "opendv")
    return lambda out, **parts: opendv.convert(meta, tmp_path / "opendv" / "videos", out, **parts)


@pytest.mark.parametrize("dataset", [bdd, nuplan_logs, physicalai, opendv_videos])
def test_any_parts_same_files_and_report(dataset, tmp_path):
    convert = dataset(tmp_path)
    convert(tmp_path / "one").write()
    for parts in (2, 7):  # 7: more parts than items
        out = tmp_path / f"in{parts}"
        for part in reversed(range(parts)):  # side by side, in any order
            convert(out, parts=parts, part=part)
        convert(out, parts=parts).write()  # every part done: the report only
        assert files(out) == files(tmp_path / "one"), parts
    assert json.loads((tmp_path / "one" / next(p.name for p in (tmp_path / "one").glob("convert-*.json"))
                       ).read_text())["converted"]


class Killed(BaseException):
    """Stands for SIGKILL: nothing after it runs."""


def test_a_killed_part_converts_again_only_the_item_in_flight_and_a_changed_source(tmp_path, monkeypatch):
    convert = bdd(tmp_path)
    calls, kill_at = [], [3]
    real = bdd100k.convert_video

    def convert_video(root, out, split, video, *args):
        calls.append(video.name)
        if len(calls) == kill_at[0]:
            kill_at[0] = 0
            raise Killed
        return real(root, out, split, video, *args)

    monkeypatch.setattr(bdd100k, "convert_video", convert_video)
    with pytest.raises(Killed):  # part 1 holds videos 2, 3 and 4: killed converting its third
        convert(tmp_path / "out", parts=2, part=1)
    log = tmp_path / "out.convert-parts/bdd100k" / part_name(1, 2) / "done.jsonl"
    assert len(log.read_text().splitlines()) == 2
    calls.clear()
    report = convert(tmp_path / "out", parts=2)  # part 0 whole, part 1 from where it stopped, then the report
    assert calls == [f"b1c66a42-{n:08d}.mov" for n in (0, 1, 4)]
    report.write()
    convert(tmp_path / "fresh").write()
    assert files(tmp_path / "out") == files(tmp_path / "fresh")

    changed = tmp_path / "bdd100k/info/100k/train/b1c66a42-00000001.json"
    os.utime(changed, ns=(changed.stat().st_atime_ns, changed.stat().st_mtime_ns + 10**9))
    calls.clear()
    convert(tmp_path / "out", parts=2)
    assert calls == ["b1c66a42-00000001.mov"]


PAI_CLIPS = {f"{n:08x}-0000-4000-8000-000000000000": ("val" if n == 4 else "train", n != 1) for n in range(6)}


def test_a_physicalai_part_killed_mid_chunk_converts_again_only_the_clips_not_done(tmp_path, monkeypatch):
    """A PhysicalAI-AV chunk is one zip of about a hundred clips: a part killed in it resumes at the clip it was on."""
    root = physicalai_tree(tmp_path / "av", clips=PAI_CLIPS)
    clips = list(PAI_CLIPS)
    calls, kill_at = [], [3]
    real = physicalai_av.convert_clip

    def convert_clip(clip_id, *args):
        calls.append(clip_id)
        if len(calls) == kill_at[0]:
            kill_at[0] = 0
            raise Killed
        return real(clip_id, *args)

    monkeypatch.setattr(physicalai_av, "convert_clip", convert_clip)
    with pytest.raises(Killed):  # clip 1 is invalid: killed converting clip 3, after clips 0, 1 and 2 were logged
        physicalai_av.convert(root, tmp_path / "out")
    log = tmp_path / "out.convert-parts/physicalai-av" / part_name(0, 1) / "done.jsonl"
    assert [json.loads(line)["item"] for line in log.read_text().splitlines()] == clips[:3]
    calls.clear()
    physicalai_av.convert(root, tmp_path / "out").write()
    assert calls == clips[3:]
    physicalai_av.convert(root, tmp_path / "fresh").write()
    assert files(tmp_path / "out") == files(tmp_path / "fresh")
    assert len(json.loads((tmp_path / "fresh/convert-physicalai-av.json").read_text())["converted"]) == 5

    calls.clear()  # in parts: the chunk's clips split between them; each part resumes where it stopped
    kill_at[0] = 2
    with pytest.raises(Killed):
        physicalai_av.convert(root, tmp_path / "in2", parts=2, part=1)  # clips 3, 4, 5: killed on clip 4
    calls.clear()
    physicalai_av.convert(root, tmp_path / "in2", parts=2).write()
    assert calls == [*clips[0:1], *clips[2:3], *clips[4:]]
    assert files(tmp_path / "in2") == files(tmp_path / "fresh")

    chunk = root / "camera/camera_front_wide_120fov/camera_front_wide_120fov.chunk_0000.zip"
    os.utime(chunk, ns=(chunk.stat().st_atime_ns, chunk.stat().st_mtime_ns + 10**9))
    calls.clear()  # the chunk's zip changed: each of its clips is converted again
    physicalai_av.convert(root, tmp_path / "out")
    assert calls == [c for c in clips if PAI_CLIPS[c][1]]


def test_a_missing_egomotion_chunk_is_one_skip_in_any_parts_and_stops_any_strict_part(tmp_path):
    """The chunk's first clip reports the chunk (as one item did when items were chunks), its other clips nothing."""
    root = physicalai_tree(tmp_path / "av", clips=PAI_CLIPS, drop_ego_chunk=True)
    report = physicalai_av.convert(root, tmp_path / "one")
    report.write()
    assert [(s.item, s.reason) for s in report.skipped] == [("chunk 0 (6 clips)", "egomotion chunk missing")]
    for parts in (2, 7):
        for part in reversed(range(parts)):
            physicalai_av.convert(root, tmp_path / f"in{parts}", parts=parts, part=part)
        physicalai_av.convert(root, tmp_path / f"in{parts}", parts=parts).write()
        assert files(tmp_path / f"in{parts}") == files(tmp_path / "one"), parts
    with pytest.raises(DatasetError, match="egomotion.chunk_0000.zip: missing, but"):  # part 1 lacks the first clip
        physicalai_av.convert(root, tmp_path / "strict", strict=True, parts=2, part=1)


def test_the_command_in_parts_and_a_limit_that_parts_cannot_keep(tmp_path, capsys):
    meta = opendv_tree(tmp_path / "opendv")
    command = ["convert", "opendv", "--meta", str(meta), "--videos", str(tmp_path / "opendv/videos"), "--out",
               str(tmp_path / "out"), "--parts", "2"]
    main([*command, "--part", "0"])
    assert "part 0000-of-0002: opendv: 2 videos converted" in capsys.readouterr().out
    assert not (tmp_path / "out/convert-opendv.json").exists()
    main(command)
    assert "opendv: 2 videos converted (0 with odometry), 2 skipped" in capsys.readouterr().out
    with pytest.raises(DatasetError, match="--limit 1 with --parts 2"):
        opendv.convert(meta, tmp_path / "opendv/videos", tmp_path / "limited", limit=1, parts=2)
    assert (tmp_path / "out.convert-parts/opendv" / part_name(1, 2) / "done.jsonl").is_file()
