"""`learn predict --stream` as a user runs it (each command a process of its own, tests/cli_runner.py):
on a dataset folder it writes what `learn predict` writes for the same windows; a model with memory
streamed gives the images of `learn.data.Windows`; the dataset exported to MCAP streams to the same
scans, and the MCAP written holds them on /scan_pred and the poses used on /tf, as the exporter
stamps and poses its frames; a memory model on data without poses and a foreign bag are refused
with one line."""

from __future__ import annotations

import os
import warnings

import numpy as np
import pytest
import torch

from learn import PRETRAINED_CHECKPOINT
from learn.checkpoint import load_checkpoint
from learn.config import LearnConfig, TrainConfig
from learn.data import DataConfig, Windows, load_frames
from learn.models import ModelConfig, build_model, predict_image
from learn.train import train

from .cli_runner import run_commands

MEMORY = LearnConfig(
    model=ModelConfig(name="polar_memory", frames=3, width=4, history=2),
    data=DataConfig(frames=3, history=2, history_stride=2),
    train=TrainConfig(epochs=1, batch_size=4, lr=1e-3, loss="bce", val_fraction=0.5, max_val_windows=8),
)


def _memory_checkpoint(data, out) -> str:
    """A polar_memory checkpoint as `learn train` writes it, its weights then drawn again (He,
    no prior bias) so that its images move with the frames and poses (one epoch on the tiny data
    leaves them near the prior everywhere), read at threshold 0.5."""
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", UserWarning)  # "has not learnt to place walls": not what is tested
        train(data, out, MEMORY, progress=False)
    path = out / "best.pt"
    ckpt = torch.load(path, weights_only=True)
    model = build_model(ModelConfig(**ckpt["model_config"]))
    torch.manual_seed(0)
    for layer in model.modules():
        if isinstance(layer, torch.nn.Conv2d):
            torch.nn.init.kaiming_normal_(layer.weight)
            if layer.bias is not None:
                torch.nn.init.zeros_(layer.bias)
    ckpt["model"], ckpt["threshold"] = model.state_dict(), 0.5
    torch.save(ckpt, path)
    return str(path)


def _image_bag(path, count: int, height: int, width: int) -> None:
    """An MCAP bag of `count` 32FC1 sonar frames of height x width on /sonar/energyscape, 0.1 s
    apart, and no /tf."""
    from mcap_ros2.writer import Writer

    from acoustic_sim.formats.mcap_export import IMAGE
    from learn.bag import IMAGE_TOPIC

    rng = np.random.default_rng(0)
    with open(path, "wb") as stream:
        writer = Writer(stream)
        schema = writer.register_msgdef("sensor_msgs/msg/Image", IMAGE)
        for k in range(count):
            stamp = 1_700_000_000 * 10**9 + k * 10**8
            pixels = rng.uniform(0, 1, (height, width)).astype("<f4")
            message = {
                "header": {"stamp": {"sec": stamp // 10**9, "nanosec": stamp % 10**9}, "frame_id": "sensor"},
                "height": height,
                "width": width,
                "encoding": "32FC1",
                "is_bigendian": 0,
                "step": 4 * width,
                "data": pixels.tobytes(),
            }
            writer.write_message(IMAGE_TOPIC, schema, message, log_time=stamp, sequence=k)
        writer.finish()


@pytest.fixture(scope="module")
def runs(tiny_dataset, tmp_path_factory):
    """Every command once, side by side: {name: (CompletedProcess, its output files)}."""
    from acoustic_sim.cli import main as simulator

    tmp = tmp_path_factory.mktemp("predict_stream")
    memory, unet = _memory_checkpoint(tiny_dataset, tmp / "memory"), str(PRETRAINED_CHECKPOINT)
    bag = tmp / "drive.mcap"
    assert simulator(["export", str(tiny_dataset), "--format", "mcap", "--out", str(bag)]) == 0
    _image_bag(tmp / "no_tf.mcap", 6, 240, 181)
    _image_bag(tmp / "small.mcap", 6, 10, 20)
    (tmp / "foreign.mcap").write_bytes(b"not an mcap file at all\n" * 4)
    np.save(tmp / "frames.npy", np.ones((6, 240, 181), np.float32))
    data = str(tiny_dataset)

    def predict(checkpoint, source, name, *more):
        return ["predict", "--checkpoint", checkpoint, "--input", source, "--out", str(tmp / f"{name}.npz"), *more]

    commands = {
        "unet_batch": predict(unet, data, "unet_batch", "--quiet"),
        "unet_stream": predict(unet, data, "unet_stream", "--stream"),
        "memory_folder": predict(memory, data, "memory_folder", "--stream", "--quiet"),
        "memory_bag": predict(memory, str(bag), "memory_bag", "--stream", "--quiet", "--mcap", str(tmp / "pred.mcap")),
        "unet_no_tf": predict(unet, str(tmp / "no_tf.mcap"), "unet_no_tf", "--stream", "--quiet"),
        "memory_npy": predict(memory, str(tmp / "frames.npy"), "memory_npy", "--stream", "--quiet"),
        "memory_no_tf": predict(memory, str(tmp / "no_tf.mcap"), "memory_no_tf", "--stream", "--quiet"),
        "foreign": predict(unet, str(tmp / "foreign.mcap"), "foreign", "--stream", "--quiet"),
        "small": predict(unet, str(tmp / "small.mcap"), "small", "--stream", "--quiet"),
    }
    env = {**os.environ, "PYTHONUNBUFFERED": "1", "CUDA_VISIBLE_DEVICES": ""}
    done = run_commands({k: ("learn", v) for k, v in commands.items()}, env=env, parallel=2 * (os.cpu_count() or 1))
    return {"done": done, "tmp": tmp, "memory": memory, "bag": bag}


def _ok(runs, name) -> dict:
    done = runs["done"][name]
    assert done.returncode == 0, done.stderr[-3000:]
    return dict(np.load(runs["tmp"] / f"{name}.npz"))


def test_streaming_writes_what_predict_writes(runs):
    """The pretrained polar UNet (K = 5) streamed over two 8-frame drives: the .npz of `predict`,
    with the same label frames (2..5 and 10..13), images equal to float16 rounding, and equal scans
    (beams whose image comes within that rounding of the threshold aside); a bar counts the frames."""
    batch, stream = _ok(runs, "unet_batch"), _ok(runs, "unet_stream")
    assert sorted(stream) == sorted(batch)
    np.testing.assert_array_equal(stream["frame"], [2, 3, 4, 5, 10, 11, 12, 13])
    np.testing.assert_array_equal(stream["frame"], batch["frame"])
    for key in ("threshold", "range_m", "azimuth_rad"):
        np.testing.assert_array_equal(stream[key], batch[key])
    image, want = stream["prediction"].astype(np.float32), batch["prediction"].astype(np.float32)
    np.testing.assert_allclose(image, want, atol=1e-3)
    near = (np.abs(want - float(batch["threshold"])) < 1e-3).any(axis=1)  # (windows, beams)
    assert np.isfinite(batch["ranges"]).any() and near.mean() < 0.05
    np.testing.assert_array_equal(stream["ranges"][~near], batch["ranges"][~near])
    bar = runs["done"]["unet_stream"].stderr
    assert "streaming" in bar and "/16 [" in bar and "frame" in bar  # the last refresh may fall within tqdm's interval


def test_a_streamed_memory_model_gives_the_images_of_its_windows(runs, tiny_dataset):
    """polar_memory (K = 3, history 2 frames 2 apart) streamed over the folder: for every window
    the image that `Windows(odometry=True).batch` and `predict_image` give (history absent at the
    start of each drive in both)."""
    got = _ok(runs, "memory_folder")
    model, ckpt = load_checkpoint(runs["memory"])
    windows = Windows(load_frames(tiny_dataset), DataConfig(**ckpt["data_config"]), odometry=True)
    x, _ = windows.batch(np.arange(len(windows)))
    with torch.no_grad():
        want = predict_image(model, x).float().clamp(0, 1)[:, 0].half().numpy()
    np.testing.assert_array_equal(got["frame"], windows.starts + 1)
    np.testing.assert_allclose(got["prediction"].astype(np.float32), want.astype(np.float32), atol=1e-3)
    assert np.ptp(want, axis=0).max() > 0.05  # the windows' images differ: a misread frame would show
    assert np.isfinite(got["ranges"]).any()


def test_the_bag_streams_as_its_dataset_and_its_mcap_shows_the_scans_in_the_world(runs):
    """The tiny dataset exported to MCAP (two drives, 1 s apart) streams to the folder's scans;
    pred.mcap holds one /scan_pred per scan, stamped as the export stamps its label frame, and a
    /tf per frame equal to the export's (the poses the model read)."""
    from mcap.reader import make_reader
    from mcap_ros2.decoder import DecoderFactory

    import learn.bag
    from acoustic_sim.formats import mcap_export

    assert learn.bag.TF_MESSAGE == mcap_export.TF_MESSAGE
    assert learn.bag.DRIVE_GAP_S < mcap_export.EPISODE_GAP_S
    folder, bag = _ok(runs, "memory_folder"), _ok(runs, "memory_bag")
    np.testing.assert_array_equal(bag["frame"], folder["frame"])
    np.testing.assert_array_equal(bag["prediction"], folder["prediction"])
    np.testing.assert_array_equal(bag["ranges"], folder["ranges"])

    def messages(path, topic):
        with open(path, "rb") as f:
            reader = make_reader(f, decoder_factories=[DecoderFactory()])
            return [(m.log_time, d) for _, c, m, d in reader.iter_decoded_messages(topics=[topic])]

    scans, truth = messages(runs["tmp"] / "pred.mcap", "/scan_pred"), messages(runs["bag"], "/scan")
    assert [t for t, _ in scans] == [truth[k][0] for k in bag["frame"]]
    for (_, scan), ranges in zip(scans, bag["ranges"], strict=True):
        np.testing.assert_array_equal(np.array(scan.ranges, np.float32), ranges)
        assert scan.header.frame_id == "sensor" and len(scan.ranges) == 181
    poses, exported = messages(runs["tmp"] / "pred.mcap", "/tf"), messages(runs["bag"], "/tf")
    assert len(poses) == len(exported) == 16
    for (t, ours), (t_export, theirs) in zip(poses, exported, strict=True):
        a, b = ours.transforms[0], theirs.transforms[0]
        assert t == t_export and (a.header.frame_id, a.child_frame_id) == ("world", "sensor")
        for part, keys in (("translation", "xyz"), ("rotation", "xyzw")):
            got = [getattr(getattr(a.transform, part), k) for k in keys]
            want = [getattr(getattr(b.transform, part), k) for k in keys]
            np.testing.assert_allclose(got, want, atol=1e-12)


def test_a_model_without_memory_streams_a_bag_without_poses(runs):
    got = _ok(runs, "unet_no_tf")
    np.testing.assert_array_equal(got["frame"], [2, 3])  # six frames, K = 5, one drive


@pytest.mark.parametrize(
    ("name", "words"),
    [
        ("memory_npy", "holds no poses (a .npy holds energyscapes alone), and"),
        ("memory_no_tf", "holds no poses (no /tf transform to the sonar's frame 'sensor')"),
        ("foreign", "is not an MCAP bag this learner can read"),
        ("small", "is 10 x 20, but the model reads 240 ranges x 181 azimuths"),
    ],
)
def test_refusals_are_one_line(runs, name, words):
    done = runs["done"][name]
    errors = [line for line in done.stderr.splitlines() if "error: " in line]
    assert done.returncode == 2 and "Traceback" not in done.stderr, done.stderr[-3000:]
    assert len(errors) == 1 and words in errors[0], done.stderr[-3000:]
    assert not (runs["tmp"] / f"{name}.npz").exists()


def test_bag_quaternions_round_trip():
    """matrix_quaternion inverts quaternion_matrix for seeded random rotations, w >= 0, and a
    rotation by yaw about z is (0, 0, sin(yaw / 2), cos(yaw / 2))."""
    from learn.bag import matrix_quaternion, quaternion_matrix

    q = np.random.default_rng(0).normal(size=(200, 4))
    q /= np.linalg.norm(q, axis=1, keepdims=True)
    q *= np.sign(q[:, 3:])
    m = quaternion_matrix(q)
    np.testing.assert_allclose(m @ m.transpose(0, 2, 1), np.broadcast_to(np.eye(3), m.shape), atol=1e-12)
    np.testing.assert_allclose(matrix_quaternion(m), q, atol=1e-12)
    yaw = np.linspace(-3.1, 3.1, 9)
    c, s = np.cos(yaw), np.sin(yaw)
    rz = np.zeros((9, 3, 3))
    rz[:, 0, 0], rz[:, 0, 1], rz[:, 1, 0], rz[:, 1, 1], rz[:, 2, 2] = c, -s, s, c, 1
    want = np.stack([0 * yaw, 0 * yaw, np.sin(yaw / 2), np.cos(yaw / 2)], -1)
    np.testing.assert_allclose(matrix_quaternion(rz), want, atol=1e-12)


def test_bag_poses_are_the_transforms_at_the_frames_or_between_them():
    """A frame stamped between two /tf transforms gets their linear blend (1/4 of the way: x 0.5 m,
    yaw 0.1 rad of 0.4); one stamped as a transform gets it; frames outside the /tf's span, or
    a /tf to another frame, give no poses and say why."""
    from types import SimpleNamespace as Msg

    from learn.bag import _poses
    from learn.odometry import planar

    def transform(x, yaw):
        return Msg(translation=Msg(x=x, y=0.0, z=0.3), rotation=Msg(x=0.0, y=0.0, z=np.sin(yaw / 2), w=np.cos(yaw / 2)))

    tf = [(0, "odom", "sensor", transform(0.0, 0.0)), (4, "odom", "sensor", transform(2.0, 0.4))]
    pose, parent, note = _poses(tf, "sensor", np.array([0, 1, 4]))
    assert parent == "odom" and note == ""
    np.testing.assert_allclose(planar(pose), [[0, 0, 0], [0.5, 0, 0.1], [2.0, 0, 0.4]], atol=5e-4)  # nlerp: 0.0997 rad
    np.testing.assert_allclose(pose[:, 2, 3], 0.3)
    assert _poses(tf, "sensor", np.array([1, 5]))[2] == "1 of 2 sonar frames lie outside the time span of its /tf"
    assert _poses(tf, "sonar", np.array([1]))[0] is None


# Bags of several elevations: one Image topic per elevation, as the exporter writes them.

ELEVATIONS = (-20.0, 0.0, 20.0)


@pytest.fixture(scope="module")
def three_elevation_bag(three_elevations, tmp_path_factory):
    """The tiny drives beamformed at -20, 0 and 20 deg (conftest's `three_elevations`) and their
    MCAP export: (folder, bag)."""
    from acoustic_sim.cli import main as simulator

    bag = tmp_path_factory.mktemp("three_elevation_bag") / "drive.mcap"
    assert simulator(["export", str(three_elevations), "--format", "mcap", "--out", str(bag)]) == 0
    return three_elevations, bag


def _elevation_bag(path, topics: dict, height: int = 10, width: int = 20) -> None:
    """An MCAP bag of 32FC1 images: for each topic, in the order given, {topic: stamps [ns]}; topic
    j's images are filled with j + 1 (each topic's images told apart by their value)."""
    from mcap_ros2.writer import Writer

    from acoustic_sim.formats.mcap_export import IMAGE

    messages = [(stamp, j, topic) for j, (topic, stamps) in enumerate(topics.items()) for stamp in stamps]
    with open(path, "wb") as stream:
        writer = Writer(stream)
        schema = writer.register_msgdef("sensor_msgs/msg/Image", IMAGE)
        for k, (stamp, j, topic) in enumerate(sorted(messages)):
            message = {
                "header": {"stamp": {"sec": stamp // 10**9, "nanosec": stamp % 10**9}, "frame_id": "sensor"},
                "height": height,
                "width": width,
                "encoding": "32FC1",
                "is_bigendian": 0,
                "step": 4 * width,
                "data": np.full((height, width), j + 1, "<f4").tobytes(),
            }
            writer.write_message(topic, schema, message, log_time=stamp, sequence=k)
        writer.finish()


def _unindexed(source, out) -> None:
    """A copy of an MCAP file without chunks, indexes or summary, as a recorder cut off writes it."""
    from mcap.reader import make_reader
    from mcap.writer import IndexType, Writer

    with open(source, "rb") as f, open(out, "wb") as stream:
        writer = Writer(
            stream,
            index_types=IndexType.NONE,
            use_chunking=False,
            use_statistics=False,
            use_summary_offsets=False,
            repeat_channels=False,
            repeat_schemas=False,
        )
        writer.start(profile="ros2", library="test")
        schemas, channels = {}, {}
        for schema, channel, message in make_reader(f).iter_messages():
            if schema.id not in schemas:
                schemas[schema.id] = writer.register_schema(schema.name, schema.encoding, schema.data)
            if channel.id not in channels:
                channels[channel.id] = writer.register_channel(
                    channel.topic, channel.message_encoding, schemas[schema.id]
                )
            writer.add_message(
                channels[channel.id], message.log_time, message.data, message.publish_time, message.sequence
            )
        writer.finish()


def test_the_bag_reader_reads_the_exporters_topic_names():
    """learn.bag restates the exporter's rule (learn may not import the simulator): every topic
    `energyscape_topics` writes reads back as its angle exactly (-0 as 0, seeded angles of 17
    digits too); its one-elevation topic is the level; other topics are none of the sonar's;
    a topic spelling its angle otherwise is refused by name."""
    from acoustic_sim.formats.mcap_export import ENERGYSCAPE_TOPIC, energyscape_topics
    from learn.bag import IMAGE_TOPIC, topic_elevation

    assert IMAGE_TOPIC == ENERGYSCAPE_TOPIC
    angles = [-90.0, -20.0, -12.5, -0.0, 0.1, 7.0, 12.5, 90.0, *np.random.default_rng(0).uniform(-90, 90, 20)]
    topics = energyscape_topics(angles)
    assert [topic_elevation(t) for t in topics] == [float(a) for a in angles]
    assert topic_elevation(topics[0]) == -90.0 and topic_elevation(topics[3]) == 0.0
    assert topic_elevation(energyscape_topics([0.0])[0]) == 0.0
    assert topic_elevation(energyscape_topics([10.0])[0]) == 10.0  # one elevation off the level keeps its angle
    for other in ("/tf", "/scan", "/sonar/energyscape/compressed", f"{topics[1]}/compressed", "/sonar/energyscape2"):
        assert topic_elevation(other) is None
    with pytest.raises(ValueError, match="/sonar/energyscape/elevation_-20_deg names no angle"):
        topic_elevation("/sonar/energyscape/elevation_-20_deg")


def test_a_bag_of_three_elevations_reads_back_as_its_dataset(three_elevation_bag, tmp_path):
    """The E = 3 dataset exported reads back (indexed, and copied without an index) as the
    folder's frames: energyscapes (16, 3, 240, 181) equal to the shards' float16 as float32, the
    elevations increasing, the drives split where the folder's episodes change, the same poses."""
    from learn.bag import read_bag

    folder, bag = three_elevation_bag
    want = load_frames(folder)
    assert want.elevation_deg == ELEVATIONS and want.energyscape.shape == (16, 3, 240, 181)
    _unindexed(bag, tmp_path / "unindexed.mcap")
    for path in (bag, tmp_path / "unindexed.mcap"):
        got = read_bag(path, want.range_m, want.azimuth_rad).frames
        assert got.elevation_deg == ELEVATIONS and got.energyscape.dtype == np.float32
        np.testing.assert_array_equal(got.energyscape, want.energyscape.astype(np.float32))
        np.testing.assert_array_equal(np.diff(got.episode) != 0, np.diff(want.episode) != 0)
        np.testing.assert_allclose(got.pose, want.pose, atol=1e-9)
    assert not np.array_equal(want.energyscape[:, 0], want.energyscape[:, 2])  # a swap would show


def test_a_bag_reads_its_elevations_in_increasing_order(tmp_path):
    """Topics written in any order (12.5, -20, -5 deg; by name 12p5 < m20 < m5) read as -20, -5,
    12.5 deg, each elevation holding its own topic's images (values 2, 3, 1), a ping per stamp."""
    from learn.bag import read_bag

    stamps = [1_700_000_000 * 10**9 + k * 10**8 for k in range(4)]
    _elevation_bag(
        tmp_path / "e3.mcap", {f"/sonar/energyscape/elevation_{a}_deg": stamps for a in ("12p5", "m20", "m5")}
    )
    drive = read_bag(tmp_path / "e3.mcap", np.arange(10.0), np.arange(20.0))
    assert drive.frames.elevation_deg == (-20.0, -5.0, 12.5)
    assert drive.frames.energyscape.shape == (4, 3, 10, 20) and drive.stamps.tolist() == stamps
    np.testing.assert_array_equal(drive.frames.energyscape[:, :, 0, 0], np.tile([2.0, 3.0, 1.0], (4, 1)))


START = 1_700_000_000 * 10**9
PINGS = [START + k * 10**8 for k in range(6)]
BELOW, LEVEL, ABOVE = (f"/sonar/energyscape/elevation_{a}_deg" for a in ("m20", "0", "20"))


@pytest.mark.parametrize(
    ("topics", "words"),
    [
        ({BELOW: PINGS, LEVEL: PINGS, ABOVE: PINGS[:5]}, f"{ABOVE} holds 5 images, {BELOW} 6: every elevation"),
        (
            {BELOW: PINGS, LEVEL: [*PINGS[:3], PINGS[3] + 10**6, *PINGS[4:]], ABOVE: PINGS},
            f"{LEVEL}'s image 3 (in time order) is stamped 1700000000.301000000 s, {BELOW}'s 1700000000.300000000 s",
        ),
        (
            {"/sonar/energyscape": PINGS, LEVEL: PINGS},
            f"holds images on /sonar/energyscape and on the elevation topics ['{LEVEL}']",
        ),
        ({LEVEL: PINGS, "/sonar/energyscape/elevation_m0_deg": PINGS}, "name one elevation, 0 deg"),
        (
            {"/sonar/energyscape/elevation_-20_deg": PINGS},
            "the topic /sonar/energyscape/elevation_-20_deg names no angle",
        ),
        ({"/scan": PINGS}, "holds no sonar images"),
    ],
    ids=["counts", "stamps", "both_layouts", "one_angle_twice", "unreadable_angle", "none"],
)
def test_bags_whose_elevations_do_not_make_pings_are_refused_in_one_line(tmp_path, capsys, topics, words):
    """`learn predict --stream` on such a bag: exit 2, one error line naming the topic, no output."""
    from learn.cli import main as learn_main

    _elevation_bag(tmp_path / "bad.mcap", topics, 240, 181)
    argv = ["predict", "--stream", "--quiet", "--checkpoint", str(PRETRAINED_CHECKPOINT)]
    assert learn_main([*argv, "--input", str(tmp_path / "bad.mcap"), "--out", str(tmp_path / "out.npz")]) == 2
    err = capsys.readouterr().err
    assert len(err.strip().splitlines()) == 1 and err.startswith("error: ") and words in err, err
    assert not (tmp_path / "out.npz").exists()


def _redrawn(ckpt: dict, model_config: dict) -> tuple[dict, torch.nn.Module]:
    """`ckpt` holding a model of `model_config` whose weights are drawn afresh (He, seeded, no
    bias) so that its images move with every input, read at threshold 0.5."""
    model = build_model(ModelConfig(**model_config))
    torch.manual_seed(0)
    for layer in model.modules():
        if isinstance(layer, torch.nn.Conv2d | torch.nn.Conv3d):
            torch.nn.init.kaiming_normal_(layer.weight)
            if layer.bias is not None:
                torch.nn.init.zeros_(layer.bias)
    return {**ckpt, "model_config": model_config, "model": model.state_dict(), "threshold": 0.5}, model.eval()


def test_a_model_of_three_elevations_predicts_from_the_bag_as_from_its_dataset(three_elevation_bag, tmp_path, capsys):
    """A polar UNet trained one epoch on the E = 3 data (weights then drawn again, so that its
    images follow every elevation: reversing them changes the images), streamed by `learn predict`
    over the exported bag, gives the folder's images and scans exactly."""
    from learn.cli import main as learn_main

    folder, bag = three_elevation_bag
    config = LearnConfig(
        model=ModelConfig(name="polar_unet", frames=3, width=4),
        data=DataConfig(frames=3),
        train=TrainConfig(epochs=1, batch_size=4, lr=1e-3, loss="bce", val_fraction=0.5, max_val_windows=8),
    )
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", UserWarning)  # "has not learnt to place walls": not what is tested
        train(folder, tmp_path / "run", config, progress=False)
    checkpoint = tmp_path / "run" / "best.pt"
    ckpt = torch.load(checkpoint, weights_only=True)
    assert tuple(ckpt["model_config"]["elevation_deg"]) == ELEVATIONS
    ckpt, model = _redrawn(ckpt, ckpt["model_config"])
    torch.save(ckpt, checkpoint)

    windows = Windows(load_frames(folder), DataConfig(**ckpt["data_config"]), elevation_deg=ELEVATIONS)
    x, _ = windows.batch(np.arange(len(windows)))
    with torch.no_grad():
        image, reversed_image = (predict_image(model.eval(), v).float().clamp(0, 1) for v in (x, x.flip(1)))
    assert (image - reversed_image).abs().max() > 0.05  # a bag read with its elevations mixed up would show

    got = {}
    for name, source in (("folder", folder), ("bag", bag)):
        argv = ["predict", "--stream", "--quiet", "--checkpoint", str(checkpoint), "--input", str(source)]
        assert learn_main([*argv, "--out", str(tmp_path / f"{name}.npz")]) == 0
        got[name] = dict(np.load(tmp_path / f"{name}.npz"))
    for key in ("frame", "prediction", "ranges"):
        np.testing.assert_array_equal(got["bag"][key], got["folder"][key])
    batch = ["predict", "--checkpoint", str(checkpoint), "--input", str(bag), "--out", str(tmp_path / "batch.npz")]
    capsys.readouterr()
    assert learn_main(batch) == 2  # batch prediction reads folders and arrays; it points to --stream
    assert "is an MCAP bag: `learn predict --stream` reads bags" in capsys.readouterr().err
    assert (
        len(got["folder"]["frame"]) == 12
        and np.ptp(got["folder"]["prediction"].astype(np.float32), axis=0).max() > 0.05
    )
