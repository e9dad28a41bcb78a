"""Dataset readers on small synthetic trees that follow each published layout field for field.

Each tree carries a known drive (speed 10 + 2 sin(0.2 t) m/s, yaw rate 0.3 + 0.05 sin(0.2 t)
rad/s, integrated into poses); the readers must recover speed and yaw rate within 1 % from
the poses (or fixes) alone, write what the importer reads, and stop on bad or partial trees
with a message naming the file.
"""

import io
import json
import sqlite3
import zipfile

import cv2
import numpy as np
import pandas as pd
import pytest

from orbis2.cli import main
from orbis2.data.datasets import DatasetError, bdd100k, nuplan, opendv, physicalai_av
from orbis2.data.importer import read_odometry_csv
from orbis2.data.video import probe, read_video, write_video

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


def nuplan_tree(root, seconds=6.0, drop_image=None, drop_table=None, size=(48, 64)):
    """One log database (camera, image, ego_pose, lidar_pc as in the devkit schema) and its CAM_F0 JPEGs."""
    db = root / "splits" / "mini" / "2021.05.12.22.00.38_veh-35_01008_01518.db"
    db.parent.mkdir(parents=True)
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
                if channel == "CAM_F0" and i != drop_image:
                    path = root / "sensor_blobs" / name
                    path.parent.mkdir(parents=True, exist_ok=True)
                    cv2.imwrite(str(path), image)
    con.commit()
    con.close()
    return db


def test_nuplan_front_camera_and_poses_become_a_clip_with_odometry(tmp_path):
    db = nuplan_tree(tmp_path / "nuplan")
    written = nuplan.convert(db.parent, tmp_path / "nuplan" / "sensor_blobs", tmp_path / "out", "val",
                             clip_seconds=20.0)
    assert [p.name for p in written] == [f"{db.stem}_000.mp4"]
    info = probe(written[0])
    assert (info.fps, info.frames, info.width) == (10.0, 60, 64)
    odo = assert_recovered(written[0].with_suffix(".csv"), offset=0.05)  # the first image is 50 ms after the pose
    assert len(odo["timestamp"]) == 60 and odo["timestamp"][0] == 0.0


def test_nuplan_turns_subset_keeps_clips_that_turn_enough(tmp_path):
    db = nuplan_tree(tmp_path / "nuplan")
    blobs = tmp_path / "nuplan" / "sensor_blobs"
    # 3-s clips turn by about 0.3 rad/s x 3 s = 52 degrees
    assert len(nuplan.convert(db, blobs, tmp_path / "a", "turns", clip_seconds=3.0, turns_deg=45)) == 2
    assert nuplan.convert(db, blobs, tmp_path / "b", "turns", clip_seconds=3.0, turns_deg=60) == []


def test_nuplan_partial_trees_stop_naming_the_file(tmp_path):
    db = nuplan_tree(tmp_path / "a", drop_image=7)
    with pytest.raises(DatasetError, match=r"CAM_F0/0007.jpg: missing or unreadable.*download the sensor blobs"):
        nuplan.convert(db, tmp_path / "a" / "sensor_blobs", tmp_path / "out", "val")
    assert not list((tmp_path / "out").rglob("*.mp4"))  # nothing half-written
    db = nuplan_tree(tmp_path / "b", drop_table="ego_pose")
    with pytest.raises(DatasetError, match=r"_01518.db: has no table 'ego_pose'"):
        nuplan.convert(db, tmp_path / "b" / "sensor_blobs", tmp_path / "out", "val")


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


def physicalai_tree(root, clips=("25cd4769-5dcf-4b53-a351-bf2c5deb6124",), drop_ego_chunk=False, n_frames=60,
                    size=(48, 64)):
    root.mkdir(parents=True)
    FEATURES.to_csv(root / "features.csv", index=False)
    pd.DataFrame({"chunk": [0] * len(clips) + [1]}, index=pd.Index([*clips, "not-downloaded"], name="clip_id")
                 ).to_parquet(root / "clip_index.parquet")
    cam = root / FEATURES.chunk_path[0].format(chunk_id=0)
    ego = root / FEATURES.chunk_path[1].format(chunk_id=0)
    cam.parent.mkdir(parents=True)
    ego.parent.mkdir(parents=True)
    with zipfile.ZipFile(cam, "w") as cams, zipfile.ZipFile(ego, "w") as egos:
        for n, clip in enumerate(clips):
            write_video(root / "tmp.mp4", frames(n_frames, n, size), 30)
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


def test_physicalai_av_chunks_become_clips_with_odometry(tmp_path):
    root = physicalai_tree(tmp_path / "pai")
    written = physicalai_av.convert(root, tmp_path / "out")
    assert [p.name for p in written] == ["25cd4769-5dcf-4b53-a351-bf2c5deb6124.mp4"]  # chunk 1 is not downloaded
    assert probe(written[0]).frames == 60
    odo = assert_recovered(written[0].with_suffix(".csv"), offset=0.02)
    assert odo["timestamp"][-1] == pytest.approx(59 * 0.033333)


def test_physicalai_av_partial_download_stops_naming_the_file(tmp_path):
    root = physicalai_tree(tmp_path / "pai", drop_ego_chunk=True)
    with pytest.raises(DatasetError, match=r"egomotion.chunk_0000.zip: missing, but .* download the egomotion chunk"):
        physicalai_av.convert(root, tmp_path / "out")
    (root / "features.csv").unlink()
    with pytest.raises(DatasetError, match=r"features.csv: missing"):
        physicalai_av.convert(root, tmp_path / "out")


# --------------------------------------------------------------------------- BDD100K


def bdd_tree(root, missing_info=False, n_frames=240, size=(48, 64)):
    video = root / "videos" / "train" / "b1c66a42-6f7d68ca.mov"
    video.parent.mkdir(parents=True)
    write_video(video, frames(n_frames, size=size), 30)
    if missing_info:
        return root
    start_ms = 1_503_835_467_014
    t, x, y, heading = drive(n_frames / 30 + 2, 1.0)  # location fixes at 1 Hz, the first 0.4 s after the first frame
    v, _ = truth(t)
    course = np.degrees(-heading) % 360  # clockwise from north, as the phones report it
    info = {"rideID": "f9a4cba2", "startTime": start_ms, "endTime": start_ms + 40_000, "filename": video.name,
            "gps": [], "gyro": [], "accelerometer": [],
            "locations": [{"timestamp": start_ms + 400 + round(ti * 1000), "latitude": 40.7, "longitude": -73.9,
                           "speed": float(vi), "course": float(ci), "accuracy": 10.0}
                          for ti, vi, ci in zip(t, v, course)]}
    info["locations"].insert(3, {**info["locations"][3], "timestamp": info["locations"][3]["timestamp"] + 1,
                                 "speed": -1.0})  # an unknown fix, dropped
    path = root / "info" / "100k" / "train" / f"{video.stem}.json"
    path.parent.mkdir(parents=True)
    path.write_text(json.dumps(info))
    return root


def test_bdd100k_info_files_give_the_odometry(tmp_path):
    written = bdd100k.convert(bdd_tree(tmp_path / "bdd100k"), tmp_path / "out")
    assert [p.name for p in written] == ["b1c66a42-6f7d68ca.mov"] and written[0].is_symlink()
    odo = read_odometry_csv(written[0].with_suffix(".csv"))
    assert odo["timestamp"][0] == 0.0 and odo["timestamp"][1] == pytest.approx(0.4)  # the first fix held back to 0 s
    v, w = truth(odo["timestamp"][1:] - 0.4)
    assert np.max(np.abs(odo["speed"][1:] / v - 1)) < 0.01 and np.max(np.abs(odo["yaw_rate"][1:] / w - 1)) < 0.01


def test_bdd100k_missing_info_stops_unless_allowed(tmp_path):
    root = bdd_tree(tmp_path / "bdd100k", missing_info=True)
    with pytest.raises(DatasetError, match=r"info/100k/train/b1c66a42-6f7d68ca.json: missing .* --allow-missing-info"):
        bdd100k.convert(root, tmp_path / "out")
    written = bdd100k.convert(root, tmp_path / "out", allow_missing_info=True)
    assert written and not written[0].with_suffix(".csv").exists()


# --------------------------------------------------------------------------- OpenDV-YouTube


def opendv_tree(root, missing=False, n_frames=60, size=(48, 64)):
    meta = root / "meta" / "OpenDV-YouTube.json"
    meta.parent.mkdir(parents=True)
    entries = [{"id": 1, "youtuber": "J Utah", "videoid": "qGjPSiWdU3A", "split": "Train", "start_discard": 1,
                "end_discard": 2, "duration": "00:06", "length": 6},
               {"id": 2, "youtuber": "Driving Experience", "videoid": "5W0mtP1x9VE", "split": "Val",
                "start_discard": 0, "end_discard": 0, "duration": "00:06", "length": 6}]
    meta.write_text(json.dumps(entries))
    for n, entry in enumerate(entries[: 1 if missing else 2]):
        write_video(root / "videos" / entry["youtuber"].replace(" ", "_") / f"{entry['videoid']}.mp4",
                    frames(n_frames, n, size), 10)
    return meta


def test_opendv_videos_lose_their_discarded_ends_and_stay_unconditional(tmp_path):
    meta = opendv_tree(tmp_path / "opendv")
    written = opendv.convert(meta, tmp_path / "opendv" / "videos", tmp_path / "out")
    assert [p.relative_to(tmp_path / "out").as_posix() for p in written] == ["train/qGjPSiWdU3A.mp4",
                                                                             "val/5W0mtP1x9VE.mp4"]
    assert len(read_video(written[0])) == 30 and len(read_video(written[1])) == 60  # 1 s + 2 s dropped at 10 fps
    assert not list((tmp_path / "out").rglob("*.csv"))


def test_opendv_missing_videos_stop_unless_allowed_and_the_cli_exits_2(tmp_path, capsys):
    meta = opendv_tree(tmp_path / "opendv", missing=True)
    with pytest.raises(SystemExit) as exit_info:
        main(["convert", "opendv", "--meta", str(meta), "--videos", str(tmp_path / "opendv" / "videos"),
              "--out", str(tmp_path / "out")])
    assert exit_info.value.code == 2
    assert "Driving_Experience/5W0mtP1x9VE.mp4: missing (1 of 2" in capsys.readouterr().err
    main(["convert", "opendv", "--meta", str(meta), "--videos", str(tmp_path / "opendv" / "videos"),
          "--out", str(tmp_path / "out"), "--allow-missing"])
    assert "opendv: 1 videos (0 with odometry)" in capsys.readouterr().out
