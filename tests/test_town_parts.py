"""The town in parts: any number of parts renders the episodes, files and index of one part, byte for byte; a
stopped part resumes without rendering again the episodes it finished; the stage's parts then its gather."""

import dataclasses
import sys

import pytest
import yaml
from test_import import stage_env
from test_import_parts import parts_then_gather

from orbis2.data import town_dataset
from orbis2.data.episodes import RawIndex
from orbis2.data.parts import part_name
from orbis2.data.town_dataset import build_town_dataset, render_part, town_key

from conftest import ROOT


@pytest.fixture
def tiny(smoke_cfg):
    """Seven one-second episodes at 64x40 (one of each split, three of train; probe with labels), in one process."""
    town = dataclasses.replace(smoke_cfg.town, episodes={"train": 3, "val": 1, "turns": 1, "heldout": 1, "probe": 1},
                               episode_seconds=dict.fromkeys(smoke_cfg.town.episodes, 1.0), turns_candidates=2,
                               workers=1)
    return dataclasses.replace(smoke_cfg.data, width=64, height=40), town


def files(root):
    """Every file under ``root`` (relative path: bytes)."""
    return {p.relative_to(root).as_posix(): p.read_bytes() for p in sorted(root.rglob("*")) if p.is_file()}


@pytest.fixture
def whole(tiny, tmp_path):
    build_town_dataset(tmp_path / "one", *tiny)
    return files(tmp_path / "one")


@pytest.mark.parametrize("parts", [3, 9])  # 9: more parts than episodes
def test_any_parts_same_episodes(tiny, whole, tmp_path, parts):
    index = build_town_dataset(tmp_path / "many", *tiny, parts=parts)
    assert files(tmp_path / "many") == whole
    assert [e.stem for e in index.episodes][:3] == [f"town_train_{i:05d}" for i in range(3)]
    assert any(name.endswith(".labels.npz") for name in whole)


class Killed(BaseException):
    """Stands for SIGKILL: nothing after it runs."""


def test_a_killed_part_renders_again_only_the_episode_in_flight(tiny, whole, tmp_path, monkeypatch):
    """Killed while writing its third episode's video (half a file on disk): the restart renders that episode and
    those after it, removes the torn file first, and the result is the one part's."""
    calls, kill_at = [], [3]
    real = town_dataset.render_and_write

    def render_and_write(plan, root, *args):
        calls.append(plan.stem)
        if len(calls) == kill_at[0]:
            kill_at[0] = 0
            (root / plan.split).mkdir(parents=True, exist_ok=True)
            (root / plan.split / f"{plan.stem}.mp4").write_bytes(b"torn")
            raise Killed
        return real(plan, root, *args)

    monkeypatch.setattr(town_dataset, "render_and_write", render_and_write)
    work = tmp_path / "work"
    work.mkdir()
    with pytest.raises(Killed):
        render_part(work, *tiny, 0, 1)
    assert len((work / part_name(0, 1) / "done.jsonl").read_text().splitlines()) == 2
    calls.clear()
    build_town_dataset(tmp_path / "raw", *tiny, work=work)
    assert len(calls) == 7 - 2
    assert files(tmp_path / "raw") == whole
    calls.clear()  # gathered: the part's episodes were moved out, so asking for the part again renders it again
    render_part(work, *tiny, 0, 1)
    assert len(calls) == 7


def test_a_work_folder_of_other_settings_is_not_resumed(tiny, tmp_path):
    data, town = tiny
    build_town_dataset(tmp_path / "a", data, town, work=tmp_path / "work")
    other = dataclasses.replace(town, seed=town.seed + 1)
    build_town_dataset(tmp_path / "b", data, other, work=tmp_path / "work")
    assert RawIndex.read(tmp_path / "b").episodes[0].origin != RawIndex.read(tmp_path / "a").episodes[0].origin
    assert town_key(data, other) != town_key(data, town)


def test_the_stage_in_parts_then_the_gather(tmp_path):
    """`stages/town.py --part I --parts 2` per part (the DAG's `town_part` jobs), then the stage without --part:
    it gathers without rendering again, and gives the index of a one-part run."""
    params = yaml.safe_load((ROOT / "params.yaml").read_text())
    params["town"]["smoke"].update(episodes={"train": 2, "val": 1, "turns": 1, "heldout": 1, "probe": 1},
                                   turns_candidates=2)  # the smoke profile's lengths (its clips must fit)
    params["town"]["all"].update(workers=1, preview_seconds=1.0)
    (tmp_path / "params.yaml").write_text(yaml.safe_dump(params))
    env = stage_env(tmp_path)
    stage = [sys.executable, str(ROOT / "stages/town.py"), "--profile", "smoke"]
    assert "in 2 parts" in parts_then_gather(stage, 2, tmp_path, env, tmp_path / "data/town_parts")
    assert len(RawIndex.read(tmp_path / "data/raw/town").episodes) == 6
    assert (tmp_path / "reports/town_contact_sheet.png").is_file()
