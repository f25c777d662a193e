"""CHIRP round trip: a dataset generated with --signals -> export -> read by the format's own reader
(cosys-chirppy) -> import -> our shards again, scored by `learn evaluate`; and the refusals."""

import dataclasses
import json
import shutil
import sys

import h5py
import numpy as np
import pytest

from acoustic_sim.cli import main
from acoustic_sim.datasets.shards import FORMAT_VERSION
from acoustic_sim.formats.mcap_export import EPISODE_GAP_S, STAMP_START_S

chirppy = pytest.importorskip("chirppy")  # the `chirp` extra, installed by the `test` extra


@pytest.fixture(scope="module")
def signals_dataset(tmp_path_factory, device):
    """The conftest's tiny dataset (two 8-frame drives: room, corridor; the same suite, seed and
    kernels), with the microphone signals kept."""
    from acoustic_sim.datasets.generate import generate
    from acoustic_sim.datasets.suites import SUITES, Physics

    suite = dataclasses.replace(SUITES["tiny"], variants={"": Physics(ray_count=2000)})
    out = tmp_path_factory.mktemp("tiny_signals")
    generate(suite, out, frames=16, shards=2, seed=3, device=device, progress=False, keep_signals=True)
    return out


@pytest.fixture(scope="module")
def exported(signals_dataset, tmp_path_factory):
    out = tmp_path_factory.mktemp("chirp") / "sim.h5"
    assert main(["export", str(signals_dataset), "--format", "chirp", "--out", str(out)]) == 0
    return out


@pytest.fixture(scope="module")
def imported(exported, device):
    out = exported.parent / "rec"
    assert main(["import", str(exported), "--format", "chirp", "--out", str(out), "--device", device]) == 0
    return out


@pytest.fixture(scope="module")
def imported_elevations(exported, device):
    """The export imported again with one image per elevation at -20, 0 and 20 deg."""
    out = exported.parent / "rec_elevations"
    argv = ["import", str(exported), "--format", "chirp", "--out", str(out), "--device", device]
    assert main([*argv, "--set", "processing.elevation_deg=[-20,0,20]"]) == 0
    return out


def read(folder, *keys) -> dict:
    """Datasets of every shard of a folder, concatenated; `episode` made unique across shards."""
    found = {k: [] for k in keys}
    for i, path in enumerate(sorted(folder.glob("shard-*.h5"))):
        with h5py.File(path, "r") as f:
            for k in keys:
                found[k].append(f[k][:] + 1000 * i if k == "episode" else f[k][:])
    return {k: np.concatenate(v) for k, v in found.items()}


def test_chirppy_reads_the_export(signals_dataset, exported):
    """The reference reader finds 16 pings: signals (samples, mics) as stored, the eRTIS array at
    450 kHz, one x, y, z, intensity point per LiDAR return (z = 0: a planar scan), the poses, and
    Unix times that are the drive's (0.1 s apart, drives 1 s apart, from STAMP_START_S)."""
    from acoustic_sim.config import LidarConfig, SonarConfig
    from acoustic_sim.engine.lidar import ranges_to_points

    truth = read(signals_dataset, "signals", "lidar/ranges", "pose", "time", "episode")
    with chirppy.CHIRPDataset(exported) as data:
        assert (data.format, data.version, len(data)) == ("chirp", "2.1", 16)
        acoustic, lidar, odometry = data.get_acoustic_sensor(0), data.get_lidar(0), data.get_odometry(0)
        assert data.reference_sensor == acoustic.name and acoustic.sample_rates == 450e3
        np.testing.assert_array_equal(acoustic.get_receiver_positions(), np.asarray(SonarConfig.ertis().microphones_m))
        np.testing.assert_array_equal(acoustic.signals[:], truth["signals"].astype(np.float32).transpose(0, 2, 1))
        assert len(data.get_acoustic_transmitter(0).get_emitted_signal()) == SonarConfig.ertis().chirp.sample_count
        beams = ranges_to_points(truth["lidar/ranges"], LidarConfig.hokuyo_ust20lx())
        for k in range(16):
            capture = data[k]  # every sensor at reference capture k
            points = capture[lidar.name]["points"]
            expected = beams[k][np.isfinite(beams[k][:, 0])]
            assert points.shape == (len(expected), 4) and np.all(points[:, 3] == 1.0)
            np.testing.assert_allclose(points[:, :3], expected, atol=1e-6)  # float32 points
            assert capture[lidar.name]["timestamp"] == capture[acoustic.name]["timestamp"]
        np.testing.assert_allclose(odometry.poses(), truth["pose"], atol=1e-12)
        np.testing.assert_array_equal(data.get_transform(acoustic.name, "base_link"), np.eye(4))
        stamps = data.reference_timestamps
    starts = np.flatnonzero(np.r_[True, np.diff(truth["episode"]) != 0])
    assert stamps[0] == STAMP_START_S and list(starts) == [0, 8]
    for a, b in zip(starts, [*starts[1:], 16], strict=True):
        np.testing.assert_allclose(np.diff(stamps[a:b]), np.diff(truth["time"][a:b]), atol=1e-6)  # float64 at 1.7e9 s
    assert stamps[8] - stamps[7] == pytest.approx(EPISODE_GAP_S, abs=1e-6)


def test_import_gives_back_the_energyscapes_and_labels(signals_dataset, imported, device):
    """Imported shards hold the originals: LiDAR labels identical, ranges within 1e-6 relative
    (points are float32), poses and episode times exact, episodes split at the 1 s gap. The
    energyscapes are our processing of the stored signals, bit for bit; against the stored
    energyscapes they differ by <= 0.2 % of each frame's peak, because those were processed from
    the float32 signals before both were rounded to float16 (0.05 % per rounding; 0.09 % seen)."""
    from acoustic_sim.config import SimConfig
    from acoustic_sim.engine.beamform import energyscape

    keys = ("energyscape", "lidar/image", "lidar/ranges", "pose", "time", "episode")
    truth, got = read(signals_dataset, *keys, "signals"), read(imported, *keys, "elevation_deg")
    assert got["energyscape"].shape == (16, 1, 240, 181) and list(got["elevation_deg"]) == [0.0, 0.0]  # two shards
    truth["energyscape"], got["energyscape"] = truth["energyscape"][:, 0], got["energyscape"][:, 0]
    np.testing.assert_array_equal(got["lidar/image"], truth["lidar/image"])
    assert truth["lidar/image"].sum() > 16 * 100  # scans with returns on the grid
    np.testing.assert_allclose(got["lidar/ranges"], truth["lidar/ranges"], rtol=1e-6)
    np.testing.assert_allclose(got["pose"], truth["pose"], atol=1e-12)
    np.testing.assert_allclose(got["time"], truth["time"], atol=1e-6)
    np.testing.assert_array_equal(got["episode"] % 1000, [0] * 8 + [1] * 8)
    rig = SimConfig()
    ours = energyscape(truth["signals"].astype(np.float32), rig.sonar, rig.processing, device=device)
    np.testing.assert_array_equal(got["energyscape"], ours.astype(np.float16))
    stored = truth["energyscape"].astype(np.float32)
    peak = stored.max(axis=(1, 2), keepdims=True)
    assert np.all(np.abs(got["energyscape"].astype(np.float32) - stored) <= 2e-3 * peak)
    manifest = json.loads((imported / "manifest.json").read_text())
    assert manifest["frames"] == 16 and manifest["import"]["lidar"] == "lidar_00"
    assert manifest["format_version"] == FORMAT_VERSION and not (imported / "card_elevations.png").exists()


def test_import_images_each_elevation(signals_dataset, imported, imported_elevations, device):
    """`--set processing.elevation_deg=[-20,0,20]`: shards (format 2) of (ping, 3, range, azimuth)
    with elevation_deg [-20, 0, 20]; the 0 deg slice is the default import's, bit for bit, and each
    slice is our processing of the stored signals at that one elevation (so none is swapped); the
    card draws a ping at every elevation."""
    from acoustic_sim.config import SimConfig
    from acoustic_sim.engine.beamform import energyscape

    for path in sorted(imported_elevations.glob("shard-*.h5")):
        with h5py.File(path, "r") as f:
            assert f.attrs["format_version"] == FORMAT_VERSION == 2
            assert f["energyscape"].shape == (8, 3, 240, 181) and f["energyscape"].dtype == np.float16
            np.testing.assert_array_equal(f["elevation_deg"][:], [-20.0, 0.0, 20.0])
    got, level = read(imported_elevations, "energyscape")["energyscape"], read(imported, "energyscape")["energyscape"]
    np.testing.assert_array_equal(got[:, 1], level[:, 0])
    signals, rig = read(signals_dataset, "signals")["signals"].astype(np.float32), SimConfig()
    for j, elevation in ((0, -20.0), (2, 20.0)):
        processing = dataclasses.replace(rig.processing, elevation_deg=elevation)
        alone = energyscape(signals, rig.sonar, processing, device=device).astype(np.float16)
        np.testing.assert_array_equal(got[:, j], alone)
    assert not np.array_equal(got[:, 0], got[:, 2])  # the two outer slices differ: a swap would show
    manifest = json.loads((imported_elevations / "manifest.json").read_text())
    elevations = manifest["sim"]["processing"]["elevation_deg"]
    assert manifest["format_version"] == FORMAT_VERSION and elevations == [-20.0, 0.0, 20.0]
    assert (imported_elevations / "card_elevations.png").is_file()
    assert "card_elevations.png" in (imported_elevations / "README.md").read_text()


def test_learn_evaluate_scores_the_imported_recording(imported, tmp_path):
    """The issue's acceptance: the imported folder is scored by `learn evaluate` with no other
    step (the shipped K = 5 model: 4 windows in each 8-ping episode), and `learn predict` runs on it."""
    from learn import PRETRAINED_CHECKPOINT
    from learn.cli import main as learn_main

    checkpoint = str(PRETRAINED_CHECKPOINT)
    report = tmp_path / "eval"
    assert learn_main(["evaluate", "--checkpoint", checkpoint, "--data", str(imported), "--out", str(report)]) == 0
    metrics = json.loads((report / "metrics.json").read_text())
    assert metrics["windows"] == 8 and metrics["split"] == "all"
    model, empty = (metrics["results"][k]["all"]["scan_f1"]["mean"] for k in ("model", "empty"))
    assert model > 0.5 and empty == 0.0  # labels with returns, and a model that finds them
    predict = ["predict", "--checkpoint", checkpoint, "--input", str(imported), "--out", str(tmp_path / "p")]
    assert learn_main(predict) == 0
    assert list(np.load(tmp_path / "p.npz")["frame"]) == [2, 3, 4, 5, 10, 11, 12, 13]


def _without_signals(signals_dataset, folder):
    shutil.copy(next(signals_dataset.glob("shard-*.h5")), folder / "shard-00000.h5")
    with h5py.File(folder / "shard-00000.h5", "a") as f:
        del f["signals"]
    return folder


def _lidar_only(path):
    with h5py.File(path, "w") as f:
        f.attrs.update(format="chirp", format_version="2.1", n_reference_captures=1, reference_sensor="")
        f.create_group("sensors/lidar_00").attrs["sensor_type"] = "lidar"
        f["sensors/lidar_00/data/points"] = np.zeros((1, 1, 4), np.float32)
        f["sensors/lidar_00/data/point_counts"] = np.ones(1, np.int32)
        f["sensors/lidar_00/data/timestamps"] = np.zeros(1)
    return path


def _other_rate(exported, path):
    shutil.copy(exported, path)
    with h5py.File(path, "a") as f:
        f["sensors/acoustic_sensor_00"].attrs["sample_rate_hz"] = 48000.0
    return path


@pytest.mark.parametrize(
    ("case", "message"),
    [
        ("export-without-signals", "generate the dataset with --signals"),
        ("import-lidar-only", "holds no microphone data"),
        ("import-our-shard", "is not a CHIRP file"),
        ("import-other-rate", "sampled at 48000 Hz, but our call is sampled at 450000 Hz"),
        ("import-without-chirppy", "needs the `chirp` extra"),
    ],
)
def test_bad_input_is_refused_in_one_line(case, message, signals_dataset, exported, tmp_path, capsys, monkeypatch):
    if case == "export-without-signals":
        folder = _without_signals(signals_dataset, tmp_path)
        argv = ["export", str(folder), "--format", "chirp", "--out", str(tmp_path / "x.h5")]
    else:
        source = {
            "import-lidar-only": lambda: _lidar_only(tmp_path / "lidar.h5"),
            "import-our-shard": lambda: next(signals_dataset.glob("shard-*.h5")),
            "import-other-rate": lambda: _other_rate(exported, tmp_path / "rate.h5"),
            "import-without-chirppy": lambda: exported,
        }[case]()
        if case == "import-without-chirppy":
            monkeypatch.setitem(sys.modules, "chirppy", None)  # `import chirppy` fails
        argv = ["import", str(source), "--format", "chirp", "--out", str(tmp_path / "rec")]
    assert main(argv) == 2
    err = capsys.readouterr().err
    assert message in err and len(err.strip().splitlines()) == 1, err
    assert not (tmp_path / "x.h5").exists() and not any((tmp_path / "rec").glob("*"))


def test_a_scan_from_points_in_any_sector():
    """planar_scan bins by degrees past the first beam, wrapped: a rear sector across +-180 deg
    keeps its points, a point half a step before the first beam falls on it; one beam is refused."""
    from acoustic_sim.config import LidarConfig
    from acoustic_sim.formats.chirp import planar_scan

    rear = dataclasses.replace(
        LidarConfig.hokuyo_ust20lx(), azimuth_min_deg=90.0, azimuth_max_deg=270.0, azimuth_count=181
    )
    bearings = np.deg2rad([-179.7, -90.0, 90.0, 89.6])  # beams 90, 180, 0, 0
    points = np.c_[2.0 * np.cos(bearings), 2.0 * np.sin(bearings), np.zeros(4)]
    ranges = planar_scan(points, rear, plane_tolerance_m=0.05)
    assert np.isfinite(ranges).sum() == 3 and np.isfinite(ranges[[0, 90, 180]]).all()
    with pytest.raises(ValueError, match="two or more beams"):
        planar_scan(points, dataclasses.replace(rear, azimuth_max_deg=90.0, azimuth_count=1), plane_tolerance_m=0.05)


def test_import_warns_when_the_recorded_call_is_another(exported, tmp_path, device):
    """Our matched filter uses the rig's call: a file whose transmitter emitted another one is
    imported with a warning that says so."""
    other = tmp_path / "other_call.h5"
    shutil.copy(exported, other)
    with h5py.File(other, "r+") as f:
        call = f["sensors/acoustic_transmitter_00/data/signals"]
        call[...] = call[()][::-1]  # the time-reversed sweep: another call
    with pytest.warns(UserWarning, match="another call"):
        assert (
            main(["import", str(other), "--format", "chirp", "--out", str(tmp_path / "rec"), "--device", device]) == 0
        )


def test_calibrate_fits_to_a_chirp_files_pings(signals_dataset, exported, tmp_path, device):
    """`calibrate` takes a CHIRP file as its recordings: every ping's signals and odometry pose as the
    dataset exported them (or `--pings` of them, evenly spaced), the file's array as the sonar; the
    command fits one drive's room from it; a file without odometry is refused."""
    import json
    import shutil

    from acoustic_sim.calibrate import load_recordings, recorded_scene, recordings_and_sonar
    from acoustic_sim.config import SonarConfig

    truth = read(signals_dataset, "signals", "pose")
    poses, signals = load_recordings(exported)
    np.testing.assert_array_equal(signals, truth["signals"].astype(np.float32))
    np.testing.assert_allclose(poses, truth["pose"], atol=1e-12)
    few_poses, few = load_recordings(exported, pings=3)
    np.testing.assert_array_equal(few, signals[[0, 8, 15]])
    np.testing.assert_array_equal(few_poses, poses[[0, 8, 15]])
    with pytest.raises(ValueError, match="pings must be >= 1"):
        load_recordings(exported, pings=0)
    import clitools.limits

    with pytest.MonkeyPatch.context() as patch:  # a file too long to read whole: told to take fewer pings
        patch.setattr(clitools.limits, "available_memory_bytes", lambda: signals.nbytes)
        with pytest.raises(ValueError, match="--pings N"):
            load_recordings(exported)
        assert len(load_recordings(exported, pings=4)[1]) == 4
    *_, sonar = recordings_and_sonar(exported, pings=1, sonar=SonarConfig.ertis())
    assert sonar.microphones_m == SonarConfig.ertis().microphones_m and sonar.record_samples == signals.shape[2]
    one_room = tmp_path / "one_room"  # the first drive alone (one room), as its own CHIRP file
    one_room.mkdir()
    first = sorted(signals_dataset.glob("shard-*.h5"))[0]
    shutil.copy(first, one_room / first.name)
    assert main(["export", str(one_room), "--format", "chirp", "--out", str(tmp_path / "room.h5")]) == 0
    room = recorded_scene(one_room)
    size = np.ptp(room.mesh.bounds, axis=0).round(6).tolist()
    out = tmp_path / "fit" / "fit.json"
    argv = ["calibrate", str(tmp_path / "room.h5"), "--scene", "box_room", "--scene-arg", f"size={size}"]
    argv += ["--rays", "3000", "--max-bounces", "1", "--no-delays", "--device", device, "--out", str(out)]
    assert main(argv) == 0
    fit = json.loads(out.read_text())
    assert fit["pings"] == 8 and "walls" in fit["classes"] and fit["loss"][-1] <= fit["loss"][0]
    with h5py.File(tmp_path / "room.h5", "r+") as f:
        del f["sensors/odometry_00"]
    with pytest.raises(ValueError, match="no poses"):
        load_recordings(tmp_path / "room.h5")
