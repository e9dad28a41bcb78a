"""Evaluation records: a smoke run's records re-write byte for byte through their types, and reading is strict."""

from __future__ import annotations

import json
import shutil

import pytest
from pydantic import ValidationError

from orbis2.errors import OrbisError
from orbis2.eval import records
from orbis2.eval.evaluate_records import EvaluateRecord
from orbis2.eval.report import tables
from orbis2.eval.report.evals import Evals, load_eval, read_evals

from conftest import ROOT

# The records of a finished smoke run, as its evaluation stages wrote them.
RECORDS = ROOT / "tests" / "fixtures" / "records"
KINDS = {"fvd_hierarchical": records.FvdRecord, "probe_abstract_tf": records.ProbeRecord,
         "steering": records.SteeringRecord, "speed": records.SpeedRecord, "conditioning": records.ConditioningRecord}


@pytest.mark.parametrize("name", sorted(KINDS))
def test_a_record_rewrites_byte_for_byte(tmp_path, name):
    """from_json then write_record gives the file back: same keys, values and float formatting (ints stay ints,
    keys written only sometimes stay absent, nulls stay null), so published records and DAG hashes hold."""
    source = RECORDS / f"{name}.json"
    record = records.from_json(KINDS[name], source, "a stage")
    records.write_record(tmp_path / source.name, record)
    assert (tmp_path / source.name).read_bytes() == source.read_bytes()


def test_keys_written_only_sometimes_are_left_out_and_nulls_kept():
    probe = json.loads((RECORDS / "probe_abstract_tf.json").read_text())
    record = records.ProbeRecord.model_validate(probe | {"block": None})  # a tokenizer's probe: no block
    assert records.to_json(record)["block"] is None and "per_block" not in records.to_json(record)
    fvd = records.from_json(records.FvdRecord, RECORDS / "fvd_hierarchical.json")
    assert fvd.chunked is not None and fvd.references["val"].real_floor.fvd is None
    assert "chunked" not in records.to_json(fvd.model_copy(update={"chunked": None}))  # a split that is not long


def test_a_stage_building_its_record_gets_no_coercion():
    """An int where the file holds a float (or a tuple for a list) would change the written bytes: it fails."""
    run = json.loads((RECORDS / "speed.json").read_text())["models"]["hierarchical"]
    assert records.to_json(records.SpeedRun(**run)) == run
    with pytest.raises(ValidationError, match="frames"):
        records.SpeedRun(**{**run, "frames": 10.0})
    with pytest.raises(ValidationError, match="predictors"):
        records.FvdRecord.model_validate({**json.loads((RECORDS / "fvd_hierarchical.json").read_text()),
                                          "predictors": ("abstract_tf", "detail")})


def _load_with(tmp_path, name: str, edit) -> Evals:
    folder = tmp_path / "eval"
    folder.mkdir()
    for file in RECORDS.glob("*.json"):
        shutil.copy(file, folder)
    doc = json.loads((folder / f"{name}.json").read_text())
    edit(doc)
    (folder / f"{name}.json").write_text(json.dumps(doc))
    return load_eval(folder)


def test_a_renamed_key_stops_the_read_naming_file_key_and_stage(tmp_path):
    def rename(doc):
        doc["chunked"]["fvd_slope_renamed"] = doc["chunked"].pop("fvd_slope")

    with pytest.raises(OrbisError) as err:
        _load_with(tmp_path, "fvd_hierarchical", rename)
    message = str(err.value)
    assert "fvd_hierarchical.json (written by stage eval_fvd_hierarchical)" in message
    assert "chunked.fvd_slope: missing key" in message and "chunked.fvd_slope_renamed: unknown key" in message
    assert message.endswith("re-run eval_fvd_hierarchical")


@pytest.mark.parametrize("name, edit, expected", [
    ("steering", lambda d: d["modes"]["original"].pop("ade_low"), r"steering\.json .*modes\.original\.ade_low: "
                                                                    r"missing key.*re-run eval_steering"),
    ("speed", lambda d: d["models"]["hierarchical"].update(fps="fast"), r"models\.hierarchical\.fps"),
    ("speed", lambda d: d.update(batch=1.0), r"speed\.json .*batch"),  # a float where the stage writes an int
    ("conditioning", lambda d: d["variants"][0].update(extra=1), r"variants\.0\.extra: unknown key"),
    ("probe_abstract_tf", lambda d: d.pop("data"), r"probe_abstract_tf\.json .*eval_probe_abstract_tf.*data"),
])
def test_every_kind_is_read_strictly(tmp_path, name, edit, expected):
    with pytest.raises(OrbisError, match=expected):
        _load_with(tmp_path, name, edit)


def test_an_unreadable_record_names_its_file(tmp_path):
    (tmp_path / "speed_all.json").write_text("{")
    with pytest.raises(OrbisError, match=r"cannot read .*speed_all\.json.*re-run eval_speed_all"):
        read_evals({}, {}, speed=tmp_path / "speed_all.json")


def test_the_reference_rows_are_fields_of_the_record():
    assert {ref for _, _, ref, _ in tables.FVD_REFERENCES} <= set(records.References.model_fields)


@pytest.mark.parametrize("split", ["heldout", "turns", "val"])
def test_a_published_evaluate_record_rewrites_byte_for_byte(tmp_path, split):
    """The records `orbis2 evaluate --out` wrote for the default run validate strictly and re-write to the same
    bytes (tests/test_evaluate.py checks one with steering scores and trajectories)."""
    source = ROOT / "docs" / "evaluate_default" / f"evaluate_{split}.json"
    record = EvaluateRecord.model_validate_json(source.read_text())
    records.write_record(tmp_path / source.name, record)
    assert (tmp_path / source.name).read_bytes() == source.read_bytes()
    assert record.references.real_floor.fvd is not None and record.steering is None


def test_the_guidance_selection_rewrites_byte_for_byte(tmp_path):
    """selection.json (tools/select_guidance.py, not key-sorted) validates strictly and dumps to the same bytes; a
    scale keyed as a number or a renamed key fails."""
    written = (ROOT / "docs" / "guidance_selection" / "selection.json").read_text()
    selection = records.GuidanceSelection.model_validate_json(written)
    assert selection.text() == written and selection.smaller_step_low_deg[f"{selection.chosen}"] > 0
    doc = json.loads(written)
    with pytest.raises(ValidationError, match="chosen_scale"):
        records.GuidanceSelection.model_validate_json(json.dumps({**doc, "chosen_scale": doc.pop("chosen")}))
    (tmp_path / "selection.json").write_text(json.dumps({**json.loads(written), "resolved": "yes"}))
    with pytest.raises(OrbisError, match=r"selection\.json .*resolved.*re-run tools/select_guidance"):
        records.from_json(records.GuidanceSelection, tmp_path / "selection.json", "tools/select_guidance.py")
