"""Dataset readers on small synthetic trees that follow each published layout field for field.

The layouts come from the datasets' own definitions (named in each builder's docstring): the
nuplan-devkit's schema (docs/nuplan_schema.md) and dataset setup page (docs/dataset_setup.md),
the PhysicalAI-AV interface's features.csv / clip_index.parquet (NVlabs/physical_ai_av), the
BDD100K download page (bdd100k/bdd100k doc/source/download.rst) and info-file format, and
OpenDV-YouTube's meta file (OpenDriveLab/DriveAGI, opendv). Nothing of theirs is copied here.

Each tree carries a known drive (speed 10 + 2 sin(0.2 t) m/s, yaw rate 0.3 + 0.05 sin(0.2 t)
rad/s, integrated into poses); the readers must recover speed and yaw rate within 1 % from
the poses (or fixes) alone, write what the importer reads, and stop on bad or partial trees
with a message naming the file.
"""

import io
import json
import os
import re
import shlex
import shutil
import sqlite3
import sys
import zipfile
from pathlib import Path

import av
import cv2
import numpy as np
import pandas as pd
import pytest

from orbis2.cli import main
from orbis2.config.params import load_config
from orbis2.data.datasets import DatasetError, bdd100k, nuplan, physicalai_av
from orbis2.data.importer import read_odometry_csv
from orbis2.data.shards import load_manifest
from orbis2.data.video import VideoError, probe, read_video, write_video
from orbis2.rollout import first_context_end

from conftest import ROOT, moving_pattern, project_copy, run

T0_US = 1_620_000_000_000_000  # a Unix time in microseconds, as the datasets store them


def truth(t):
    return 10 + 2 * np.sin(0.2 * t), 0.3 + 0.05 * np.sin(0.2 * t)


def drive(seconds: float, rate: float):
    """(t, x, y, heading) sampled at ``rate`` from the drive integrated at 1 kHz."""
    fine = np.arange(0, seconds + 1e-9, 1e-3)
    v, w = truth(fine)
    heading = np.concatenate([[0.0], np.cumsum(0.5 * (w[1:] + w[:-1]) * 1e-3)])
    x = np.concatenate([[0.0], np.cumsum(0.5 * (v[1:] * np.cos(heading[1:]) + v[:-1] * np.cos(heading[:-1])) * 1e-3)])
    y = np.concatenate([[0.0], np.cumsum(0.5 * (v[1:] * np.sin(heading[1:]) + v[:-1] * np.sin(heading[:-1])) * 1e-3)])
    t = np.arange(0, seconds + 1e-9, 1 / rate)
    return t, *(np.interp(t, fine, a) for a in (x, y, heading))


def assert_recovered(csv_path, offset=0.0, rel=0.01):
    """The CSV (read as the import stage reads it) holds the drive within ``rel``; ``offset``: drive time of 0 s."""
    odo = read_odometry_csv(csv_path)
    v, w = truth(odo["timestamp"] + offset)
    assert np.max(np.abs(odo["speed"] / v - 1)) < rel
    assert np.max(np.abs(odo["yaw_rate"] / w - 1)) < rel
    return odo


def frames(n, seed=0, size=(48, 64)):
    rng = np.random.default_rng(seed)
    return rng.integers(0, 255, (n, *size, 3), dtype=np.uint8)


# --------------------------------------------------------------------------- nuPlan


def nuplan_tree(root, seconds=6.0, drop_image=None, drop_table=None, size=(48, 64),
                log="2021.05.12.22.00.38_veh-35_01008_01518", blobs="sensor_blobs", with_images=True):
    """One log database and its CAM_F0 JPEGs, as the nuplan-devkit lays them out.

    Tables and columns: the devkit's docs/nuplan_schema.md (log, camera, image, ego_pose,
    lidar_pc; BLOB tokens, microsecond timestamps, UTM-sized x/y). Paths: its
    docs/dataset_setup.md (``nuplan-v1.1/splits/mini/<log>.db``, images under the sensor-blob
    root at ``image.filename_jpg`` = ``<log>/CAM_F0/<token>.jpg``). ``blobs`` names the folder
    the camera archive was unpacked to; ``with_images=False`` leaves them undownloaded.
    """
    db = root / "splits" / "mini" / f"{log}.db"
    db.parent.mkdir(parents=True, exist_ok=True)
    con = sqlite3.connect(db)
    tables = {
        "log": "token BLOB, vehicle_name TEXT, date TEXT, timestamp INTEGER, logfile TEXT, location TEXT, "
               "map_version TEXT",
        "camera": "token BLOB, log_token BLOB, channel TEXT, model TEXT, translation BLOB, rotation BLOB, "
                  "intrinsic BLOB, distortion BLOB, width INTEGER, height INTEGER",
        "image": "token BLOB, next_token BLOB, prev_token BLOB, ego_pose_token BLOB, camera_token BLOB, "
                 "filename_jpg TEXT, timestamp INTEGER",
        "ego_pose": "token BLOB, log_token BLOB, timestamp INTEGER, x REAL, y REAL, z REAL, qw REAL, qx REAL, "
                    "qy REAL, qz REAL, vx REAL, vy REAL, vz REAL, acceleration_x REAL, acceleration_y REAL, "
                    "acceleration_z REAL, angular_rate_x REAL, angular_rate_y REAL, angular_rate_z REAL, epsg INTEGER",
        "lidar_pc": "token BLOB, next_token BLOB, prev_token BLOB, scene_token BLOB, ego_pose_token BLOB, "
                    "lidar_token BLOB, filename TEXT, timestamp INTEGER",
    }
    for name, columns in tables.items():
        if name != drop_table:
            con.execute(f"CREATE TABLE {name} ({columns})")
    t, x, y, heading = drive(seconds, 100.0)  # nuPlan logs ego poses at ~100 Hz
    if drop_table != "ego_pose":
        con.executemany("INSERT INTO ego_pose (token, timestamp, x, y, z, qw, qx, qy, qz) VALUES (?,?,?,?,?,?,?,?,?)",
                        [(bytes([i % 256, i // 256]), T0_US + round(ti * 1e6), xi + 664_000.0, yi + 3_997_000.0,
                          0.0, np.cos(h / 2), 0.0, 0.0, np.sin(h / 2)) for i, (ti, xi, yi, h) in
                         enumerate(zip(t, x, y, heading))])
    if drop_table not in ("camera", "image"):
        for token, channel in ((b"f0", "CAM_F0"), (b"l0", "CAM_L0")):
            con.execute("INSERT INTO camera (token, channel, width, height) VALUES (?,?,?,?)", (token, channel, 64, 48))
        images = frames(int(seconds * 10), size=size)
        for i, image in enumerate(images):  # front images at 10 Hz, starting 50 ms after the first pose
            for token, channel in ((b"f0", "CAM_F0"), (b"l0", "CAM_L0")):
                name = f"{db.stem}/{channel}/{i:04x}.jpg"
                con.execute("INSERT INTO image (token, camera_token, filename_jpg, timestamp) VALUES (?,?,?,?)",
                            (f"{channel}{i}".encode(), token, name, T0_US + 50_000 + i * 100_000))
                if channel == "CAM_F0" and i != drop_image and with_images:
                    path = root / blobs / name
                    path.parent.mkdir(parents=True, exist_ok=True)
                    cv2.imwrite(str(path), image)
    con.commit()
    con.close()
    return db


def test_nuplan_front_camera_and_poses_become_a_clip_with_odometry(tmp_path):
    db = nuplan_tree(tmp_path / "nuplan")
    written = nuplan.convert(db.parent, [tmp_path / "nuplan" / "sensor_blobs"], tmp_path / "out", "val",
                             clip_seconds=20.0).videos
    assert [p.name for p in written] == [f"{db.stem}_000.mp4"]
    info = probe(written[0])
    assert (info.fps, info.frames, info.width) == (10.0, 60, 64)
    odo = assert_recovered(written[0].with_suffix(".csv"), offset=0.05)  # the first image is 50 ms after the pose
    assert len(odo["timestamp"]) == 60 and odo["timestamp"][0] == 0.0


def test_nuplan_turns_subset_keeps_clips_that_turn_enough(tmp_path):
    db = nuplan_tree(tmp_path / "nuplan")
    blobs = [tmp_path / "nuplan" / "sensor_blobs"]
    # 3-s clips turn by about 0.3 rad/s x 3 s = 52 degrees
    assert len(nuplan.convert(db, blobs, tmp_path / "a", "turns", clip_seconds=3.0, turns_deg=45).videos) == 2
    assert nuplan.convert(db, blobs, tmp_path / "b", "turns", clip_seconds=3.0, turns_deg=60).videos == []


def test_nuplan_split_with_logs_without_images_converts_the_rest_and_reports_them(tmp_path, capsys):
    """A split as downloaded: camera archives unpacked into two folders, one log's archive not downloaded,
    one log without camera data in its database, one image missing from a clip."""
    root = tmp_path / "nuplan-v1.1"
    nuplan_tree(root, seconds=3.0, log="2021.05.12.22.00.38_veh-35_01008_01518", blobs="camera_a")
    nuplan_tree(root, seconds=3.0, log="2021.06.09.17.23.18_veh-38_00773_01140", blobs="camera_b", drop_image=12)
    nuplan_tree(root, seconds=3.0, log="2021.10.11.08.31.07_veh-50_01750_01948", with_images=False)
    nuplan_tree(root, seconds=3.0, log="2021.07.16.20.45.29_veh-35_01095_01486", drop_table="image")
    out = tmp_path / "out"
    main(["convert", "nuplan", "--db", str(root / "splits" / "mini"), "--sensor-root", str(root / "camera_a"),
          str(root / "camera_b"), "--split", "val", "--clip-seconds", "1.5", "--out", str(out)])
    summary = capsys.readouterr().out
    assert ("nuplan: 3 videos converted (3 with odometry), 3 skipped (1 images not downloaded, 1 missing images, "
            "1 not a log database)") in summary
    report = json.loads((out / "convert-nuplan.json").read_text())
    skipped = {s["item"].rsplit("/", 1)[-1]: s for s in report["skipped"]}
    assert skipped["2021.06.09.17.23.18_veh-38_00773_01140_000"]["reason"] == "missing images"  # image 12: clip 0
    assert "camera archive is not downloaded" in skipped["2021.10.11.08.31.07_veh-50_01750_01948.db"]["problem"]
    assert sorted(p.name for p in (out / "val").glob("*.mp4")) == [
        "2021.05.12.22.00.38_veh-35_01008_01518_000.mp4", "2021.05.12.22.00.38_veh-35_01008_01518_001.mp4",
        "2021.06.09.17.23.18_veh-38_00773_01140_001.mp4"]
    with pytest.raises(DatasetError, match=r"_01140/CAM_F0/000c.jpg: missing or unreadable"):
        nuplan.convert(root / "splits" / "mini", [root / "camera_a", root / "camera_b"], tmp_path / "strict", "val",
                       clip_seconds=1.5, strict=True)


def test_nuplan_log_without_camera_data_is_reported_and_nothing_usable_exits_2(tmp_path, capsys):
    db = nuplan_tree(tmp_path / "a", drop_table="ego_pose")
    with pytest.raises(SystemExit) as exit_info:
        main(["convert", "nuplan", "--db", str(db), "--sensor-root", str(tmp_path / "a" / "sensor_blobs"),
              "--out", str(tmp_path / "out")])
    assert exit_info.value.code == 2
    err = capsys.readouterr().err
    assert "0 videos converted" in err and "nothing usable" in err and "convert-nuplan.json" in err
    problem = json.loads((tmp_path / "out" / "convert-nuplan.json").read_text())["skipped"][0]["problem"]
    assert "_01518.db: has no table 'ego_pose'" in problem
    assert not list((tmp_path / "out").rglob("*.mp4"))  # nothing half-written


# --------------------------------------------------------------------------- PhysicalAI-AV


FEATURES = pd.DataFrame({
    "feature": ["camera_front_wide_120fov", "egomotion"],
    "directory": ["camera", "labels"],
    "chunk_path": ["camera/camera_front_wide_120fov/camera_front_wide_120fov.chunk_{chunk_id:04d}.zip",
                   "labels/egomotion/egomotion.chunk_{chunk_id:04d}.zip"],
    "clip_files_in_zip": [json.dumps({"video": "{clip_id}.camera_front_wide_120fov.mp4",
                                      "frame_timestamps": "{clip_id}.camera_front_wide_120fov.timestamps.parquet"}),
                          json.dumps({"egomotion": "{clip_id}.egomotion.parquet"})],
})


CLIPS = {"25cd4769-5dcf-4b53-a351-bf2c5deb6124": ("train", True), "030c760c-ae38-49aa-9ad8-f5650a545d26": ("val", True),
         "7b6bd2e1-0f8f-4b4e-9a57-0d1c2b3a4f5e": ("train", False)}


def physicalai_tree(root, clips=CLIPS, drop_ego_chunk=False, n_frames=60, size=(48, 64), drop_member=None):
    """features.csv, clip_index.parquet and one chunk of the camera and egomotion zips.

    The layout the dataset's interface reads (NVlabs/physical_ai_av: ``features.csv`` with
    ``chunk_path`` and ``clip_files_in_zip`` templates; ``clip_index.parquet`` indexed by
    ``clip_id`` with ``chunk``, ``split`` and ``clip_is_valid``); a clip in chunk 1, not
    downloaded. ``drop_member``: a clip whose mp4 is missing from the zip.
    """
    root.mkdir(parents=True)
    FEATURES.to_csv(root / "features.csv", index=False)
    pd.DataFrame({"chunk": [0] * len(clips) + [1], "split": [s for s, _ in clips.values()] + ["train"],
                  "clip_is_valid": [v for _, v in clips.values()] + [True]},
                 index=pd.Index([*clips, "not-downloaded"], name="clip_id")).to_parquet(root / "clip_index.parquet")
    cam = root / FEATURES.chunk_path[0].format(chunk_id=0)
    ego = root / FEATURES.chunk_path[1].format(chunk_id=0)
    cam.parent.mkdir(parents=True)
    ego.parent.mkdir(parents=True)
    with zipfile.ZipFile(cam, "w") as cams, zipfile.ZipFile(ego, "w") as egos:
        for n, clip in enumerate(clips):
            write_video(root / "tmp.mp4", frames(n_frames, n, size), 30)
            if clip != drop_member:
                cams.write(root / "tmp.mp4", f"{clip}.camera_front_wide_120fov.mp4")
            buffer = io.BytesIO()
            pd.DataFrame({"timestamp": T0_US + 20_000 + np.arange(n_frames) * 33_333}).to_parquet(buffer)
            cams.writestr(f"{clip}.camera_front_wide_120fov.timestamps.parquet", buffer.getvalue())
            t, x, y, heading = drive(n_frames / 30 + 0.5, 10.0)  # egomotion at 10 Hz
            buffer = io.BytesIO()
            pd.DataFrame({"timestamp": T0_US + np.round(t * 1e6).astype(np.int64), "x": x, "y": y, "z": 0.0,
                          "qx": 0.0, "qy": 0.0, "qz": np.sin(heading / 2), "qw": np.cos(heading / 2),
                          "vx": 0.0, "vy": 0.0, "vz": 0.0, "ax": 0.0, "ay": 0.0, "az": 0.0, "curvature": 0.0}
                         ).to_parquet(buffer)
            egos.writestr(f"{clip}.egomotion.parquet", buffer.getvalue())
    (root / "tmp.mp4").unlink()
    if drop_ego_chunk:
        ego.unlink()
    return root


def test_physicalai_av_clips_go_to_their_split_and_invalid_ones_are_reported(tmp_path):
    root = physicalai_tree(tmp_path / "pai")
    report = physicalai_av.convert(root, tmp_path / "out")
    assert [p.relative_to(tmp_path / "out").as_posix() for p in report.videos] == [
        "train/25cd4769-5dcf-4b53-a351-bf2c5deb6124.mp4", "val/030c760c-ae38-49aa-9ad8-f5650a545d26.mp4"]
    assert [(s.item, s.reason) for s in report.skipped] == [("7b6bd2e1-0f8f-4b4e-9a57-0d1c2b3a4f5e",
                                                             "clip_is_valid false")]
    assert report.notes == {"clips in chunks not downloaded": 1}
    assert probe(report.videos[0]).frames == 60
    odo = assert_recovered(report.videos[0].with_suffix(".csv"), offset=0.02)
    assert odo["timestamp"][-1] == pytest.approx(59 * 0.033333)
    # the overrides: every clip into one split, invalid ones included
    report = physicalai_av.convert(root, tmp_path / "all", split="train", include_invalid=True)
    assert len(report.videos) == 3 and not report.skipped
    assert {p.parent.name for p in report.videos} == {"train"}


def test_physicalai_av_partial_download_skips_and_reports(tmp_path):
    root = physicalai_tree(tmp_path / "pai", drop_member="030c760c-ae38-49aa-9ad8-f5650a545d26")
    report = physicalai_av.convert(root, tmp_path / "out")
    assert [(s.item, s.reason) for s in report.skipped][0] == ("030c760c-ae38-49aa-9ad8-f5650a545d26",
                                                               "incomplete chunk")
    assert [p.parent.name for p in report.videos] == ["train"] and not list((tmp_path / "out").rglob("030c*"))
    root = physicalai_tree(tmp_path / "pai2", drop_ego_chunk=True)
    report = physicalai_av.convert(root, tmp_path / "out2")
    assert not report.videos and report.skipped[0].reason == "egomotion chunk missing"
    assert "egomotion.chunk_0000.zip: missing, but" in report.skipped[0].problem
    (root / "features.csv").unlink()
    with pytest.raises(DatasetError, match=r"features.csv: missing"):
        physicalai_av.convert(root, tmp_path / "out")


# --------------------------------------------------------------------------- BDD100K


def bdd_info(start_ms, seconds, first_fix_s=0.4, gyro=True, course_noise_deg=0.0):
    """One info file of the 100K release: ``rideID``, ``startTime``/``endTime`` (ms), ``locations`` (1-Hz fused
    fixes: ``timestamp`` ms, ``latitude``, ``longitude``, ``speed`` m/s, ``course`` degrees clockwise from
    north, ``accuracy``) and the raw ``gyro``/``accelerometer`` streams (``timestamp``, ``x``, ``y``, ``z``, in
    the phone's axes), as the BDD100K info archive publishes them (one unknown fix, speed -1, among them).

    The phone is tilted (its vertical is not an axis) and reads gravity as negative, so the gyro's yaw rate
    must be found along the accelerometer's direction with the sign the course agrees with."""
    t, x, y, heading = drive(seconds + first_fix_s + 3, 50.0)
    v, w = truth(t)
    rng = np.random.default_rng(0)
    fixes = np.flatnonzero(np.isclose((t - first_fix_s) % 1.0, 0, atol=1e-6) & (t >= first_fix_s - 1e-9))
    course = (np.degrees(-heading[fixes]) + rng.normal(0, course_noise_deg, len(fixes))) % 360
    locations = [{"timestamp": start_ms + round(t[i] * 1000), "latitude": 40.7, "longitude": -73.9,
                  "speed": float(v[i]), "course": float(c), "accuracy": 10.0} for i, c in zip(fixes, course)]
    locations.insert(2, {**locations[2], "timestamp": locations[2]["timestamp"] + 1, "speed": -1.0})
    up = np.array([0.1, -0.98, 0.17]) / np.linalg.norm([0.1, -0.98, 0.17])  # the accelerometer's mean direction
    side = np.cross(up, [1.0, 0.0, 0.0])
    rates = -w[:, None] * up + 0.02 * np.sin(3 * t)[:, None] * side  # yaw about -up, plus some pitching
    info = {"rideID": "f9a4cba2", "startTime": start_ms, "endTime": start_ms + round(seconds * 1000),
            "locations": locations, "gps": [],
            "gyro": [{"timestamp": start_ms + round(ti * 1000), "x": a, "y": b, "z": c}
                     for ti, (a, b, c) in zip(t, rates)] if gyro else [],
            "accelerometer": [{"timestamp": start_ms + round(ti * 1000), "x": a, "y": b, "z": c}
                              for ti, (a, b, c) in zip(t, 9.81 * up + rng.normal(0, 0.3, (len(t), 3)))]}
    return info


def bdd_tree(root, videos=None, n_frames=90, size=(48, 64), layout="", split="train", fps=30):
    """``videos/<layout>/train/<name>.mov`` and ``info/100k/train/<name>.json``: the layout of the BDD100K
    download page (bdd100k/bdd100k doc/source/download.rst); ``layout="100k"`` is the older video archive's
    ``videos/100k/train/``. ``videos`` maps names to :func:`bdd_info` arguments, None for no info file."""
    videos = videos or {"b1c66a42-6f7d68ca": {}}
    for n, (name, args) in enumerate(videos.items()):
        video = root / "videos" / layout / split / f"{name}.mov"
        video.parent.mkdir(parents=True, exist_ok=True)
        images = frames(n_frames, n, size=size) if size != "moving" else moving_pattern(n_frames, 192, 108, seed=n)
        write_video(video, images, fps)
        if args is not None:
            path = root / "info" / "100k" / split / f"{name}.json"
            path.parent.mkdir(parents=True, exist_ok=True)
            path.write_text(json.dumps(bdd_info(1_503_835_467_014, n_frames / fps, **args)))
    return root


def test_bdd100k_gyro_gives_the_yaw_rate_and_a_late_first_fix_is_bridged(tmp_path):
    root = bdd_tree(tmp_path / "bdd100k", {"b1c66a42-6f7d68ca": {"first_fix_s": 2.3, "course_noise_deg": 8.0}},
                    layout="100k")
    report = bdd100k.convert(root, tmp_path / "out")
    assert [p.name for p in report.videos] == ["b1c66a42-6f7d68ca.mov"] and report.videos[0].is_symlink()
    assert {k: report.converted[0][k] for k in ("bridged_s", "yaw_rate_from")} == {"bridged_s": 2.3,
                                                                                 "yaw_rate_from": "gyro"}
    odo = read_odometry_csv(report.videos[0].with_suffix(".csv"))
    v, w = truth(odo["timestamp"])
    assert odo["timestamp"][0] == 0.0 and np.max(np.abs(odo["yaw_rate"] / w - 1)) < 0.01  # the gyro, from 0 s
    after = odo["timestamp"] >= 2.3
    assert np.max(np.abs(odo["speed"][after] / v[after] - 1)) < 0.01
    assert np.all(odo["speed"][~after] == odo["speed"][after][0])  # held back over the bridged span


def test_bdd100k_without_a_gyro_takes_the_yaw_rate_from_the_course(tmp_path):
    report = bdd100k.convert(bdd_tree(tmp_path / "bdd100k", {"b1c66a42-6f7d68ca": {"gyro": False}}),
                             tmp_path / "out")
    assert report.converted[0]["yaw_rate_from"] == "course"
    odo = read_odometry_csv(report.videos[0].with_suffix(".csv"))
    assert odo["timestamp"][0] == 0.0 and odo["timestamp"][1] == pytest.approx(0.4)  # the first fix held back to 0 s
    v, w = truth(odo["timestamp"][1:])
    assert np.max(np.abs(odo["speed"][1:] / v - 1)) < 0.01 and np.max(np.abs(odo["yaw_rate"][1:] / w - 1)) < 0.01


def test_bdd100k_skips_and_reports_late_fixes_and_missing_info(tmp_path, capsys):
    root = bdd_tree(tmp_path / "bdd100k", {"a-late": {"first_fix_s": 6.0}, "b-good": {}, "c-noinfo": None})
    main(["convert", "bdd100k", "--root", str(root), "--out", str(tmp_path / "out")])
    assert "bdd100k: 1 videos converted (1 with odometry), 2 skipped (1 late first fix, 1 no info file)" in (
        capsys.readouterr().out)
    skipped = json.loads((tmp_path / "out" / "convert-bdd100k.json").read_text())["skipped"]
    assert "a-late.json: the first location fix is 6.00 s after the first frame" in skipped[0]["problem"]
    assert "c-noinfo.json: missing" in skipped[1]["problem"]
    report = bdd100k.convert(root, tmp_path / "out2", allow_missing_info=True, max_fix_delay=7.0)
    assert len(report.videos) == 3 and report.converted[0]["bridged_s"] == 6.0
    assert not (tmp_path / "out2" / "train" / "c-noinfo.csv").exists()


# --------------------------------------------------------------------------- OpenDV-YouTube


def encode(path, images, fps, codec="libsvtav1", live=False):
    """Write frames with PyAV's FFmpeg (``libsvtav1``: AV1, ``libx264``: H.264, ``libx265``: HEVC); ``live``:
    a Matroska/WebM header without a duration, as streamed downloads have (OpenCV then reports about -2.3e17
    frames)."""
    path.parent.mkdir(parents=True, exist_ok=True)
    policy, param = os.sched_getscheduler(0), os.sched_getparam(0)
    try:
        with av.open(str(path), "w", options={"live": "1"} if live else {}) as out:
            stream = out.add_stream(codec, rate=fps)
            stream.width, stream.height, stream.pix_fmt = images.shape[2], images.shape[1], "yuv420p"
            for image in images:
                out.mux(stream.encode(av.VideoFrame.from_ndarray(image, format="rgb24")))
            out.mux(stream.encode())
    finally:  # SVT-AV1, run as root, puts the calling thread in the real-time class (SCHED_FIFO 99), which the
        # rest of the worker's tests and everything they start would inherit, the smoke build starving beside them
        os.sched_setscheduler(0, policy, param)
    return path


def opendv_tree(root, n_frames=60, size=(48, 64)):
    """``meta/OpenDV-YouTube.json`` and ``<youtuber with _>/<videoid>.<ext>``: the meta file's fields (``id``,
    ``youtuber``, ``videoid``, ``split`` Train/Val, ``start_discard``, ``end_discard``, ``duration``, ``length``)
    and the download script's paths as OpenDV-YouTube (OpenDriveLab/DriveAGI, opendv/) publishes them.

    The entries cover what real downloads bring: an mp4; an AV1 webm streamed without a duration in its header
    and with blank discard cells (NaN after the CSV meta became JSON); a video YouTube removed; an entry with an
    unknown split."""
    meta = root / "meta" / "OpenDV-YouTube.json"
    meta.parent.mkdir(parents=True)
    entries = [{"id": 1, "youtuber": "J Utah", "videoid": "qGjPSiWdU3A", "split": "Train", "start_discard": 1,
                "end_discard": 2, "duration": "00:06", "length": 6},
               {"id": 2, "youtuber": "Driving Experience", "videoid": "5W0mtP1x9VE", "split": "Val",
                "start_discard": float("nan"), "end_discard": "", "duration": "00:06", "length": 6},
               {"id": 3, "youtuber": "J Utah", "videoid": "removed0000", "split": "Train", "start_discard": 0,
                "end_discard": 0, "duration": "00:06", "length": 6},
               {"id": 4, "youtuber": "J Utah", "videoid": "odd00000000", "split": "Test", "start_discard": 0,
                "end_discard": 0, "duration": "00:06", "length": 6}]
    meta.write_text(json.dumps(entries))
    write_video(root / "videos" / "J_Utah" / "qGjPSiWdU3A.mp4", frames(n_frames, 0, size), 10)
    encode(root / "videos" / "Driving_Experience" / "5W0mtP1x9VE.webm", frames(n_frames, 1, size), 10, live=True)
    return meta


def test_opendv_real_downloads_convert_or_are_reported(tmp_path, capsys):
    meta = opendv_tree(tmp_path / "opendv")
    main(["convert", "opendv", "--meta", str(meta), "--videos", str(tmp_path / "opendv" / "videos"),
          "--out", str(tmp_path / "out")])
    assert "opendv: 2 videos converted (0 with odometry), 2 skipped (1 bad meta entry, 1 not downloaded)" in (
        capsys.readouterr().out)
    report = json.loads((tmp_path / "out" / "convert-opendv.json").read_text())
    mp4, webm = report["converted"]
    assert webm["codec"] == "AV01" and webm["frames_counted_by_decoding"] == 60
    assert webm["blank_cells"] == ["start_discard", "end_discard"] and "blank_cells" not in mp4
    assert len(read_video(mp4["video"])) == 30 and len(read_video(webm["video"])) == 60  # 1 s + 2 s dropped at 10 fps
    assert [p.relative_to(tmp_path / "out").as_posix() for p in map(Path, (mp4["video"], webm["video"]))] == [
        "train/qGjPSiWdU3A.mp4", "val/5W0mtP1x9VE.mp4"]
    assert not list((tmp_path / "out").rglob("*.csv"))
    assert "J_Utah/removed0000.mp4: missing" in report["skipped"][0]["problem"]
    assert "entry 3 has split 'Test'" in report["skipped"][1]["problem"]
    with pytest.raises(SystemExit) as exit_info:
        main(["convert", "opendv", "--meta", str(meta), "--videos", str(tmp_path / "opendv" / "videos"),
              "--out", str(tmp_path / "strict"), "--strict"])
    assert exit_info.value.code == 2 and "removed0000.mp4: missing" in capsys.readouterr().err


def test_a_codec_nothing_decodes_is_named(tmp_path):
    """An AV1 stream cut after its header: OpenCV opens it and decodes nothing, and PyAV can read no frame."""
    path = encode(tmp_path / "cut.mkv", frames(20, 0), 10)
    path.write_bytes(path.read_bytes()[:600])
    with pytest.raises(VideoError, match=r"cut.mkv: no frame could be decoded from its (libdav1d|av1) video stream"):
        read_video(path)


def test_the_documented_commands_convert_trees_laid_out_as_documented(tmp_path, monkeypatch, capsys):
    """Each `orbis2 convert` command of docs/datasets.md, as written, on trees at the paths it names."""
    from test_docs import documented_commands

    commands = [c.text for c in documented_commands(ROOT / "docs" / "datasets.md") if c.text.startswith("orbis2 ")]
    assert {shlex.split(c)[2] for c in commands} == {"nuplan", "physicalai-av", "bdd100k", "opendv"}
    nuplan_tree(tmp_path / "nuplan-v1.1")
    for n, blobs in enumerate(("nuplan-sensor-blobs-1", "nuplan-sensor-blobs-2")):
        nuplan_tree(tmp_path / "nuplan-v1.1", log=f"2021.06.09.17.23.18_veh-38_0077{n}_01140",
                    blobs=f"../{blobs}")
    physicalai_tree(tmp_path / "PhysicalAI-Autonomous-Vehicles")
    bdd_tree(tmp_path / "bdd100k")
    opendv_tree(tmp_path / "OpenDV-YouTube")
    monkeypatch.chdir(tmp_path)
    for command in commands:
        main(shlex.split(command)[1:])
        summary = capsys.readouterr().out
        assert re.search(r": [1-9]\d* videos converted", summary), (command, summary)


def test_a_25_fps_source_plays_through_shards_latents_and_evaluate(smoke_main, tmp_path):
    """BDD100K-layout videos at 25 frames/s (with gyro odometry) -> convert -> import -> shards -> latents with
    the smoke project's tokenizers -> rollouts of the smoke model from the imported episodes -> orbis2 evaluate.

    The FVD itself means nothing at this scale; what is checked is that nothing downstream refuses or
    misreads data that came in at 25 frames/s."""
    root = project_copy(tmp_path / "project")
    for folder in ("data/tokenizers", "data/predictors", "data/assets"):
        shutil.copytree(smoke_main / folder, root / folder, symlinks=True)
    source = tmp_path / "bdd100k"
    for split, names in (("train", ("t-25fps-0", "t-25fps-1")), ("val", ("v-25fps-0", "v-25fps-1"))):
        bdd_tree(source, {name: {"first_fix_s": 1.6} for name in names}, n_frames=160, size="moving", split=split,
                 fps=25)
    out = run([sys.executable, "-m", "orbis2.cli", "convert", "bdd100k", "--root", str(source), "--out",
               "data/videos"], root)
    assert "bdd100k: 4 videos converted (4 with odometry)" in out
    run([sys.executable, "stages/import.py", "--videos", "data/videos"], root)
    index = json.loads((root / "data/raw/import/index.json").read_text())
    assert {e["source_fps"] for e in index["episodes"]} == {25.0}
    assert max(e["timing_error_ms"] for e in index["episodes"]) == pytest.approx(20.0, abs=0.01)
    assert {e["frames"] for e in index["episodes"]} == {64}  # 159 frames at 25 fps span 6.36 s -> 64 at 10 fps
    run([sys.executable, "stages/shards.py", "--raw", "data/raw/import"], root)
    assert load_manifest(root / "data/shards")["splits"]["val"]["samples"] == 2
    run([sys.executable, "stages/latents.py"], root)
    assert (root / "data/latents").is_dir()
    cfg = load_config(root / "params.yaml", "smoke")
    start = first_context_end(cfg.data) - (cfg.data.detail_context - 1)  # the rollout's first detail-context frame
    for episode in sorted(e["stem"] for e in index["episodes"] if e["split"] == "val"):
        video = root / "data/raw/import/val" / f"{episode}.mp4"
        run([sys.executable, "-m", "orbis2.cli", "rollout", "--video", str(video), "--seconds", "2", "--out",
             f"rollouts/generated/{episode}.mp4"], root)
        write_video(root / "rollouts/real" / f"{episode}.mkv", read_video(video)[start:], cfg.data.fps, lossless=True)
    out = run([sys.executable, "-m", "orbis2.cli", "evaluate", "--generated", "rollouts/generated", "--real",
               "rollouts/real", "--context-frames", str(cfg.data.detail_context), "--generated-has-context",
               "--out", "rollouts/evaluate.json"], root)
    record = json.loads((root / "rollouts/evaluate.json").read_text())
    assert "FVD (2 s)" in out and record["protocol"]["fps"] == 10.0 and record["protocol"]["videos"] == 2
