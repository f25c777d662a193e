"""MCAP export read back with the mcap reader: frames, ranges, images, poses and stamps."""

import h5py
import numpy as np
import pytest

from acoustic_sim.cli import main
from acoustic_sim.formats.mcap_export import EPISODE_GAP_S, STAMP_START_S


def test_export_reads_back_as_the_dataset(tiny_dataset, tmp_path):
    from mcap.reader import make_reader
    from mcap_ros2.decoder import DecoderFactory

    out = tmp_path / "drive.mcap"
    assert main(["export", str(tiny_dataset), "--format", "mcap", "--out", str(out)]) == 0
    shards = sorted(tiny_dataset.glob("shard-*.h5"))
    truth = {k: [] for k in ("ranges", "energy", "pose", "time", "episode")}
    for path in shards:
        with h5py.File(path, "r") as f:
            for key, name in (("ranges", "lidar/ranges"), ("energy", "energyscape"), ("pose", "pose")):
                truth[key].append(f[name][:])
            truth["time"].append(f["time"][:])
            truth["episode"].append(f["episode"][:] + 1000 * len(truth["episode"]))
    truth = {k: np.concatenate(v) for k, v in truth.items()}
    got = {"/scan": [], "/sonar/energyscape": [], "/tf": []}
    with open(out, "rb") as f:
        for _, channel, message, decoded in make_reader(
            f, decoder_factories=[DecoderFactory()]
        ).iter_decoded_messages():
            stamp = decoded.header.stamp if channel.topic != "/tf" else decoded.transforms[0].header.stamp
            assert stamp.sec * 10**9 + stamp.nanosec == message.log_time
            got[channel.topic].append((message.log_time, decoded))
    n = len(truth["time"])
    assert n == 16 and all(len(v) == n for v in got.values())
    for k, ((_, scan), (_, image), (_, tf)) in enumerate(zip(*got.values(), strict=True)):
        np.testing.assert_array_equal(np.array(scan.ranges, np.float32), truth["ranges"][k].astype(np.float32))
        assert len(scan.ranges) == 1081 and scan.angle_min == pytest.approx(np.deg2rad(-135.0))
        assert scan.angle_min + 1080 * scan.angle_increment == pytest.approx(scan.angle_max)
        pixels = np.frombuffer(bytes(image.data), "<f4").reshape(image.height, image.width)
        np.testing.assert_array_equal(pixels, truth["energy"][k].astype(np.float32))
        assert image.encoding == "32FC1" and image.step == 4 * image.width
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


def test_export_refuses_a_folder_without_shards(tmp_path, capsys):
    assert main(["export", str(tmp_path), "--format", "mcap", "--out", str(tmp_path / "x.mcap")]) == 2
    assert "no shard" in capsys.readouterr().err


def test_predicted_scans_land_on_the_exported_frames(tiny_dataset, tmp_path):
    """`learn predict --mcap` writes one LaserScan per window on /scan_pred, stamped as the export
    stamps its label frame, with the .npz's ranges; learn restates the export's message definition
    and stamp rule (it may not import the simulator), and both agree."""
    from mcap.reader import make_reader
    from mcap_ros2.decoder import DecoderFactory

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

    def messages(path, topic):
        with open(path, "rb") as f:
            reader = make_reader(f, decoder_factories=[DecoderFactory()])
            return [(m.log_time, d) for _, c, m, d in reader.iter_decoded_messages() if c.topic == topic]

    predicted, truth = messages(scans, "/scan_pred"), messages(tmp_path / "drive.mcap", "/scan")
    assert len(predicted) == len(saved["frame"]) == 8  # two 8-frame drives, K = 5
    assert [t for t, _ in predicted] == [truth[k][0] for k in saved["frame"]]
    for (_, scan), ranges in zip(predicted, saved["ranges"], strict=True):
        np.testing.assert_array_equal(np.array(scan.ranges, np.float32), ranges)
        assert len(scan.ranges) == 181 and scan.angle_min == pytest.approx(-np.pi / 2)
