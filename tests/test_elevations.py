"""Energyscapes at several elevations, from the generator to the learner: shards (T, E, R, A), the
level slice unchanged, models that read each elevation as channels and refuse other elevations,
the baselines on the level slice, format-1 shards still read."""

import dataclasses
import json
import shutil

import h5py
import numpy as np
import pytest
import torch

from learn.checkpoint import load_checkpoint
from learn.config import LearnConfig, TrainConfig
from learn.data import DataConfig, Frames, Windows, level_slice, load_frames
from learn.evaluate import evaluate
from learn.models import ModelConfig, build_model
from learn.predict import predict
from learn.train import train

ELEVATIONS = (-20.0, 0.0, 20.0)
QUICK = TrainConfig(epochs=1, batch_size=4, lr=1e-3, loss="bce", val_fraction=0.5, max_val_windows=8)


def test_shards_hold_every_elevation_and_the_level_slice_is_the_planar_one(three_elevations, tiny_dataset):
    """Format 2 stores (T, E, R, A) with its elevation axis; the 0 deg slice is bit for bit the
    energyscape of the same drives generated with the default single elevation; the others
    differ from it (the floor below, the ceiling above) and from each other."""
    with h5py.File(next(three_elevations.glob("shard-*.h5"))) as f:
        assert f["energyscape"].shape[1:] == (3, 240, 181) and f["elevation_deg"][:].tolist() == list(ELEVATIONS)
        assert f["lidar/image"].shape[1:] == (240, 181)
    many, one = load_frames(three_elevations), load_frames(tiny_dataset)
    assert many.elevation_deg == ELEVATIONS and one.elevation_deg == (0.0,) and many.level == 1
    np.testing.assert_array_equal(many.energyscape[:, 1], one.energyscape[:, 0])
    np.testing.assert_array_equal(many.label, one.label)
    below, level, above = (many.energyscape[:, e].astype(np.float32) for e in range(3))
    assert not np.array_equal(below, level) and not np.array_equal(above, level) and not np.array_equal(below, above)
    np.testing.assert_array_equal(level_slice(many).energyscape, one.energyscape)


def test_format_1_shards_read_as_one_level_slice(tiny_dataset, tmp_path):
    """A shard of the old layout (energyscape (T, R, A), no elevation axis, format_version 1)
    reads as the same frames at one elevation, 0 deg."""
    old = tmp_path / "old"
    shutil.copytree(tiny_dataset, old)
    for path in old.glob("shard-*.h5"):
        with h5py.File(path, "a") as f:
            energy = f["energyscape"][:, 0]
            del f["energyscape"], f["elevation_deg"]
            f.create_dataset("energyscape", data=energy, chunks=(1, *energy.shape[1:]), fletcher32=True)
            f.attrs["format_version"] = 1
    got, want = load_frames(old), load_frames(tiny_dataset)
    assert got.elevation_deg == (0.0,)
    np.testing.assert_array_equal(got.energyscape, want.energyscape)


def test_windows_give_each_elevation_as_a_channel_normalised_together(three_elevations):
    """x (B, E, K, R, A): frame k's elevation e is its stored slice, in dB below the frame's peak
    over all elevations (so the level slice keeps how much weaker it is than a floor echo)."""
    frames = load_frames(three_elevations)
    windows = Windows(frames, DataConfig(frames=3))
    x, _ = windows.batch([4])
    assert x.shape == (1, 3, 3, 240, 181)
    start = windows.starts[4]
    energy = torch.from_numpy(frames.energyscape[start : start + 3].astype(np.float32))  # (K, E, R, A)
    peak = energy.amax(dim=(1, 2, 3))
    below_peak = 0
    for k in range(3):
        assert x[0, :, k].max() == pytest.approx(1.0)
        for e in range(3):
            share = float(energy[k, e].amax() / peak[k])  # this elevation's peak over the frame's
            below_peak += share < 0.9
            expected = max(0.0, 1.0 + 20.0 * np.log10(max(share, 1e-30)) / 40.0)
            assert float(x[0, e, k].max()) == pytest.approx(expected, abs=1e-4)
    assert below_peak >= 3  # slices weaker than their frame's peak, which a per-slice scaling would lift to 1


@pytest.mark.parametrize("name", ["polar_unet", "paper"])
def test_models_read_every_elevation(name):
    """Each elevation is an input: changing only the top elevation changes the output."""
    torch.manual_seed(0)
    model = build_model(ModelConfig(name=name, frames=3, width=4, elevation_deg=ELEVATIONS)).eval()
    x = torch.rand(2, 3, 3, 40, 30)
    other = x.clone()
    other[:, 2] = torch.rand(2, 3, 40, 30)
    with torch.no_grad():
        assert model(x).shape == (2, 1, 40, 30)
        assert not torch.allclose(model(x), model(other))
    with pytest.raises(ValueError, match="increasing"):
        ModelConfig(elevation_deg=(20.0, 0.0))


def test_a_model_trained_on_three_elevations_refuses_one_by_name(three_elevations, tiny_dataset, tmp_path):
    """Training records the data's elevations; evaluate and predict refuse data at others, naming
    both; on its own data the baselines read the level slice, as on the planar dataset."""
    config = LearnConfig(
        model=ModelConfig(name="polar_unet", frames=3, width=4),
        data=DataConfig(frames=3),
        train=QUICK,
    )
    train(three_elevations, tmp_path / "run", config, progress=False)
    ckpt_path = tmp_path / "run" / "best.pt"
    _, ckpt = load_checkpoint(ckpt_path)
    assert tuple(ckpt["model_config"]["elevation_deg"]) == ELEVATIONS
    with pytest.raises(ValueError, match=r"1 elevation \(0 deg\).*trained on 3 elevations \(-20, 0, 20 deg\)"):
        evaluate(ckpt_path, tiny_dataset, tmp_path / "e1", device="cpu", grids=False)
    many = evaluate(ckpt_path, three_elevations, tmp_path / "e3", device="cpu", grids=False, split="all")
    planar = evaluate_baselines(tiny_dataset, tmp_path)
    for name in ("echo peak", "empty"):
        assert json.dumps(many["results"][name]["all"]) == json.dumps(planar["results"][name]["all"])  # NaN alike
    scapes = load_frames(three_elevations).energyscape[:6].astype(np.float32)
    np.save(tmp_path / "e3.npy", scapes)
    np.save(tmp_path / "e1.npy", scapes[:, 1])
    assert predict(ckpt_path, tmp_path / "e3.npy", tmp_path / "p3").exists()
    with pytest.raises(ValueError, match=r"expected energyscapes \(N, 3, 240, 181\)"):
        predict(ckpt_path, tmp_path / "e1.npy", tmp_path / "p1")


def evaluate_baselines(data, tmp_path):
    """evaluate's report of a one-elevation model on `data` (its baselines are what is compared)."""
    config = LearnConfig(
        model=ModelConfig(name="polar_unet", frames=3, width=4),
        data=DataConfig(frames=3),
        train=QUICK,
    )
    train(data, tmp_path / "planar", config, progress=False)
    return evaluate(tmp_path / "planar" / "best.pt", data, tmp_path / "ep", device="cpu", grids=False, split="all")


def test_frames_refuse_energyscapes_that_do_not_match_their_elevations():
    with pytest.raises(ValueError, match=r"\(T, E, R, A\) with E = 3"):
        Frames(
            energyscape=np.zeros((2, 2, 8, 8), np.float16),
            label=np.zeros((2, 8, 8), np.uint8),
            episode=np.zeros(2, np.int64),
            scenario=np.zeros(2, np.int64),
            scenarios=["x"],
            range_m=np.arange(8.0),
            azimuth_rad=np.arange(8.0),
            info={},
            elevation_deg=ELEVATIONS,
        )


def test_a_model_of_the_level_slice_reads_it_out_of_three(three_elevations, tiny_dataset, tmp_path):
    """model.elevation_deg [0] on data of three elevations trains exactly the model the planar
    dataset trains (the windows hold the level slice alone, normalised on its own), scores
    beside a three-elevation model on the same data, and asks for an elevation the data lacks
    by name."""
    level = dataclasses.replace(ModelConfig(name="polar_unet", frames=3, width=4), elevation_deg=(0.0,))
    config = LearnConfig(model=level, data=DataConfig(frames=3), train=QUICK)
    train(three_elevations, tmp_path / "level", config, progress=False)
    train(tiny_dataset, tmp_path / "planar", config, progress=False)
    _, picked = load_checkpoint(tmp_path / "level" / "best.pt")
    _, planar = load_checkpoint(tmp_path / "planar" / "best.pt")
    assert tuple(picked["model_config"]["elevation_deg"]) == (0.0,)
    for name, weights in planar["model"].items():
        assert torch.equal(weights, picked["model"][name]), name
    full = LearnConfig(model=ModelConfig(name="polar_unet", frames=3, width=4), data=DataConfig(frames=3), train=QUICK)
    train(three_elevations, tmp_path / "full", full, progress=False)
    report = evaluate(
        {"level": tmp_path / "level" / "best.pt", "full": tmp_path / "full" / "best.pt"},
        three_elevations,
        tmp_path / "both",
        device="cpu",
        grids=False,
        split="all",
    )
    assert {"level", "full", "echo peak"} <= set(report["results"])
    wrong = dataclasses.replace(config, model=dataclasses.replace(level, elevation_deg=(0.0, 10.0)))
    with pytest.raises(ValueError, match=r"holds no energyscapes at \[10\.0\] deg"):
        train(three_elevations, tmp_path / "wrong", wrong, progress=False)


def test_a_run_of_before_elevations_resumes_and_fine_tunes(tiny_dataset, tmp_path):
    """A checkpoint written before elevations (no elevation_deg in its model config, dataset format 1)
    read the level slice: --resume and --init-from take it on planar data as they did."""
    config = LearnConfig(
        model=ModelConfig(name="polar_unet", frames=3, width=4), data=DataConfig(frames=3), train=QUICK
    )
    train(tiny_dataset, tmp_path / "run", config, progress=False)
    for name in ("last.pt", "best.pt"):
        ckpt = torch.load(tmp_path / "run" / name, weights_only=True)
        del ckpt["model_config"]["elevation_deg"]
        ckpt["dataset"]["format_version"] = 1
        torch.save(ckpt, tmp_path / "run" / name)
    longer = dataclasses.replace(config, train=dataclasses.replace(QUICK, epochs=2))
    train(tiny_dataset, tmp_path / "run", longer, progress=False, resume=True)
    assert torch.load(tmp_path / "run" / "last.pt", weights_only=True)["state"]["epoch"] == 2
    train(tiny_dataset, tmp_path / "tuned", config, progress=False, init_from=tmp_path / "run" / "best.pt")


def test_a_recording_says_its_elevations_and_predict_reads_them(three_elevations, tmp_path):
    """A .npy beside the record `import --format pdm` writes is taken at the elevations the record
    names: a model of the level slice picks its row out of three; a model of three elevations
    refuses an array recorded at others, naming both."""
    level = dataclasses.replace(ModelConfig(name="polar_unet", frames=3, width=4), elevation_deg=(0.0,))
    train(
        three_elevations,
        tmp_path / "level",
        LearnConfig(model=level, data=DataConfig(frames=3), train=QUICK),
        progress=False,
    )
    scapes = load_frames(three_elevations).energyscape[:6].astype(np.float32)
    np.save(tmp_path / "rec.npy", scapes)
    (tmp_path / "rec.json").write_text(json.dumps({"elevation_deg": list(ELEVATIONS)}))
    np.save(tmp_path / "level.npy", scapes[:, 1])
    picked = np.load(predict(tmp_path / "level" / "best.pt", tmp_path / "rec.npy", tmp_path / "p3"))
    alone = np.load(predict(tmp_path / "level" / "best.pt", tmp_path / "level.npy", tmp_path / "p1"))
    np.testing.assert_array_equal(picked["prediction"], alone["prediction"])
    (tmp_path / "rec.json").write_text(json.dumps({"elevation_deg": [-10.0, 0.0, 10.0]}))
    full = LearnConfig(model=ModelConfig(name="polar_unet", frames=3, width=4), data=DataConfig(frames=3), train=QUICK)
    train(three_elevations, tmp_path / "full", full, progress=False)
    with pytest.raises(ValueError, match=r"3 elevations \(-10, 0, 10 deg\).*trained on 3 elevations \(-20, 0, 20"):
        predict(tmp_path / "full" / "best.pt", tmp_path / "rec.npy", tmp_path / "p")


def test_onnx_export_takes_every_elevation_and_names_them(tmp_path):
    """The exported graph reads (batch, E, K, R, A), equals torch, and its metadata names the
    channels' elevations in order."""
    onnxruntime = pytest.importorskip("onnxruntime")
    import onnx

    from learn.export import export_onnx

    torch.manual_seed(0)
    model = build_model(ModelConfig(name="polar_unet", frames=3, width=4, elevation_deg=ELEVATIONS)).eval()
    info = export_onnx(model, tmp_path / "m.onnx", frames=3, range_count=40, azimuth_count=30, elevation_deg=ELEVATIONS)
    meta = {p.key: p.value for p in onnx.load(info["path"]).metadata_props}
    assert json.loads(meta["elevation_deg"]) == list(ELEVATIONS)
    x = torch.rand(2, 3, 3, 40, 30)
    session = onnxruntime.InferenceSession(info["path"], providers=["CPUExecutionProvider"])
    assert session.get_inputs()[0].shape[1:] == [3, 3, 40, 30]
    (got,) = session.run(None, {"energyscapes": x.numpy()})
    with torch.no_grad():
        np.testing.assert_allclose(got, model(x).numpy(), atol=1e-4)


def test_frames_read_only_the_elevations_a_model_reads(three_elevations):
    """load_frames(elevation_deg=) keeps those rows in order, whose windows equal the windows that
    pick them out of all three; data lacking one keeps every row for the reader to refuse."""
    every = load_frames(three_elevations)
    for want, rows in (([0.0], [1]), ([20.0, -20.0], [0, 2])):
        some = load_frames(three_elevations, elevation_deg=want)
        assert some.elevation_deg == tuple(every.elevation_deg[r] for r in rows)
        assert np.array_equal(some.energyscape, every.energyscape[:, rows])
        picked = Windows(every, DataConfig(frames=3), elevation_deg=want)
        held = Windows(some, DataConfig(frames=3), elevation_deg=want)
        assert torch.equal(picked.batch([2, 5])[0], held.batch([2, 5])[0])
    assert load_frames(three_elevations, elevation_deg=[0.0, 10.0]).elevation_deg == every.elevation_deg
