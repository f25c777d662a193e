"""What the README's commands and python blocks leave behind, checked against what its prose says
they write (tests/test_readme.py runs them; each check returns a line for its report).

A command that runs in the README walk must have a check here: one that only exits with 0 proves
nothing about what it wrote.
"""

from __future__ import annotations

import json
import re
from pathlib import Path

import h5py
import numpy as np

from clitools import counted
from tests.pictures import axes_frames, near, read_rgb

README = Path(__file__).resolve().parents[1] / "README.md"
GRID_SHAPE = (240, 181)
"""README: "0.2-5 m in 2 cm bins (240) x -90..+90 deg in 1 deg bins (181)"."""

SHARD_ARRAYS = ("energyscape", "lidar/ranges", "lidar/image", "pose", "time", "episode", "scenario")
"""README: "Each shard holds `energyscape` (frame, range, azimuth) float16, `lidar/ranges`, `lidar/image`
(the label), `pose`, `time`, `episode`, `scenario` and the axes"."""

DATASET_FILES = ("manifest.json", "README.md", "card.png", "plan.json")
"""README: "`manifest.json` (...), a dataset card (`README.md` + `card.png` ...) and `plan.json`"."""


def shards(folder: Path) -> list[Path]:
    found = sorted(folder.glob("shard-*.h5"))
    assert found, f"{folder} holds no shard-*.h5"
    return found


def read_arrays(folder: Path, *names: str) -> dict[str, np.ndarray]:
    """The named arrays of a dataset folder, its shards concatenated in order."""
    parts = {name: [] for name in names}
    for path in shards(folder):
        with h5py.File(path) as f:
            for name in names:
                parts[name].append(f[name][()])
    return {name: np.concatenate(arrays) for name, arrays in parts.items()}


def check_render(args, cwd: Path, stdout: str) -> str:
    """`render` writes the picture and PICTURE.json (the options as given, the rig as used) beside it,
    and says so; the picture has the top view beside the polar image, one row per simulation (with
    `--sonar` two: no secondary reflections, then `--max-bounces`); the top view shows the
    trajectory (blue) and the LiDAR scan (red)."""
    picture = cwd / args.out
    sidecar = picture.with_suffix(".json")
    written = json.loads(sidecar.read_text())
    options = {k: v for k, v in vars(args).items() if not callable(v)}
    assert written["picture"] == picture.name and written["options"] == json.loads(json.dumps(options))
    assert set(written["sim"]) == {"lidar", "sonar", "tracer", "processing"}
    assert f"wrote {args.out} and its settings in {sidecar.name}" in stdout, stdout
    mapped = _check_mesh_report(args, cwd, stdout) if args.mesh else ""
    image = read_rgb(picture)
    frames = axes_frames(image)
    if args.sonar:
        bounces = args.max_bounces if args.max_bounces is not None else written["sim"]["tracer"]["max_bounces"]
        assert f"with max_bounces 0 and {bounces};" in stdout, stdout
        assert len(frames) == 4, f"{picture.name}: {len(frames)} panels, not two rows of two"
        return f"{picture.name}: two rows of two panels (max_bounces 0, {bounces}); {sidecar.name}: the options"
    assert len(frames) == 2, f"{picture.name}: {len(frames)} panels, not the top view beside the polar image"
    top_view = min(frames, key=lambda box: box.left)
    for colour in ("tab:blue", "tab:red"):
        assert (near(image, colour, 0.1) & top_view.inside(image.shape)).sum() > 20, f"no {colour} in the top view"
    return (
        f"{picture.name}: top view with trajectory and scan beside the polar image; {sidecar.name}: the options{mapped}"
    )


def check_calibrate(args, cwd: Path, stdout: str) -> str:
    """`calibrate` writes OUT (.json: each class's fitted and nominal R, a gain and a delay per
    microphone, the error at each step, falling) and its picture beside it, and says so; where the
    recordings carry the truth they were made with (`truth`, JSON; `delay_s`), every fitted R is
    within 5 % of it and every delay within 0.2 us."""
    written = cwd / args.out
    fit = json.loads(written.read_text())
    assert f"wrote {args.out} and its picture" in stdout, stdout
    assert all(0 < c["reflection"] <= 1 and 0 < c["nominal"] <= 1 for c in fit["classes"].values()), fit["classes"]
    assert len(fit["mic_gain_db"]) == len(fit["mic_delay_us"]) == 32 and fit["loss"][-1] < fit["loss"][0]
    assert read_rgb(written.with_suffix(".png")).shape[0] > 400
    with np.load(cwd / args.recordings) as recording:
        truth = json.loads(str(recording["truth"])) if "truth" in recording else {}
        delay_us = recording["delay_s"] * 1e6 if "delay_s" in recording else None
    for name, value in truth.items():
        got = fit["classes"][name]["reflection"]
        assert abs(got / value - 1) < 0.05, f"{name}: fitted R {got:.3f}, recorded with {value}"
    found = f"; R within 5 % of the recordings' truth ({', '.join(truth)})" if truth else ""
    if delay_us is not None:
        missed = np.abs(np.asarray(fit["mic_delay_us"]) - delay_us).max()
        assert missed < 0.2, f"a microphone's fitted delay is {missed:.3f} us off the recordings' truth"
        found += f"; delays within {missed:.3f} us"
    picture = written.with_suffix(".png").name
    return f"{written.name}: {len(fit['classes'])} classes, the error falling; {picture}{found}"


def _check_mesh_report(args, cwd: Path, stdout: str) -> str:
    """`render --mesh` prints the import report: the file, its frame and unit (as given), and one
    line per material name of the file with the material it got, each key of --materials by the
    table (read here from the file)."""
    from scenes.material_map import read_material_table

    lines = stdout.splitlines()
    assert lines[0].startswith(f"mesh {args.mesh}: "), lines[0]
    for option, said in (("up", f": {args.up} up (given)"), ("units", f", {args.units} (given)")):
        if getattr(args, option):
            assert said in lines[0], lines[0]
    table = read_material_table(cwd / args.materials) if args.materials else {}
    for key, ours in table.items():
        assert any(line.endswith(f"-> {ours} (table: {key!r})") for line in lines), f"{key} -> {ours} not reported"
    names = [line for line in lines if re.match(r"  .+: \d+ faces? -> \w+ \(", line)]  # '(no name)' too
    assert names, "no material names reported"
    readme = README.read_text()
    if lines[0] in readme:  # the README quotes this report: every line of it as printed
        report = lines[: 1 + next(i for i, line in enumerate(lines[1:]) if not line.startswith("  "))]
        assert all(line in readme for line in report), [line for line in report if line not in readme]
    return f"; the import report: {len(names)} material names, {len(table)} by the table"


def check_generate(args, cwd: Path, stdout: str, frames: int) -> str:
    """`generate` writes shards, manifest, card and plan; its shards hold the README's arrays (and
    `signals` with --signals), `frames` in all; its first line counts them, its last says where
    the time went."""
    out = cwd / args.out
    for name in DATASET_FILES:
        assert (out / name).is_file(), f"{out.name}/{name} missing"
    manifest = json.loads((out / "manifest.json").read_text())
    extra = ("signals",) if args.signals else ()
    arrays = read_arrays(out, *SHARD_ARRAYS, *extra)
    assert manifest["frames"] == frames == len(arrays["energyscape"])
    elevations = np.size(manifest["sim"]["processing"]["elevation_deg"])  # as the command asked
    assert arrays["energyscape"].dtype == np.float16 and arrays["energyscape"].shape[1:] == (elevations, *GRID_SHAPE)
    assert arrays["lidar/image"].shape == (frames, *GRID_SHAPE) and arrays["pose"].shape == (frames, 4, 4)
    assert len(np.unique(arrays["episode"])) == manifest["episodes"]
    if args.signals:
        assert arrays["signals"].shape[:2] == (frames, 32)
    lines = stdout.strip().splitlines()
    counts = f"{counted(frames, 'frame')} in {counted(len(shards(out)), 'shard')}"
    assert lines[0].startswith(f"{manifest['suite']}: {counts} under "), lines[0]
    assert lines[-1].startswith("time by part: "), lines[-1]
    return f"{args.out}: {frames} frames of {manifest['episodes']} episodes, arrays {', '.join(SHARD_ARRAYS + extra)}"


def check_export_mcap(args, cwd: Path) -> str:
    """MCAP: every frame as a LaserScan on /scan, a 32FC1 Image on /sonar/energyscape (row i = range
    bin i, column j = azimuth j) and a TFMessage on /tf; the first frame's scan and image are the
    dataset's."""
    from mcap.reader import make_reader
    from mcap_ros2.decoder import DecoderFactory

    data = read_arrays(cwd / args.dataset, "energyscape", "lidar/ranges")
    first: dict[str, object] = {}
    counts = {"/scan": 0, "/sonar/energyscape": 0, "/tf": 0}
    with open(cwd / args.out, "rb") as f:
        for _, channel, _, decoded in make_reader(f, decoder_factories=[DecoderFactory()]).iter_decoded_messages():
            counts[channel.topic] = counts.get(channel.topic, 0) + 1
            first.setdefault(channel.topic, decoded)
    frames = len(data["energyscape"])
    assert counts == {"/scan": frames, "/sonar/energyscape": frames, "/tf": frames}, counts
    image = first["/sonar/energyscape"]
    assert (image.encoding, image.height, image.width) == ("32FC1", *GRID_SHAPE)
    pixels = np.frombuffer(bytes(image.data), dtype=np.float32).reshape(GRID_SHAPE)
    np.testing.assert_array_equal(pixels, data["energyscape"][0, 0].astype(np.float32))  # its one elevation
    np.testing.assert_array_equal(np.asarray(first["/scan"].ranges, dtype=np.float32), data["lidar/ranges"][0])
    return f"{args.out}: {frames} frames on /scan, /sonar/energyscape and /tf; frame 0 is the dataset's"


def check_export_chirp(args, cwd: Path) -> str:
    """CHIRP: per ping the microphone signals (the dataset's) with the array's positions and sample
    rate, the call, the LiDAR returns as points, the poses as odometry."""
    data = read_arrays(cwd / args.dataset, "signals", "lidar/ranges", "pose")
    manifest = json.loads((cwd / args.dataset / "manifest.json").read_text())
    with h5py.File(cwd / args.out) as f:
        sensors = {group.attrs["sensor_type"]: group for group in f["sensors"].values()}
        assert set(sensors) == {"acoustic_sensor", "acoustic_transmitter", "lidar", "odometry"}, set(sensors)
        acoustic = sensors["acoustic_sensor"]
        signals = acoustic["data/signals"]  # (ping, sample, microphone)
        assert signals.shape == (len(data["signals"]), data["signals"].shape[2], 32)
        np.testing.assert_array_equal(signals[0].T, data["signals"][0].astype(np.float32))
        mics = acoustic["calibration/receiver_relative_translations"][()]
        np.testing.assert_allclose(mics, manifest["sim"]["sonar"]["microphones_m"])
        assert acoustic.attrs["sample_rate_hz"] == manifest["sim"]["sonar"]["chirp"]["sample_rate_hz"]
        counts = sensors["lidar"]["data/point_counts"][()]
        np.testing.assert_array_equal(counts, np.isfinite(data["lidar/ranges"]).sum(axis=1))
        np.testing.assert_allclose(sensors["odometry"]["data/position"][()], data["pose"][:, :3, 3])
    return f"{args.out}: {len(data['signals'])} pings, the dataset's signals, array, LiDAR point counts and poses"


def check_import_chirp(args, cwd: Path, source: Path | None) -> str:
    """CHIRP back into shards: "the round trip gives back the labels exactly and the energyscapes
    within 0.2 % of each frame's peak" (when the file was exported from a dataset earlier)."""
    out = cwd / args.out
    got = read_arrays(out, "energyscape", "lidar/image")
    if source is None:
        return f"{args.out}: {len(got['energyscape'])} frames"
    want = read_arrays(cwd / source, "energyscape", "lidar/image")
    np.testing.assert_array_equal(got["lidar/image"], want["lidar/image"])
    error = np.abs(got["energyscape"].astype(np.float32) - want["energyscape"].astype(np.float32)).max(axis=(1, 2, 3))
    peak = np.abs(want["energyscape"].astype(np.float32)).max(axis=(1, 2, 3))
    assert np.all(error <= 0.002 * peak), (error / peak).max()
    return f"{args.out}: the labels of {source} exactly, energyscapes within {(error / peak).max():.2%} of the peak"


def check_evaluate(args, cwd: Path, stdout: str) -> str:
    """`evaluate` writes metrics.json and report.md into --out and prints one line per predictor: every
    window of K frames within one drive of the data is scored (K from the checkpoint), with the
    shipped baselines beside the model."""
    metrics = json.loads((cwd / args.out / "metrics.json").read_text())
    assert (cwd / args.out / "report.md").is_file()
    episodes = read_arrays(cwd / args.data, "episode")["episode"]
    frames = metrics["model"]["frames"]
    windows = sum(max(0, n - frames + 1) for n in np.unique(episodes, return_counts=True)[1])
    if metrics["split"] == "all":
        assert metrics["windows"] == windows, (metrics["windows"], windows)
    assert {"echo peak", "empty"} <= set(metrics["results"]), list(metrics["results"])
    for name, result in metrics["results"].items():
        assert 0.0 <= result["all"]["scan_f1"]["mean"] <= 1.0, name
        assert any(
            line.strip().startswith(f"{name}: scan F1 {result['all']['scan_f1']['mean']:.3f}")
            for line in stdout.splitlines()
        ), f"{name} not printed"
    lines = stdout.strip().splitlines()
    assert lines[0] == f"{counted(metrics['windows'], 'window')} ({metrics['split']} split) of {args.data}:", lines[0]
    assert lines[-1] == f"report: {args.out}/report.md", lines[-1]
    model = metrics["results"][next(iter(metrics["checkpoints"]))]["all"]["scan_f1"]["mean"]
    return f"{args.out}: {metrics['windows']} windows of {frames} frames scored, scan F1 {model:.3f}"


def check_predict(args, cwd: Path) -> str:
    """`predict` writes the images and the scans (`ranges`, inf = no return): each scan is its image
    read per azimuth column at the threshold (the nearest cell at or above it); --png draws them."""
    saved = np.load(cwd / args.out)
    images, ranges, threshold = saved["prediction"], saved["ranges"], float(saved["threshold"])
    assert images.shape[1:] == (len(saved["range_m"]), len(saved["azimuth_rad"])) == GRID_SHAPE

    def scans(level):
        hit = images >= level
        return np.where(hit.any(axis=1), saved["range_m"][hit.argmax(axis=1)], np.inf)

    # The images are stored as float16: a cell within its rounding (< 5e-4) of the threshold may go either way.
    nearest, farthest = scans(threshold - 1e-3), scans(threshold + 1e-3)
    assert np.all((nearest - 1e-6 <= ranges) & (ranges <= farthest + 1e-6)), "a scan is not its image's first return"
    assert np.mean(np.isclose(ranges, scans(threshold))) > 0.99
    assert len(saved["frame"]) == len(images) and 0 < threshold <= 1
    report = f"{args.out}: {len(images)} images, their scans at threshold {threshold:g}"
    if args.png:
        truth = Path(args.input).suffix != ".npy"  # a .npy of energyscapes holds no LiDAR truth to draw
        rows = len(axes_frames(read_rgb(cwd / args.png))) // (4 if truth else 3)  # sonar, (truth,) prediction, top
        assert rows == min(4, len(images)), rows
        report += f"; {args.png}: {rows} rows"
    return report


def check_onnx(args, cwd: Path, stdout: str) -> str:
    """`export` writes ONNX "with the threshold in its metadata" (the checkpoint's) and checks it
    against torch."""
    import onnx
    import torch

    info = json.loads(stdout.strip().splitlines()[-1])
    assert info["max_abs_diff"] is not None and info["max_abs_diff"] <= info["tolerance"], info
    metadata = {p.key: p.value for p in onnx.load(cwd / args.out).metadata_props}
    threshold = torch.load(cwd / args.checkpoint, map_location="cpu", weights_only=True)["threshold"]
    assert float(metadata["return_threshold"]) == threshold, metadata
    diff = info["max_abs_diff"]
    return f"{args.out}: return_threshold {metadata['return_threshold']} as in the checkpoint; torch diff {diff:.1e}"


SHAPE_COMMENT = re.compile(r"^(\w+) = .*#\s*\(([\w\s,]+)\)")
"""A python block's `name = ...  # (50, 1081) metres`: the value's shape, numbers or names."""


def shape_probe(code: str) -> tuple[str, list[tuple[str, list[str]]]]:
    """The block with a line appended that prints the shapes its comments claim, and the claims."""
    claims = [(m[1], [d.strip() for d in m[2].split(",")]) for m in map(SHAPE_COMMENT.match, code.splitlines()) if m]
    names = [name for name, _ in claims]
    shapes = f"{{n: _np.shape(globals()[n]) for n in {names!r}}}"
    probe = f"\nimport json as _json, numpy as _np\nprint('README-SHAPES', _json.dumps({shapes}))\n"
    return code + probe, claims


def check_shapes(claims: list[tuple[str, list[str]]], stdout: str, number: int) -> str:
    """Each commented shape holds: numbers as written, a name (N, samples) the same size wherever it is used."""
    line = next(line for line in stdout.splitlines() if line.startswith("README-SHAPES "))
    shapes = json.loads(line.removeprefix("README-SHAPES "))
    sizes: dict[str, int] = {}
    for name, dims in claims:
        got = shapes[name]
        assert len(got) == len(dims), (
            f"README.md:{number}: {name} has shape {tuple(got)}, the comment says ({', '.join(dims)})"
        )
        for dim, size in zip(dims, got, strict=True):
            expected = int(dim) if dim.isdigit() else sizes.setdefault(dim, size)
            assert size == expected, (
                f"README.md:{number}: {name} has shape {tuple(got)}, the comment says ({', '.join(dims)})"
            )
    return f"shapes of {', '.join(name for name, _ in claims)} as commented" if claims else "no shapes commented"
