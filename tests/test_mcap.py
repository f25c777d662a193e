"""MCAP export read back with the mcap reader: frames, ranges, images, poses and stamps; one
image topic per elevation for a dataset of several; shards of format 1 still export."""

import shutil

import h5py
import numpy as np
import pytest

from acoustic_sim.cli import main
from acoustic_sim.datasets.shards import COMPRESSION
from acoustic_sim.formats.mcap_export import EPISODE_GAP_S, STAMP_START_S, energyscape_topics


def messages(path, topic=None) -> dict:
    """The decoded messages of an MCAP file by topic (or of `topic` alone): [(log time, message)]."""
    from mcap.reader import make_reader
    from mcap_ros2.decoder import DecoderFactory

    found = {}
    with open(path, "rb") as f:
        for _, channel, message, decoded in make_reader(
            f, decoder_factories=[DecoderFactory()]
        ).iter_decoded_messages():
            if topic in (None, channel.topic):
                found.setdefault(channel.topic, []).append((message.log_time, decoded))
    return found


def pixels(image) -> np.ndarray:
    """A 32FC1 sensor_msgs/Image as float32 (height, width), after checking its layout."""
    assert image.encoding == "32FC1" and image.step == 4 * image.width and image.is_bigendian == 0
    return np.frombuffer(bytes(image.data), "<f4").reshape(image.height, image.width)


def restack(dataset, folder, elevations, slices):
    """A copy of `dataset` in `folder` whose shards hold (frame, E, range, azimuth) energyscapes:
    slice j is `slices[j]` of the original level slice (frame, range, azimuth), at `elevations[j]`."""
    folder.mkdir()
    for path in sorted(dataset.glob("shard-*.h5")):
        copy = folder / path.name
        shutil.copy(path, copy)
        with h5py.File(copy, "r+") as f:
            level = f["energyscape"][:, 0]
            del f["energyscape"], f["elevation_deg"]
            stack = np.stack([make(level) for make in slices], axis=1).astype(np.float16)
            f.create_dataset("energyscape", data=stack, chunks=(1, *stack.shape[1:]), **COMPRESSION)
            f["elevation_deg"] = np.asarray(elevations, np.float64)
    return folder


def test_export_reads_back_as_the_dataset(tiny_dataset, tmp_path):
    out = tmp_path / "drive.mcap"
    assert main(["export", str(tiny_dataset), "--format", "mcap", "--out", str(out)]) == 0
    shards = sorted(tiny_dataset.glob("shard-*.h5"))
    truth = {k: [] for k in ("ranges", "energy", "pose", "time", "episode")}
    for path in shards:
        with h5py.File(path, "r") as f:
            assert f["energyscape"].shape[1] == 1  # one elevation: the topic of datasets before elevations
            for key, name in (("ranges", "lidar/ranges"), ("pose", "pose")):
                truth[key].append(f[name][:])
            truth["energy"].append(f["energyscape"][:, 0])
            truth["time"].append(f["time"][:])
            truth["episode"].append(f["episode"][:] + 1000 * len(truth["episode"]))
    truth = {k: np.concatenate(v) for k, v in truth.items()}
    found = messages(out)
    assert sorted(found) == ["/scan", "/sonar/energyscape", "/tf"]
    got = {topic: found[topic] for topic in ("/scan", "/sonar/energyscape", "/tf")}
    for topic, sent in got.items():
        for log_time, decoded in sent:
            stamp = decoded.header.stamp if topic != "/tf" else decoded.transforms[0].header.stamp
            assert stamp.sec * 10**9 + stamp.nanosec == log_time
    n = len(truth["time"])
    assert n == 16 and all(len(v) == n for v in got.values())
    for k, ((_, scan), (_, image), (_, tf)) in enumerate(zip(*got.values(), strict=True)):
        np.testing.assert_array_equal(np.array(scan.ranges, np.float32), truth["ranges"][k].astype(np.float32))
        assert len(scan.ranges) == 1081 and scan.angle_min == pytest.approx(np.deg2rad(-135.0))
        assert scan.angle_min + 1080 * scan.angle_increment == pytest.approx(scan.angle_max)
        np.testing.assert_array_equal(pixels(image), truth["energy"][k].astype(np.float32))
        move = tf.transforms[0].transform
        position = [move.translation.x, move.translation.y, move.translation.z]
        np.testing.assert_allclose(position, truth["pose"][k][:3, 3])
        q = move.rotation  # yaw about z: the rotation's x axis is the pose's forward axis
        yaw = 2 * np.arctan2(q.z, q.w)
        np.testing.assert_allclose([np.cos(yaw), np.sin(yaw)], truth["pose"][k][:2, 0], atol=1e-9)
    # Stamps: each drive's own clock (0.1 s apart), drives one after another with a gap.
    stamps = (np.array([t for t, _ in got["/scan"]]) - STAMP_START_S * 10**9) / 1e9
    starts = np.flatnonzero(np.r_[True, np.diff(truth["episode"]) != 0])
    assert stamps[0] == 0
    for a, b in zip(starts, [*starts[1:], n], strict=True):
        np.testing.assert_allclose(np.diff(stamps[a:b]), np.diff(truth["time"][a:b]), atol=1e-9)
    np.testing.assert_allclose(np.diff(stamps)[starts[1:] - 1], EPISODE_GAP_S, atol=1e-9)


def test_topic_names_are_ros_names():
    """The level slice alone keeps /sonar/energyscape; one other elevation or several get one topic
    each, the angle spelt with letters, digits and underscores (m: minus, p: point; -0 is 0),
    distinct for distinct angles."""
    assert energyscape_topics([0.0]) == energyscape_topics([-0.0]) == ["/sonar/energyscape"]
    assert energyscape_topics([12.5]) == ["/sonar/energyscape/elevation_12p5_deg"]  # not read back as 0 deg
    topics = energyscape_topics([-20.0, -0.0, 12.5, 0.1])
    assert topics == [
        "/sonar/energyscape/elevation_m20_deg",
        "/sonar/energyscape/elevation_0_deg",
        "/sonar/energyscape/elevation_12p5_deg",
        "/sonar/energyscape/elevation_0p1_deg",
    ]
    assert all(t.split("/")[-1].replace("_", "").isalnum() and t.split("/")[-1][0].isalpha() for t in topics)
    assert len(set(energyscape_topics([1.0, np.nextafter(1.0, 2.0)]))) == 2


def test_several_elevations_export_one_image_topic_each(tiny_dataset, tmp_path):
    """An E = 3 dataset (-20, 0, 20 deg; slices made unlike each other: the level slice, it doubled,
    its range axis reversed) exports three image topics, each frame's image the slice of its
    elevation, stamped with the frame's scan; no /sonar/energyscape."""
    slices = (lambda e: e, lambda e: 2 * e, lambda e: e[:, ::-1])
    stacked = restack(tiny_dataset, tmp_path / "e3", [-20.0, 0.0, 20.0], slices)
    out = tmp_path / "e3.mcap"
    assert main(["export", str(stacked), "--format", "mcap", "--out", str(out)]) == 0
    truth = []
    for path in sorted(stacked.glob("shard-*.h5")):
        with h5py.File(path, "r") as f:
            truth.append(f["energyscape"][:])
    truth = np.concatenate(truth)
    topics = [f"/sonar/energyscape/elevation_{a}_deg" for a in ("m20", "0", "20")]
    found = messages(out)
    assert sorted(found) == sorted(["/scan", "/tf", *topics])
    for j, topic in enumerate(topics):
        assert [t for t, _ in found[topic]] == [t for t, _ in found["/scan"]] and len(found[topic]) == 16
        for k, (_, image) in enumerate(found[topic]):
            np.testing.assert_array_equal(pixels(image), truth[k, j].astype(np.float32))
    assert not np.array_equal(truth[:, 0], truth[:, 2])  # a swap of the outer slices would show


def test_a_format_1_dataset_still_exports(tiny_dataset, tmp_path):
    """Shards written in format 1 (energyscape (frame, range, azimuth), format_version 1, no
    elevation_deg) export as before: their energyscape on /sonar/energyscape."""
    old = tmp_path / "v1"
    old.mkdir()
    truth = []
    for path in sorted(tiny_dataset.glob("shard-*.h5")):
        shutil.copy(path, old / path.name)
        with h5py.File(old / path.name, "r+") as f:
            level = f["energyscape"][:, 0]
            del f["energyscape"], f["elevation_deg"]
            f.create_dataset("energyscape", data=level, chunks=(1, *level.shape[1:]), **COMPRESSION)  # as written then
            f.attrs["format_version"] = 1
            truth.append(level)
    truth = np.concatenate(truth)
    out = tmp_path / "v1.mcap"
    assert main(["export", str(old), "--format", "mcap", "--out", str(out)]) == 0
    found = messages(out)
    assert sorted(found) == ["/scan", "/sonar/energyscape", "/tf"] and len(found["/sonar/energyscape"]) == 16
    for k, (_, image) in enumerate(found["/sonar/energyscape"]):
        np.testing.assert_array_equal(pixels(image), truth[k].astype(np.float32))


def test_export_refuses_repeated_elevations(tiny_dataset, tmp_path, capsys):
    """Two images at one angle would share a topic: refused in one line naming the shard, nothing written."""
    stacked = restack(tiny_dataset, tmp_path / "twice", [0.0, 0.0], (lambda e: e, lambda e: e))
    assert main(["export", str(stacked), "--format", "mcap", "--out", str(tmp_path / "x.mcap")]) == 2
    err = capsys.readouterr().err
    assert "repeats an angle" in err and "shard-00000.h5" in err and len(err.strip().splitlines()) == 1
    assert not (tmp_path / "x.mcap").exists()


def test_export_refuses_a_folder_without_shards(tmp_path, capsys):
    assert main(["export", str(tmp_path), "--format", "mcap", "--out", str(tmp_path / "x.mcap")]) == 2
    assert "no shard" in capsys.readouterr().err


def test_predicted_scans_land_on_the_exported_frames(tiny_dataset, tmp_path):
    """`learn predict --mcap` writes one LaserScan per window on /scan_pred, stamped as the export
    stamps its label frame, with the .npz's ranges; learn restates the export's message definition
    and stamp rule (it may not import the simulator), and both agree."""
    import learn.ros
    from acoustic_sim.formats import mcap_export
    from learn import PRETRAINED_CHECKPOINT
    from learn.cli import main as learn_main

    assert learn.ros.LASER_SCAN == mcap_export.LASER_SCAN
    assert (learn.ros.STAMP_START_S, learn.ros.EPISODE_GAP_S) == (mcap_export.STAMP_START_S, EPISODE_GAP_S)
    scans = tmp_path / "pred.mcap"
    argv = ["predict", "--checkpoint", str(PRETRAINED_CHECKPOINT), "--input", str(tiny_dataset)]
    assert learn_main([*argv, "--out", str(tmp_path / "pred"), "--mcap", str(scans)]) == 0
    assert main(["export", str(tiny_dataset), "--format", "mcap", "--out", str(tmp_path / "drive.mcap")]) == 0
    saved = np.load(tmp_path / "pred.npz")

    predicted = messages(scans, "/scan_pred")["/scan_pred"]
    truth = messages(tmp_path / "drive.mcap", "/scan")["/scan"]
    assert len(predicted) == len(saved["frame"]) == 8  # two 8-frame drives, K = 5
    assert [t for t, _ in predicted] == [truth[k][0] for k in saved["frame"]]
    for (_, scan), ranges in zip(predicted, saved["ranges"], strict=True):
        np.testing.assert_array_equal(np.array(scan.ranges, np.float32), ranges)
        assert len(scan.ranges) == 181 and scan.angle_min == pytest.approx(-np.pi / 2)
