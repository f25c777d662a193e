"""Dataset generation: shards readable with plain h5py, resumable after a kill, deterministic,
clear errors for foreign or broken files; windows never cross episodes."""

import copy
import dataclasses
import json
import mmap
import os
import sys
import threading
import typing
from pathlib import Path
from types import SimpleNamespace

import h5py
import numpy as np
import pytest

import acoustic_sim.datasets.generate as gen
import acoustic_sim.datasets.helper_processes as helper_processes
import acoustic_sim.datasets.runner as runner
import acoustic_sim.datasets.shared_frames as shared_frames
import acoustic_sim.datasets.workers as workers
from acoustic_sim.datasets.shards import FORMAT_VERSION, DatasetError, ShardFrames, read_attrs
from acoustic_sim.datasets.suites import SUITES, Physics, load_suite
from learn.data import window_starts

# Three 3-frame drives (one per scenario) in two shards, few rays: a few seconds on the CPU.
SUITE = dataclasses.replace(SUITES["tiny"], episode_frames=3, variants={"": Physics(ray_count=2000)})
FRAMES = 9


def generate(out, device, **kwargs):
    """The test dataset, with the optional raw signals and arrivals (so determinism covers them)."""
    return gen.generate(
        SUITE,
        out,
        frames=FRAMES,
        shards=2,
        seed=7,
        device=device,
        progress=False,
        keep_signals=True,
        keep_arrivals=True,
        **kwargs,
    )


def shard_arrays(folder: Path) -> dict:
    out = {}
    for path in sorted(folder.glob("shard-*.h5")):
        with h5py.File(path, "r") as f:
            f.visititems(
                lambda name, obj, p=path: (
                    out.__setitem__(f"{p.name}/{name}", obj[()]) if isinstance(obj, h5py.Dataset) else None
                )
            )
    return out


@pytest.fixture(scope="module")
def reference(tmp_path_factory, device):
    out = tmp_path_factory.mktemp("reference")
    summary = generate(out, device)
    return out, summary


def test_shards_open_with_plain_h5py(reference):
    """Two shards, 9 frames, every dataset the format promises with its shape and dtype; the
    configs and episode records are JSON; the manifest and dataset card are written."""
    out, summary = reference
    assert summary["frames"] == FRAMES and summary["shards_written"] == 2
    total = 0
    for path in sorted(out.glob("shard-*.h5")):
        with h5py.File(path, "r") as f:
            n = int(f.attrs["frame_count"])
            total += n
            assert f.attrs["format_version"] == FORMAT_VERSION
            assert f["energyscape"].shape == (n, 1, 240, 181) and f["energyscape"].dtype == np.float16
            assert f["elevation_deg"][:].tolist() == [0.0]
            assert f["lidar/image"].shape == (n, 240, 181) and f["lidar/image"].dtype == np.uint8
            assert f["lidar/ranges"].shape == (n, 1081) and f["pose"].shape == (n, 4, 4)
            assert f["range_m"].shape == (240,) and f["azimuth_rad"].shape == (181,)
            assert np.isfinite(f["energyscape"][:]).all() and f["energyscape"][:].max() > 0
            assert f["lidar/image"][:].sum() > 0
            episodes = json.loads(f.attrs["episodes"])
            assert sorted({e["index"] for e in episodes}) == sorted(set(f["episode"][:]))
            assert json.loads(f.attrs["config"])["physics"]["ray_count"] == 2000
            assert f["signals"].shape == (n, 32, 16384) and f["signals"].dtype == np.float16
            frame = f["arrivals/frame"][:]
            assert frame.min() == 0 and frame.max() == n - 1 and f["arrivals/direction"].shape == (len(frame), 3)
    assert total == FRAMES
    manifest = json.loads((out / "manifest.json").read_text())
    assert manifest["frames"] == FRAMES and len(manifest["shards"]) == 2
    assert manifest["scenarios"] == {"room": 3, "corridor": 3, "random": 3}
    assert (out / "card.png").stat().st_size > 10_000 and "card.png" in (out / "README.md").read_text()


def test_resume_after_a_kill_gives_the_same_dataset(reference, tmp_path, device, monkeypatch):
    """A run killed while writing its second shard leaves only the first under a final name;
    rerunning skips it and finishes with arrays identical to an uninterrupted run."""
    real_write = runner.write_shard

    def dying_write(path, frames, **kwargs):
        if path.name == "shard-00001.h5":
            path.with_name(path.name + ".tmp").write_bytes(b"half a shard")
            raise KeyboardInterrupt
        real_write(path, frames, **kwargs)

    monkeypatch.setattr(runner, "write_shard", dying_write)
    with pytest.raises(KeyboardInterrupt):
        generate(tmp_path, device)
    assert sorted(p.name for p in tmp_path.glob("shard-*")) == ["shard-00000.h5", "shard-00001.h5.tmp"]
    first = (tmp_path / "shard-00000.h5").stat().st_mtime_ns
    monkeypatch.setattr(runner, "write_shard", real_write)
    summary = generate(tmp_path, device)
    assert summary["shards_skipped"] == 1 and summary["shards_written"] == 1
    assert (tmp_path / "shard-00000.h5").stat().st_mtime_ns == first
    assert not list(tmp_path.glob("*.tmp"))
    got, want = shard_arrays(tmp_path), shard_arrays(reference[0])
    assert got.keys() == want.keys()
    for key in want:
        np.testing.assert_array_equal(got[key], want[key], err_msg=key)
    again = generate(tmp_path, device)
    assert again["shards_written"] == 0


def test_overlapped_parts_change_nothing_but_the_time(reference, tmp_path, device, monkeypatch):
    """Preparing the next episode and writing a finished shard beside the rendering (the default;
    the last shard, with nothing left to render, by the rendering thread itself) gives the same
    arrays as doing each part in turn, and the summary says where the time went."""
    events = []
    real_prepare, real_write = gen.prepare_episode, runner.write_shard

    def prepare(episode, *args):
        events.append(("prepare", episode.index, threading.current_thread() is threading.main_thread()))
        return real_prepare(episode, *args)

    def write(path, frames, **kwargs):
        events.append(("write", path.name, threading.current_thread() is threading.main_thread()))
        real_write(path, frames, **kwargs)

    monkeypatch.setattr(gen, "prepare_episode", prepare)
    monkeypatch.setattr(runner, "write_shard", write)
    overlapped = generate(tmp_path / "overlapped", device, helpers=0)  # threads (helper processes: below)
    # in any order: the first shard's write beside the rendering of the second, the last after it
    assert sorted((part, on_main) for part, _, on_main in events) == [("prepare", False)] * 3 + [
        ("write", False),
        ("write", True),
    ]
    events.clear()
    monkeypatch.setattr(gen, "prepare_episode", real_prepare)  # simulate_episode prepares by itself
    in_turn = generate(tmp_path / "in_turn", device, overlap=False)
    assert [e[0] for e in events] == ["write", "write"] and all(on_main for *_, on_main in events)
    for folder in ("overlapped", "in_turn"):
        got, want = shard_arrays(tmp_path / folder), shard_arrays(reference[0])
        assert got.keys() == want.keys()
        for key in want:
            np.testing.assert_array_equal(got[key], want[key], err_msg=f"{folder}: {key}")
    for summary in (overlapped, in_turn):
        parts = summary["seconds_by_part"]
        assert set(parts) == set(gen.PARTS) == {"start-up", "prepare", "lidar", "sonar", "assemble", "write", "waiting"}
        assert parts["start-up"] == 0  # one process: no worker to start
        assert all(parts[k] > 0 for k in ("prepare", "lidar", "sonar", "assemble", "write"))
        # the rendering thread's parts never add up to more than the run (assemble not counted twice)
        assert parts["lidar"] + parts["sonar"] + parts["assemble"] + parts["waiting"] < summary["seconds"]
    assert in_turn["seconds_by_part"]["waiting"] == 0


def test_helper_processes_prepare_and_write_the_same_shards(reference, tmp_path, device, monkeypatch):
    """With helper processes (the default where cores allow), episodes are prepared and shards
    written in other processes than the rendering one (but the last shard, written after the
    rendering by its process, on its cores), two episodes ahead and two writes in flight, a
    helper compressing in one thread; the arrays are the single-thread run's bit for bit."""
    log = tmp_path / "who.txt"
    real_prepare, real_write = gen.prepare_episode, runner.write_shard

    def prepare(episode, *args):
        with log.open("a") as f:
            f.write(f"prepare {os.getpid()}\n")
        return real_prepare(episode, *args)

    def write(path, frames, **kwargs):
        mapped = all(in_shared_memory(a[0]) for a in (frames.energyscape, frames.lidar_image))
        with log.open("a") as f:
            f.write(f"write {os.getpid()} {mapped} {kwargs.get('threads')}\n")
        real_write(path, frames, **kwargs)

    real_share = shared_frames.SharedFrames.share.__func__

    def share(cls, frames, *args):
        with log.open("a") as f:
            f.write(f"share {os.getpid()} {threading.current_thread().name.split('_')[0]}\n")
        return real_share(cls, frames, *args)

    monkeypatch.setattr(gen, "prepare_episode", prepare)
    monkeypatch.setattr(runner, "write_shard", write)
    monkeypatch.setattr(shared_frames.SharedFrames, "share", classmethod(share))
    leftovers = set(Path(shared_frames.FOLDER).glob("sonar2lidar-*"))
    summary = generate(tmp_path / "out", device, helpers=2)
    who = [line.split() for line in log.read_text().splitlines()]
    # copied into shared memory beside the rendering, by this process's hand-over thread
    assert [rest for part, *rest in who if part == "share"] == [[str(os.getpid()), "shard-handover"]]
    who = [line for line in who if line[0] != "share"]
    assert sorted(part for part, *_ in who) == ["prepare"] * 3 + ["write"] * 2
    here = [(part, *rest) for part, pid, *rest in who if pid == str(os.getpid())]
    assert here == [("write", "False", "None")]  # the last shard, from this process's own arrays
    assert [rest for part, pid, *rest in who if part == "write" and pid != str(os.getpid())] == [["True", "1"]]
    assert set(Path(shared_frames.FOLDER).glob("sonar2lidar-*")) == leftovers  # every file removed
    got, want = shard_arrays(tmp_path / "out"), shard_arrays(reference[0])
    assert got.keys() == want.keys()
    for key in want:
        np.testing.assert_array_equal(got[key], want[key], err_msg=key)
    parts = summary["seconds_by_part"]
    assert parts["prepare"] > 0 and parts["write"] > 0  # timed in the helpers, sent back


def in_shared_memory(array: np.ndarray) -> bool:
    """Whether `array` is a view into a memory map (a shard handed over by SharedFrames)."""
    while array is not None and not isinstance(array, mmap.mmap):
        array = array.obj if isinstance(array, memoryview) else getattr(array, "base", None)
    return array is not None


def test_shared_frames_round_trip_and_fall_back(tmp_path, monkeypatch):
    """A shard's arrays come back equal from the shared file, which `open` removes (a write that
    never opened it is cleaned up by `release`); with no room the caller is told to pickle."""
    rng = np.random.default_rng(0)
    frames = ShardFrames(
        energyscape=[rng.random((3, 1, 5, 7)).astype(np.float16), rng.random((2, 1, 5, 7)).astype(np.float16)],
        lidar_ranges=[rng.random((5, 11), dtype=np.float32)],
        lidar_image=[rng.integers(0, 2, (5, 5, 7), dtype=np.uint8)],
        pose=[np.tile(np.eye(4), (5, 1, 1))],
        time=[np.arange(5.0)],
        episode=[np.zeros(3, np.int64), np.ones(2, np.int64)],
        scenario=[np.zeros(5, np.int64)],
        arrivals=[{"frame": np.arange(4)}],
    )
    shared = shared_frames.SharedFrames.share(frames, folder=str(tmp_path))
    assert shared is not None and Path(shared.path).exists()
    back = copy.deepcopy(shared).open()  # a copy, as a helper process gets it: no map travels
    assert not Path(shared.path).exists()
    shared.release()  # after the helper opened it: nothing left to remove
    for name in shared_frames.ARRAYS:
        want = getattr(frames, name)
        got = getattr(back, name)
        if want:
            assert len(got) == 1 and in_shared_memory(got[0])
            np.testing.assert_array_equal(got[0], np.concatenate(want), err_msg=name)
        else:
            assert got == []
    assert back.frame_count == 5 and back.arrivals[0]["frame"].tolist() == [0, 1, 2, 3]
    unopened = shared_frames.SharedFrames.share(frames, folder=str(tmp_path))
    unopened.release()
    assert list(tmp_path.iterdir()) == []
    assert shared_frames.SharedFrames.share(frames, folder=str(tmp_path / "absent")) is None

    def full(fd, data, offset):
        raise OSError(28, "No space left on device")

    monkeypatch.setattr(shared_frames.os, "pwrite", full)
    assert shared_frames.SharedFrames.share(frames, folder=str(tmp_path)) is None
    assert list(tmp_path.iterdir()) == []
    # a rendering process killed after handing a shard over: its parent sweeps what it left
    left = [tmp_path / f"sonar2lidar-{pid}-0-ab12cd34" for pid in (4242, 42, 424)]
    for path in left:
        path.write_bytes(b"x")
    assert shared_frames.sweep([4242, 424], folder=str(tmp_path)) == 2
    assert list(tmp_path.iterdir()) == [left[1]]


def test_helper_counts(monkeypatch):
    """Cores left per worker, at least MIN_HELPERS and at most MAX_HELPERS (threads where none is
    left); a count given is kept, a negative one refused."""
    assert runner.host_helpers(1, 0) == 0 and runner.host_helpers(8, 3) == 3
    with pytest.raises(ValueError, match="helpers must be >= 0"):
        runner.host_helpers(2, -1)
    monkeypatch.setenv("SONAR2LIDAR_CPU_THREADS", "16")
    expected = [4, 3, 3, 3, 0] if sys.platform.startswith("linux") else [0] * 5  # cores left: 15, 3, 2, 1, 0
    assert (runner.MIN_HELPERS, runner.MAX_HELPERS) == (3, 4)
    assert [runner.host_helpers(w) for w in (1, 4, 5, 8, 16)] == expected


def _niceness(_renderer) -> int:
    return os.nice(0)


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="helper processes are forked on Linux only")
def test_helpers_run_at_the_niceness_asked(monkeypatch):
    """SONAR2LIDAR_HELPER_NICENESS lowers the helpers' priority below this process's (0 by
    default); a value outside 0-19 is refused before any helper is forked."""
    own = os.nice(0)
    for asked, expected in ((None, own), ("7", min(19, own + 7))):
        if asked is None:
            monkeypatch.delenv(helper_processes.HELPER_NICENESS_ENV, raising=False)
        else:
            monkeypatch.setenv(helper_processes.HELPER_NICENESS_ENV, asked)
        pool = helper_processes.helper_pool(1, None)
        try:
            assert pool.submit(_niceness, None).result() == expected
        finally:
            pool.shutdown()
    for bad in ("-2", "20", "low"):
        monkeypatch.setenv(helper_processes.HELPER_NICENESS_ENV, bad)
        with pytest.raises(ValueError, match="SONAR2LIDAR_HELPER_NICENESS"):
            helper_processes.helper_pool(1, None)


def test_foreign_corrupt_and_other_version_files(reference, tmp_path, device):
    path = tmp_path / "x.h5"
    path.write_text("not hdf5")
    with pytest.raises(DatasetError, match="not a readable HDF5"):
        read_attrs(path)
    with h5py.File(path, "w") as f:
        f.attrs["format"] = "something-else"
    with pytest.raises(DatasetError, match="not a sonar2lidar-dataset"):
        read_attrs(path)
    shard = tmp_path / "shard.h5"
    shard.write_bytes((reference[0] / "shard-00000.h5").read_bytes())
    with h5py.File(shard, "a") as f:
        f.attrs["format_version"] = 99
    with pytest.raises(DatasetError, match="format_version 99"):
        read_attrs(shard)
    with h5py.File(shard, "a") as f:
        f.attrs["format_version"] = FORMAT_VERSION
        del f["lidar/image"]
    with pytest.raises(DatasetError, match="incomplete or corrupt"):
        read_attrs(shard)
    # Another run's folder is never overwritten.
    with pytest.raises(DatasetError, match="other settings"):
        gen.generate(SUITE, reference[0], frames=FRAMES, shards=2, seed=8, device=device, progress=False)


def test_windows_never_cross_episodes():
    """Episodes of 4, 1 and 3 frames: K = 3 windows start only where all three frames share an
    episode; a repeated episode id after another episode is still a boundary."""
    episode = np.array([5, 5, 5, 5, 6, 7, 7, 7, 5, 5])
    np.testing.assert_array_equal(window_starts(episode, 3), [0, 1, 5])
    np.testing.assert_array_equal(window_starts(episode, 1), np.arange(10))
    np.testing.assert_array_equal(window_starts(episode, 2), [0, 1, 2, 5, 6, 8])
    assert len(window_starts(episode, 11)) == 0


def test_suite_files(tmp_path):
    """A TOML suite starts from a named one; physics overrides apply to every variant; mistakes
    are named."""
    path = tmp_path / "mine.toml"
    path.write_text('base = "ablation"\nframes = 50\n[physics]\nray_count = 1000\n')
    suite = load_suite(path)
    assert suite.frames == 50 and set(suite.variants) == {"bounces_0", "bounces_1", "bounces_3"}
    assert {p.ray_count for p in suite.variants.values()} == {1000}
    assert [p.max_bounces for p in suite.variants.values()] == [0, 1, 3]
    path.write_text('base = "paper"\nframez = 5\n')
    with pytest.raises(ValueError, match="unknown keys"):
        load_suite(path)
    path.write_text('[[scenarios]]\nname = "x"\nbuilder = "castle"\n')
    with pytest.raises(ValueError, match="unknown builder"):
        load_suite(path)
    with pytest.raises(ValueError, match="unknown suite"):
        load_suite("nope")


def test_episodes_are_dealt_by_weight_and_shared_by_variants():
    """Ablation variants hold the same episodes (scenes, seeds); scenarios are dealt evenly."""
    suite = SUITES["ablation"]
    tasks = gen.plan(suite, "/nonexistent", frames=2400, shards=3, seed=1)
    by_variant = {}
    for t in tasks:
        by_variant.setdefault(t.variant, []).extend(t.episodes)
    assert by_variant["bounces_0"] == by_variant["bounces_1"] == by_variant["bounces_3"]
    counts = np.bincount([e.scenario for e in by_variant["bounces_0"]], minlength=12)
    assert counts.min() == counts.max() == 2
    assert len({e.seed for e in by_variant["bounces_0"]}) == 24


class BarSteps:
    """Stands in for tqdm in `generate`: records every step the progress bar is moved by."""

    steps: typing.ClassVar[list[int]] = []

    def __init__(self, *args, **kwargs):
        BarSteps.steps = []

    def update(self, n):
        BarSteps.steps.append(n)

    def set_description(self, text):
        pass

    def close(self):
        pass


@pytest.mark.parametrize("start", ["fork", "spawn"])
def test_parallel_workers_write_the_same_shards(reference, tmp_path, device, monkeypatch, start):
    """Two worker processes (forked, or spawned as after CUDA has started here), one shard each:
    the arrays equal the single-process run's, and the parent's bar moves as the workers simulate
    frames (per episode here), not per shard."""
    if start == "fork" and workers.start_method() != "fork":
        pytest.skip("this process has started CUDA (or is not on Linux): its workers are spawned")
    monkeypatch.setenv(workers.START_ENV, start)
    monkeypatch.setattr(gen, "tqdm", BarSteps)
    summary = generate(tmp_path, device, workers=2)
    assert summary["shards_written"] == 2 and summary["worker_start"] == start
    assert sum(BarSteps.steps) == FRAMES and len(BarSteps.steps) == 3, BarSteps.steps
    parts = summary["seconds_by_part"]
    assert parts["sonar"] > 0 and parts["write"] > 0 and parts["start-up"] > 0  # sent back
    got, want = shard_arrays(tmp_path), shard_arrays(reference[0])
    assert got.keys() == want.keys()
    for key in want:
        np.testing.assert_array_equal(got[key], want[key], err_msg=key)


def test_ray_tasks_write_the_same_shards(reference, tmp_path, device):
    """The same shard tasks on a local Ray instance give the single-process arrays. Needs the
    `ray` extra (not installed in CI, where this test is reported as skipped)."""
    pytest.importorskip("ray")
    summary = generate(tmp_path, device, ray_address="local")
    assert summary["shards_written"] == 2
    got, want = shard_arrays(tmp_path), shard_arrays(reference[0])
    for key in want:
        np.testing.assert_array_equal(got[key], want[key], err_msg=key)


@pytest.mark.parametrize("mode", [None, "disabled", "token"])
def test_a_refused_ray_connection_names_token_authentication(tmp_path, monkeypatch, mode):
    """`ray start` has turned token authentication on by default since Ray 2.59, and a caller
    without RAY_AUTH_MODE=token (unset or "disabled") gets only "failed to connect": the error says
    what to set. A caller in token mode gets Ray's own error (its token, not the mode, is wrong). A fake Ray module
    stands in: CI has no Ray."""

    class Refusing:
        @staticmethod
        def init(**kwargs):
            raise ConnectionError("Failed to connect to Ray cluster at 10.0.0.1:6379")

    monkeypatch.setitem(sys.modules, "ray", Refusing)
    if mode:
        monkeypatch.setenv("RAY_AUTH_MODE", mode)
    else:
        monkeypatch.delenv("RAY_AUTH_MODE", raising=False)
    with pytest.raises(ConnectionError) as caught:
        gen._run_on_ray([], gen.SuiteRenderer(), "10.0.0.1:6379", gpu_share=0, bar=None)
    assert ("RAY_AUTH_MODE=token" in str(caught.value)) == (mode != "token"), caught.value


@pytest.mark.parametrize(("per_gpu", "share", "actors"), [(1, 1.0, 2), (4, 0.25, 8), (None, 0, 3)])
def test_ray_actors_hold_a_share_of_a_gpu_and_render_every_shard_once(tmp_path, monkeypatch, per_gpu, share, actors):
    """`ray_tasks_per_gpu` n asks Ray for 1/n of a GPU per actor, so n share one, and the cluster's
    GPUs / (1/n) actors render the shards, each on the GPU Ray shows it (its cuda:0), the next run of
    shards to whichever is free (on CPUs: an actor per CPU); the run reports each actor's host and
    GPU as they name them, not cuda:0. A fake Ray module stands in: CI has no Ray."""
    asked, rendered, made = {}, [], []

    class Recording:
        @staticmethod
        def init(**kwargs):
            pass

        @staticmethod
        def cluster_resources():
            return {"GPU": 2.0, "CPU": 3.0}

        @staticmethod
        def remote(**options):
            asked.update(options)

            def actor_class(cls):
                def make(renderer, device):
                    made.append(device)
                    where = f"10.0.0.{len(made) % 2} GPU {len(made) // 2}"  # the host and GPU Ray gave it

                    def render(run):
                        rendered.append(run)
                        return sum(task.frame_count for task in run), where  # the ref: what `get` returns

                    return SimpleNamespace(render=SimpleNamespace(remote=render))

                return SimpleNamespace(remote=make)

            return actor_class

        @staticmethod
        def wait(refs, num_returns):
            return refs[:num_returns], refs[num_returns:]

        @staticmethod
        def get(ref):
            return ref

    monkeypatch.setitem(sys.modules, "ray", Recording)
    frames = []
    bar = SimpleNamespace(update=frames.append)
    tasks = [SimpleNamespace(frame_count=i + 1) for i in range(10)]
    places = gen._run_on_ray(tasks, gen.SuiteRenderer(), "local", gpu_share=1 / per_gpu if per_gpu else 0, bar=bar)
    assert asked.get("num_gpus", 0) == share and asked.get("num_cpus") == (None if share else 1)
    assert made == ["cuda:0" if share else "cpu"] * actors
    assert sorted(t.frame_count for run in rendered for t in run) == list(range(1, 11)) and sum(frames) == 55
    assert [len(run) for run in rendered][: len(made)] == [gen.ray_run_length(10, actors)] * len(made)
    assert places == sorted({f"10.0.0.{(i + 1) % 2} GPU {(i + 1) // 2}" for i in range(actors)})  # what it reports
    assert gen.ray_slots(Recording, 0.5, tasks=3) == 3  # never more actors than shards
    with pytest.raises(ValueError, match="needs a Ray address"):
        gen.make_dataset([], gen.SuiteRenderer(), tmp_path, plan_meta={}, ray_tasks_per_gpu=2)


def test_ray_runs_shrink_as_the_work_runs_out():
    """An actor gets about half of an even share of the shards left, so its rendering overlaps its
    writing over several shards, at most MAX_RUN (its bar moves), and the last ones go one by one."""
    assert [gen.ray_run_length(n, 4) for n in (1000, 64, 40, 16, 9, 8, 3, 1)] == [8, 8, 5, 2, 1, 1, 1, 1]
    left, actors, runs = 100, 4, []
    while left:
        runs.append(gen.ray_run_length(left, actors))
        left -= runs[-1]
    assert runs[:5] == [8] * 5 and runs == sorted(runs, reverse=True) and runs[-8:] == [1] * 8


def test_a_worker_takes_its_next_shard_only_during_the_last_episode_of_this_one(tmp_path, device, monkeypatch):
    """run_tasks reads its tasks lazily (in a worker, from the queue all workers share): the next
    shard is taken while the last episode of the current one renders, never earlier, so a worker
    holds at most one shard it has not started and the workers finish close together."""
    tasks = gen.plan(SUITE, tmp_path, frames=FRAMES, shards=2, seed=7)
    assert [len(t.episodes) for t in tasks] == [2, 1]
    events = []
    real_simulate = gen.simulate_episode

    def taken():
        for task in tasks:
            events.append(("take", task.shard))
            yield task

    def simulate(ready, *args, **kwargs):
        events.append(("render", ready.episode.index))
        return real_simulate(ready, *args, **kwargs)

    monkeypatch.setattr(gen, "simulate_episode", simulate)
    entries, _ = gen.run_tasks(taken(), gen.SuiteRenderer(), device)
    episodes = [e.index for t in tasks for e in t.episodes]
    assert events == [
        ("take", 0),
        ("render", episodes[0]),
        ("take", 1),  # to prepare its first episode beside the render of shard 0's last
        ("render", episodes[1]),
        ("render", episodes[2]),
    ]
    assert [e["file"] for e in entries] == ["shard-00000.h5", "shard-00001.h5"]
