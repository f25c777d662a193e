"""Specular path tracer against the analytic image sources of a shoebox room."""

import dataclasses
import itertools
import sys
import warnings

import numpy as np
import pytest
import warp as wp

import acoustic_sim as sim
import scenes
from acoustic_sim.engine.kernels.common import add_count, claim_slot
from acoustic_sim.engine.kernels.image_sources import image_key
from acoustic_sim.engine.lidar import check_poses
from acoustic_sim.engine.paths import KIND_SCATTERED, KIND_SPECULAR, PosesOnDevice
from acoustic_sim.engine.sonar import Sonar
from benchmarks.provenance import gpus  # nvidia-smi's list, without starting CUDA here
from scenes.scene import assemble, box_mesh

SIZE = np.array([6.0, 4.0, 3.0])
POSE = scenes.pose(2.0, 1.5, 0.4, 1.2)
# A vanishing piston radius makes the emitter omnidirectional over its front half-space.
OMNI = sim.SonarConfig.ertis(emitter_radius_m=1e-6)
SPHERE = sim.SonarConfig.ertis(emitter_pattern="omni")  # omnidirectional over the whole sphere
SAMPLE_M = 343.0 / 450e3  # one sample at 450 kHz, as a path length


def shoebox_images(size, emitter, receiver, pose, max_order):
    """Image sources of `emitter` in the box [0, size] with order <= max_order that leave the
    emitter forwards (sensor +x half-space): (lengths (n,), orders (n,), images (n, 3)).

    Image along axis i: 2 n L_i + (1 - 2 q) e_i with n integer, q in {0, 1}; it takes |2n - q|
    reflections on that axis' walls. Leaving direction: the arrival direction with each axis
    flipped once per reflection on it.
    """
    out = []
    span = range(-max_order, max_order + 1)
    for n in itertools.product(span, span, span):
        for q in itertools.product((0, 1), repeat=3):
            counts = np.abs(2 * np.array(n) - q)
            if not 1 <= counts.sum() <= max_order:
                continue
            image = 2 * np.array(n) * size + (1 - 2 * np.array(q)) * emitter
            arrival = (receiver - image) / np.linalg.norm(receiver - image)
            leaving = pose[:3, :3].T @ (arrival * (-1.0) ** counts)
            if leaving[0] >= -1e-9:
                out.append((np.linalg.norm(image - receiver), counts.sum(), image))
    lengths, orders, images = (np.array(v) for v in zip(*out, strict=True))
    return lengths, orders, images


def emitter_and_receiver(pose, config):
    return (pose @ np.r_[config.emitter_m, 1.0])[:3], pose[:3, 3]


@pytest.mark.parametrize("max_bounces", [0, 1, 2])
def test_specular_paths_equal_shoebox_image_sources(device, max_bounces):
    """6 x 4 x 3 m mirror box, sensor at (2, 1.5, 1.2) yawed 0.4 rad, emitter 5 cm above the
    array: every image source up to order max_bounces + 1 that leaves the emitter forwards is
    found once (corner echoes on the wall edges included), path lengths within 1e-4 m (0.13 of a
    sample at 450 kHz), amplitude 1 / length, arrival direction towards the image; no extras."""
    room = scenes.box_room(tuple(SIZE), wall="mirror", floor="mirror", ceiling="mirror")
    arrivals = Sonar(OMNI, max_bounces=max_bounces, ray_count=20_000, scattering=False, device=device).trace(room, POSE)
    emitter, receiver = emitter_and_receiver(POSE, OMNI)
    lengths, orders, images = shoebox_images(SIZE, emitter, receiver, POSE, max_bounces + 1)
    got = arrivals.for_pose(0)
    assert len(got) == len(lengths), f"found {np.bincount(got.order)}, expected {np.bincount(orders)}"
    expected_images = (images - receiver) @ POSE[:3, :3]  # into the sensor frame
    gap = np.linalg.norm(expected_images[:, None] - got.source_m[None], axis=-1)
    match = gap.argmin(axis=1)  # each reference image to the arrival at its position
    assert len(set(match)) == len(lengths) and gap.min(axis=1).max() < 1e-4
    got = got.select(match)
    np.testing.assert_allclose(got.length_m, lengths, atol=1e-4)
    assert np.all(np.abs(got.length_m - lengths) < SAMPLE_M)
    np.testing.assert_array_equal(got.order, orders)
    np.testing.assert_allclose(got.delay_s, lengths / OMNI.atmosphere.speed_of_sound, rtol=1e-6)
    np.testing.assert_allclose(got.amplitude * got.length_m, 1.0, rtol=1e-4)
    np.testing.assert_allclose(got.direction, expected_images / lengths[:, None], atol=1e-5)
    # The last reflection point lies on a wall, straight along the arrival direction.
    world = got.point_m @ POSE[:3, :3].T + POSE[:3, 3]
    assert np.all(np.minimum(np.abs(world), np.abs(world - SIZE)).min(axis=1) < 1e-4)
    along = np.einsum("ij,ij->i", got.point_m, got.direction)
    np.testing.assert_allclose(got.point_m, along[:, None] * got.direction, atol=1e-4)


def test_reflection_and_scattering_coefficients_scale_amplitude(device):
    """Painted walls (R = 0.97, s = 0.05): each reflection scales pressure by sqrt(R (1 - s))."""
    room = scenes.box_room(tuple(SIZE), wall="painted_wall", floor="painted_wall", ceiling="painted_wall")
    got = Sonar(OMNI, max_bounces=2, device=device).trace(room, POSE)
    got = got.select(got.kind == KIND_SPECULAR)
    factor = np.sqrt(0.97 * (1 - 0.05)) ** got.order
    np.testing.assert_allclose(got.amplitude * got.length_m, factor, rtol=1e-4)


def wall_counts(image, emitter, size):
    """Reflections off each wall (x = 0, x = Lx, y = 0, y = Ly, floor, ceiling) of the path of a
    shoebox image source: along axis i the image is 2 n L + e (n reflections off each wall) or
    2 n L - e (|2n - 1|: n off the far wall and n - 1 off the near one for n >= 1, |n| and |n| + 1
    for n <= 0)."""
    counts = []
    for x, e, length in zip(image, emitter, size, strict=True):
        even, odd = (x - e) / (2 * length), (x + e) / (2 * length)
        if abs(even - round(even)) < 1e-4:
            n = abs(round(even))
            counts += [n, n]
        else:
            assert abs(odd - round(odd)) < 1e-4, "not an image source of this box"
            n = round(odd)
            counts += [n - 1, n] if n >= 1 else [abs(n) + 1, abs(n)]
    return counts


def test_each_specular_path_names_the_walls_it_reflects_off(device):
    """A box whose six walls are six surface classes of different R: each specular arrival's
    faces (`Arrivals.faces`, counted per class by `surface_counts`) reflect off each wall as often
    as its image source says, and its amplitude is the product of sqrt(R) of those walls over its
    length (an omnidirectional emitter)."""
    mirror = scenes.material("mirror")
    reflection = (0.9, 0.8, 0.7, 0.6, 0.5, 0.4)
    room = scenes.box_room(tuple(SIZE), wall="mirror", floor="mirror", ceiling="mirror")
    centre = room.mesh.triangles_center
    wall = np.full(len(centre), -1)
    for axis in range(3):
        wall[np.isclose(centre[:, axis], 0.0)] = 2 * axis
        wall[np.isclose(centre[:, axis], SIZE[axis])] = 2 * axis + 1
    assert (wall >= 0).all()
    materials = tuple(
        dataclasses.replace(mirror, name=f"wall{k}", acoustic_reflection=r) for k, r in enumerate(reflection)
    )
    room = dataclasses.replace(room, face_material=wall, materials=materials)
    arrivals = Sonar(OMNI, max_bounces=2, ray_count=20_000, scattering=False, device=device).trace(room, POSE)
    assert (arrivals.kind == KIND_SPECULAR).all() and len(arrivals) > 30
    emitter, _ = emitter_and_receiver(POSE, OMNI)
    images = (POSE @ np.c_[arrivals.source_m, np.ones(len(arrivals))].T).T[:, :3]
    expected = np.array([wall_counts(image, emitter, SIZE) for image in images])
    got = arrivals.surface_counts(room.face_material, len(materials))
    np.testing.assert_array_equal(got, expected)
    assert (got.sum(axis=1) == arrivals.order).all()
    factor = np.prod(np.sqrt(reflection) ** got, axis=1)
    np.testing.assert_allclose(arrivals.amplitude * arrivals.length_m, factor, rtol=1e-4)


def test_obstacle_occludes_its_wall(device):
    """A pillar between the sensor and the x = 6 m wall removes that wall's first-order echo and
    adds the pillar's own; the other first-order echoes stay."""
    pose = scenes.pose(2.0, 2.0, 0.0, 1.2)
    walls = dict(wall="mirror", floor="mirror", ceiling="mirror")
    room = scenes.box_room(tuple(SIZE), **walls)
    pillar = assemble([(room.mesh, "mirror"), (box_mesh((4.0, 2.0, 1.5), (0.4, 0.4, 3.0)), "mirror")], name="p")
    sonar = Sonar(OMNI, max_bounces=0, scattering=False, device=device)
    before = sonar.trace(room, pose).length_m
    after = sonar.trace(pillar, pose).length_m
    wall_echo = 2 * (6.0 - 2.0)  # straight ahead and back (the emitter sits 5 cm higher)
    assert np.min(np.abs(before - wall_echo)) < 0.01
    assert np.min(np.abs(after - wall_echo)) > 0.1
    assert np.min(np.abs(after - 2 * 1.8)) < 0.01  # the pillar's face at x = 3.8 m
    assert len(after) == len(before)  # the floor and ceiling echoes remain


def test_trace_is_deterministic_and_batched(device):
    """Two poses in one call equal each pose traced alone; a repeat gives identical arrays."""
    room = scenes.box_room(tuple(SIZE), wall="mirror", floor="mirror", ceiling="mirror")
    other = scenes.pose(4.0, 2.5, 2.5, 1.0)
    sonar = Sonar(OMNI, max_bounces=1, device=device)
    both = sonar.trace(room, np.stack([POSE, other]))
    np.testing.assert_array_equal(both.for_pose(1).length_m, sonar.trace(room, other).for_pose(0).length_m)
    np.testing.assert_array_equal(both.for_pose(0).length_m, sonar.trace(room, POSE).for_pose(0).length_m)


def test_rays_are_the_fibonacci_lattice_in_neighbouring_order():
    """ray_directions reorders the lattice and changes no ray: its rows are the lattice's
    (x uniform in cos theta, golden-angle azimuth), and neighbours in the array are neighbours on
    the sphere (median angle under 1 degree at 100k rays; the lattice's own order: ~108 degrees)."""
    from acoustic_sim.engine.paths import ray_directions

    n = 100_000
    i = np.arange(n) + 0.5
    x = 1.0 - i / n
    phi = np.pi * (3.0 - np.sqrt(5.0)) * i
    lattice = np.c_[x, np.sqrt(1.0 - x * x) * np.cos(phi), np.sqrt(1.0 - x * x) * np.sin(phi)]
    rays = ray_directions(n)
    np.testing.assert_array_equal(rays[np.lexsort(rays.T)], lattice[np.lexsort(lattice.T)])
    step = np.degrees(np.arccos(np.clip(np.sum(rays[1:] * rays[:-1], axis=1), -1.0, 1.0)))
    assert np.median(step) < 1.0, np.median(step)


def test_the_order_of_the_rays_changes_no_echo(device):
    """The rays are launched in Z-order of their directions, for coherent warps; any order must
    give the same signals bit for bit (each echo is summed in integers), scattered arrivals and
    multipath included. A random permutation of the rays (and their energy shares) is the check."""
    room = scenes.box_room(tuple(SIZE))  # default materials: rough walls scatter
    poses = np.stack([POSE, scenes.pose(4.0, 2.5, 1.0, 2.5)])
    sonar = Sonar(OMNI, max_bounces=3, ray_count=3000, device=device)
    arrivals = sonar.trace(room, poses)
    assert (arrivals.kind == KIND_SCATTERED).sum() > 1000 and (arrivals.kind == KIND_SPECULAR).any()
    before = sonar.record(arrivals, pose_count=2)
    tracer = sonar.tracer
    order = np.random.default_rng(0).permutation(3000)
    tracer._ray_dirs = wp.array(tracer._ray_dirs.numpy()[order], dtype=wp.vec3, device=tracer.device)
    tracer._ray_energy = wp.array(tracer._ray_energy.numpy()[order], dtype=float, device=tracer.device)
    np.testing.assert_array_equal(sonar.record(sonar.trace(room, poses), pose_count=2), before)


def test_host_copies_of_batches_take_turns_in_two_sets(device):
    """A batch is queued while the one before it is in flight, its checks unread: their host
    copies must not share memory, while the batch after reuses the first's, of any smaller shape
    (no page-locked memory is allocated, or freed, per batch), and a larger batch gets its own."""
    tracer = Sonar(OMNI, max_bounces=1, ray_count=16, device=device).tracer
    first = tracer._host_checks_for(4, None)
    second = tracer._host_checks_for(4, first)
    assert {a.ptr for a in first}.isdisjoint(a.ptr for a in second)
    third = tracer._host_checks_for(3, second)
    assert [a.ptr for a in third] == [a.ptr for a in first] and third[0].shape == (3,)
    larger = tracer._host_checks_for(9, third)
    assert larger[0].shape == (9,) and {a.ptr for a in larger}.isdisjoint(a.ptr for a in third)
    again = tracer._host_checks_for(9, larger)  # the other set grows too
    assert again[0].shape == (9,) and {a.ptr for a in again}.isdisjoint(a.ptr for a in larger)
    assert [a.ptr for a in tracer._host_checks_for(5, again)] == [a.ptr for a in larger]


def test_a_tracer_that_is_gone_leaves_its_host_copies_to_the_next(device, monkeypatch):
    """A suite that draws its sonar per episode builds a tracer per episode: the next one takes
    the page-locked check copies of the one before instead of allocating (and the old one's
    freeing, which waits for the GPU), and a device keeps at most SPARE_CHECKS_KEPT spare sets."""
    import gc
    from collections import defaultdict

    from acoustic_sim.engine import paths

    monkeypatch.setattr(paths, "_SPARE_CHECKS", defaultdict(list))
    tracer = Sonar(OMNI, max_bounces=1, ray_count=16, device=device).tracer
    first = tracer._host_checks_for(4, None)
    before = {first[0].ptr, tracer._host_checks_for(4, first)[0].ptr}
    del tracer, first
    gc.collect()
    after = Sonar(OMNI, max_bounces=2, ray_count=16, device=device).tracer
    taken = after._host_checks_for(3, None)
    assert taken[0].shape == (3,) and {taken[0].ptr, after._host_checks_for(3, taken)[0].ptr} == before
    tracers = [Sonar(OMNI, ray_count=16, device=device).tracer for _ in range(6)]
    for t in tracers:
        t._host_checks_for(5, t._host_checks_for(5, None))  # two sets each
    del tracers
    gc.collect()
    assert len(paths._SPARE_CHECKS[str(after.device)]) == paths.SPARE_CHECKS_KEPT


def test_pings_that_overflow_the_sequence_table_are_traced_again_larger(device):
    """Of three pings at a mirror box, one inside sees some 340 reflection sequences up to order
    4, one outside facing the box a few, one outside facing away none. With 16 slots per ping
    only the inside ping overflows, and it alone is traced again with larger tables: echoes and
    energyscapes equal those of the default table, in any batching, with no warning (but the one
    that says two poses lie outside the room)."""
    room = scenes.box_room(tuple(SIZE), wall="mirror", floor="mirror", ceiling="mirror")
    poses = np.stack(
        [scenes.pose(-1.0, 2.0, 0.0, 1.5), scenes.pose(0.5, 3.5, -0.8, 1.5), scenes.pose(-1.0, 2.0, np.pi, 1.5)]
    )
    small, large = (
        Sonar(OMNI, max_bounces=3, ray_count=5_000, table_size=t, scattering=False, device=device) for t in (16, 32768)
    )
    on_device = PosesOnDevice.upload(check_poses(poses), small.tracer.device)
    dropped = small.tracer._checked(small.tracer._queue_batch(room, on_device, np.arange(3), 16, None))
    assert dropped[0] == dropped[2] == 0 and dropped[1] > 0
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        warnings.filterwarnings("ignore", message=r"\d+ of \d+ poses .* lie behind")
        want, image = large.trace(room, poses), large.simulate(room, poses, absorption=False).energyscape
        for batch in (2, 3):
            got = small.trace(room, poses, batch=batch)
            np.testing.assert_array_equal(got.pose_index, want.pose_index)
            np.testing.assert_allclose(got.length_m, want.length_m, rtol=1e-6)
            np.testing.assert_allclose(got.amplitude, want.amplitude, rtol=1e-5)
            done = []  # pings reported finished, batch by batch (a retraced ping counts once)
            got_image = small.simulate(room, poses, batch=batch, absorption=False, on_pings=done.append).energyscape
            np.testing.assert_allclose(got_image, image, rtol=1e-4, atol=1e-6 * image.max())
            assert sum(done) == len(poses) and len(done) >= 2, done
    assert len(want.for_pose(0)) > 0 and len(want.for_pose(1)) > 16 and len(want.for_pose(2)) == 0


def echo_signal(arrivals, mic, samples, config):
    """One microphone's signal written directly from the echoes: each one the call (continuous in
    time, tests/test_record.py, looked up 32 times finer than a sample) scaled by its amplitude and
    delayed by (path to its source point + |source - mic|) / c. No absorption, no noise."""
    from tests.test_record import call_at

    fs, c = config.chirp.sample_rate_hz, config.atmosphere.speed_of_sound
    fine = np.arange(0.0, config.chirp.duration_s + 1 / fs, 1 / (32 * fs))
    call = call_at(fine)
    source = np.asarray(arrivals.source_m, dtype=np.float64)
    delay = (arrivals.length_m - np.linalg.norm(source, axis=1) + np.linalg.norm(source - mic, axis=1)) / c
    index = np.floor(delay * fs).astype(int)[:, None] + np.arange(config.chirp.sample_count + 2)
    keep = index < samples
    values = arrivals.amplitude[:, None] * np.interp(index / fs - delay[:, None], fine, call, left=0.0, right=0.0)
    return np.bincount(index[keep], weights=values[keep], minlength=samples)


def test_simulate_equals_trace_record_energyscape_step_by_step(device):
    """`simulate` (echoes, signals and images left on the device, batch after batch; the next
    batch is traced, into the other of two buffer sets, before this one is recorded; on a GPU the
    images come back on a side stream behind the next batch) gives the energyscapes of the
    host-side chain trace -> record -> energyscape, for 5 poses in batches of 2 (the last one
    short), with noise seeded per ping. Both share the recorder and the beamformer, so simulate's
    own output is also checked against references that share no code with them: with no noise
    and no absorption its signals are the traced echoes written directly (within 1 % of the peak,
    three microphones of pings 1 and 4), its energyscapes on a grid of baseband samples are a
    full-rate numpy matched filter, delay-and-sum and envelope of those signals (within 0.5 % of
    the peak), and the noise it adds has the standard deviation of each ping's peak 40 dB down,
    drawn afresh for every ping."""
    from tests.reference.beamform import full_rate_envelope

    room = scenes.box_room(tuple(SIZE))
    poses = np.stack([scenes.pose(1.0 + 0.8 * i, 2.0, 0.3 * i, 1.0) for i in range(5)])
    sonar = Sonar(OMNI, max_bounces=2, ray_count=3_000, device=device)
    want = sonar.energyscape(sonar.record(sonar.trace(room, poses), pose_count=5, noise="gaussian", seed=3))
    for batch in (2, 5):
        got = sonar.simulate(room, poses, batch=batch, noise="gaussian", seed=3).energyscape
        np.testing.assert_allclose(got, want, rtol=1e-4, atol=1e-5 * want.max())

    step = 343.0 * 8 / 450e3 / 2  # range between baseband samples (decimation 8, 343 m/s in processing)
    grid = sim.PolarGrid(range_min_m=99.5 * step, range_max_m=1499.5 * step, range_bin_m=step, azimuth_step_deg=5.0)
    processing = sim.ProcessingConfig(grid=grid, lowpass_hz=None)
    run = {"batch": 2, "absorption": False, "keep_signals": True, "processing": processing}
    clean = sonar.simulate(room, poses, **run)
    noisy = sonar.simulate(room, poses, noise="gaussian", snr_db=40.0, seed=3, **run)
    arrivals, mics = sonar.trace(room, poses), np.asarray(OMNI.microphones_m)
    samples = clean.signals.shape[2]
    for ping in (1, 4):  # the second of a batch, and the short last batch
        for m in (0, 13, 31):
            expected = echo_signal(arrivals.for_pose(ping), mics[m], samples, OMNI)
            assert np.abs(clean.signals[ping, m] - expected).max() < 0.01 * np.abs(expected).max(), (ping, m)
        call = OMNI.chirp.samples()
        full = full_rate_envelope(clean.signals[ping], mics, call, 450e3, grid.azimuth_rad, (20e3, 55e3))
        image = full[:, np.rint(grid.range_m / step).astype(int) * 8].T  # (R, A)
        assert np.abs(clean.energyscape[ping] - image).max() < 0.005 * image.max(), ping
    residual = (noisy.signals - clean.signals).astype(np.float64)
    peak = np.abs(clean.signals).max(axis=(1, 2))
    np.testing.assert_allclose(residual.std(axis=(1, 2)), peak * 10 ** (-40 / 20), rtol=0.02)
    correlation = np.corrcoef(residual.reshape(len(poses), -1))
    assert np.abs(correlation[~np.eye(len(poses), dtype=bool)]).max() < 0.01


def test_simulates_threads_start_with_its_device_current(device, monkeypatch):
    """Every thread `simulate` starts (recording and beamforming a batch's rows, and on a GPU
    moving images to the host) first makes the sonar's device current: a thread with no CUDA
    context made CUDA's runtime open one on GPU 0 for a process working on GPU 1. Those threads
    are kept for the next call from the same thread (starting one cost a worker ~2 ms an episode):
    a second call starts none, and its images are the first's."""
    import threading

    import acoustic_sim.engine.sonar as sonar_module

    made: list[tuple[str, str]] = []
    real = sonar_module.current_in_thread

    def record(where):
        made.append((threading.current_thread().name, str(where)))
        real(where)

    monkeypatch.setattr(sonar_module, "current_in_thread", record)
    sonar_module._batch_copies.cache_clear()  # a GPU's image mover and the recording threads, started afresh here
    sonar_module._recording_threads.cache_clear()
    room = scenes.box_room(tuple(SIZE))
    poses = np.stack([scenes.pose(1.0 + 0.3 * i, 2.0, 0.2 * i, 1.0) for i in range(3)])
    sonar = Sonar(OMNI, max_bounces=1, ray_count=300, device=device, cpu_threads=2)
    first = sonar.simulate(room, poses, batch=2, noise="gaussian", seed=1).energyscape
    assert made and {where for _, where in made} == {str(sonar.device)}
    assert threading.main_thread().name not in {name for name, _ in made}
    started = len(made)
    np.testing.assert_array_equal(sonar.simulate(room, poses, batch=2, noise="gaussian", seed=1).energyscape, first)
    assert len(made) == started


def _simulate_in_child(want: np.ndarray) -> None:
    sonar = Sonar(OMNI, max_bounces=1, ray_count=300, device="cpu", cpu_threads=2)
    got = sonar.simulate(scenes.box_room(tuple(SIZE)), np.stack([scenes.pose(1.0, 2.0, 0.0, 1.0)] * 2)).energyscape
    raise SystemExit(0 if np.array_equal(got, want) else 3)


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="forks (generate forks its workers on Linux)")
def test_a_forked_child_simulates_on_threads_of_its_own():
    """The recording threads simulate keeps are per process: a child forked after a simulate (as
    generate forks workers, and a worker its helpers) records on threads of its own and gives the
    parent's images. With the parent's pool (whose threads a child lacks) its simulate hung."""
    import multiprocessing

    from acoustic_sim.devices import cuda_started

    if cuda_started():
        pytest.skip("this process has started CUDA: a forked child of it cannot use Warp's runtime")
    sonar = Sonar(OMNI, max_bounces=1, ray_count=300, device="cpu", cpu_threads=2)
    want = sonar.simulate(scenes.box_room(tuple(SIZE)), np.stack([scenes.pose(1.0, 2.0, 0.0, 1.0)] * 2)).energyscape
    child = multiprocessing.get_context("fork").Process(target=_simulate_in_child, args=(want,))
    child.start()
    child.join(timeout=120)
    if child.is_alive():
        child.kill()
        child.join()
        pytest.fail("the forked child's simulate did not finish in 120 s")
    assert child.exitcode == 0


@pytest.mark.skipif(len(gpus().get("gpus", [])) < 2, reason="needs two GPUs (run on a lent two-GPU machine)")
def test_a_process_on_the_second_gpu_holds_no_context_on_the_first():
    """A process that simulates on cuda:1, as a generate worker does, holds no CUDA context on
    GPU 0 afterwards (nvidia-smi): one there cost each such worker 518 MiB and its first episode
    ~1.5 s on two H100s (benchmarks/results/multi_gpu/session37)."""
    import subprocess
    import sys

    script = (
        "import os, subprocess, numpy as np, warp as wp, scenes\n"
        "from acoustic_sim.engine.sonar import Sonar\n"
        "import acoustic_sim as sim\n"
        "room = scenes.box_room((6.0, 4.0, 3.0))\n"
        "poses = np.stack([scenes.pose(1.0 + 0.1 * i, 2.0, 0.0, 0.3) for i in range(20)])\n"
        "with wp.ScopedDevice('cuda:1'):\n"
        "    Sonar(sim.SonarConfig.ertis(), ray_count=2000, device='cuda:1').simulate(room, poses, noise='gaussian')\n"
        "ask = ['nvidia-smi', '--format=csv,noheader']\n"
        "gpu0 = subprocess.run([*ask, '--query-gpu=uuid', '-i', '0'], capture_output=True, text=True).stdout.strip()\n"
        "apps = subprocess.run([*ask, '--query-compute-apps=pid,gpu_uuid'], capture_output=True, text=True).stdout\n"
        "print('on GPU 0:', any(a.startswith(f'{os.getpid()},') and gpu0 in a for a in apps.splitlines()))\n"
    )
    done = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True, timeout=600, check=True)
    assert "on GPU 0: False" in done.stdout, done.stdout + done.stderr


def test_cpu_threads_split_a_batch_without_changing_a_sample(device):
    """On the CPU a batch's pings are traced, recorded and beamformed in threads (uneven slices
    of 5 pings over 3 threads, noise seeded per ping): arrivals, signals and energyscapes equal
    one thread's."""
    room = scenes.box_room(tuple(SIZE))
    poses = np.stack([scenes.pose(1.0 + 0.8 * i, 2.0, 0.2 * i, 1.0) for i in range(5)])
    sonars = [Sonar(OMNI, max_bounces=1, ray_count=2_000, device=device, cpu_threads=t) for t in (1, 3)]
    traced = [s.trace(room, poses) for s in sonars]
    for key, value in traced[0].__dict__.items():
        np.testing.assert_array_equal(value, getattr(traced[1], key), err_msg=key)
    runs = [s.simulate(room, poses, noise="gaussian", seed=4, keep_signals=True) for s in sonars]
    np.testing.assert_array_equal(runs[0].signals, runs[1].signals)
    np.testing.assert_array_equal(runs[0].energyscape, runs[1].energyscape)
    assert runs[0].energyscape.max() > 0
    with pytest.raises(ValueError, match="cpu_threads"):
        Sonar(OMNI, device=device, cpu_threads=0)


def test_generate_workers_share_the_cores(monkeypatch):
    """The default thread count is the process's cores, or the share `generate` gives each of its
    worker processes (SONAR2LIDAR_CPU_THREADS), so W workers do not start W x cores threads."""
    monkeypatch.setenv("SONAR2LIDAR_CPU_THREADS", "3")
    assert (
        Sonar(OMNI, device="cpu").cpu_threads == 3
        and sim.Lidar(sim.LidarConfig.hokuyo_ust20lx(), device="cpu").cpu_threads == 3
    )
    monkeypatch.delenv("SONAR2LIDAR_CPU_THREADS")
    assert Sonar(OMNI, device="cpu").cpu_threads == len(__import__("os").sched_getaffinity(0))


def test_an_omni_emitter_hears_every_image_source_of_pyroomacoustics(device):
    """pyroomacoustics' image sources (a peer engine; its sources are omnidirectional) in a
    6 x 4 x 3 m shoebox, energy absorption 0.1 on the walls, 0.3 on the floor, 0.5 on the
    ceiling, orders 1-3 (62 images, every one audible in a box): the tracer of an "omni" emitter
    finds each once, those leaving the emitter backwards included, the path length within 0.1 mm
    and the amplitude pyroomacoustics' damping (prod sqrt(1 - a)) over it; the baffled piston's
    tracer finds exactly the images whose path leaves forwards. The emitter sits 2 cm to the
    side as well as 5 cm above the array: straight above it, every path reflecting once off each
    of two adjoining walls runs exactly through the edge between them (an image source for
    pyroomacoustics, for rays a graze they may miss), and the pose avoids simple ratios to the
    room's sides for the same reason."""
    pra = pytest.importorskip("pyroomacoustics")
    pose = scenes.pose(2.13, 1.37, 0.4, 1.21)
    sphere, piston = (dataclasses.replace(c, emitter_m=(0.0, 0.02, 0.05)) for c in (SPHERE, OMNI))
    absorption = {"wall": 0.1, "floor": 0.3, "ceiling": 0.5}
    mats = {side: pra.Material(absorption["wall"]) for side in ("east", "west", "north", "south")}
    mats |= {side: pra.Material(absorption[side]) for side in ("floor", "ceiling")}
    emitter, receiver = emitter_and_receiver(pose, sphere)
    room = pra.ShoeBox(SIZE, fs=450000, max_order=3, materials=mats, air_absorption=False)
    room.add_source(emitter)
    room.add_microphone(receiver)
    room.image_source_model()
    theirs = room.sources[0]
    order = theirs.orders > 0
    images, damping = theirs.images.T[order], theirs.damping[0, order]
    lengths = np.linalg.norm(images - receiver, axis=1)
    leaving = (receiver - images) / lengths[:, None] * (-1.0) ** np.abs(theirs.orders_xyz.T[order])
    forwards = leaving @ pose[:3, 0] >= -1e-6  # the floor's and ceiling's own echoes leave in the baffle's plane

    def surface(name):
        return scenes.Material(
            name=name, acoustic_reflection=1.0 - absorption[name], acoustic_scattering=0.0, lidar_reflectivity=0.5
        )

    box = scenes.box_room(tuple(SIZE), wall=surface("wall"), floor=surface("floor"), ceiling=surface("ceiling"))
    for config, heard in ((sphere, np.ones(len(images), bool)), (piston, forwards)):
        got = Sonar(config, max_bounces=2, ray_count=40_000, scattering=False, device=device).trace(box, pose)
        expected = (images[heard] - receiver) @ pose[:3, :3]  # into the sensor frame
        gap = np.linalg.norm(got.source_m[:, None] - expected[None], axis=-1)
        assert len(got) == heard.sum() and len(set(gap.argmin(axis=1))) == len(got), (config.emitter_pattern, len(got))
        match = gap.argmin(axis=0)  # each image's arrival
        assert gap.min(axis=0).max() < 1e-4
        np.testing.assert_allclose(got.length_m[match], lengths[heard], atol=1e-4)
        np.testing.assert_allclose(got.amplitude[match] * got.length_m[match], damping[heard], rtol=1e-4)
    assert 0.3 < 1 - forwards.mean() < 0.7  # about half of them leave backwards


LOOKING_DOWN = np.array([[0.0, 0.0, 1.0], [0.0, 1.0, 0.0], [-1.0, 0.0, 0.0]])  # sensor x -> world -z
LOOKING_UP = np.array([[0.0, 0.0, -1.0], [0.0, 1.0, 0.0], [1.0, 0.0, 0.0]])  # sensor x -> world +z


@pytest.mark.parametrize(
    ("height", "pattern", "facing"), [(1.0, "piston", "down"), (2.0, "piston", "down"), (1.5, "omni", "up")]
)
def test_scattered_energy_from_a_lambertian_plane(device, height, pattern, facing):
    """Omnidirectional sonar `height` m above an infinite Lambertian floor (R = 1, s = 1): the
    scattered energy reaching it is the radiosity integral int cos^2(t) / (pi r^4) dA =
    1 / (2 h^2), echoes starting at 2 h / c; a vanishing piston facing the floor, or an "omni"
    emitter facing away from it (sent backwards: a baffled one hears nothing there)."""
    floor = trimesh_square(200.0)
    lambert = scenes.Material(name="lambert", acoustic_reflection=1.0, acoustic_scattering=1.0, lidar_reflectivity=0.5)
    scene = scenes.from_mesh(floor, material=lambert)
    pose = np.eye(4)
    pose[:3, :3] = LOOKING_DOWN if facing == "down" else LOOKING_UP
    pose[2, 3] = height
    config = sim.SonarConfig.ertis(emitter_radius_m=1e-6, emitter_m=(0.0, 0.0, 0.0), emitter_pattern=pattern)
    got = Sonar(config, max_bounces=0, ray_count=20_000, device=device).trace(scene, pose)
    if facing == "up":
        baffled = dataclasses.replace(config, emitter_pattern="piston")
        assert len(Sonar(baffled, max_bounces=0, ray_count=2_000, device=device).trace(scene, pose)) == 0
    assert np.all(got.kind == KIND_SCATTERED) and np.all(got.order == 1)
    assert np.sum(got.amplitude**2) == pytest.approx(1.0 / (2 * height**2), rel=2e-3)
    assert got.length_m.min() == pytest.approx(2 * height, abs=1e-3)


def trimesh_square(side: float):
    import trimesh

    half = side / 2
    vertices = [[-half, -half, 0.0], [half, -half, 0.0], [half, half, 0.0], [-half, half, 0.0]]
    return trimesh.Trimesh(vertices, [[0, 1, 2], [0, 2, 3]], process=False)


def test_scattering_switch_and_bounce_limit(device):
    """A painted box room: scattering off leaves only specular arrivals; max_bounces = 0 leaves only
    first-order arrivals of both kinds; more bounces add higher orders."""
    room = scenes.box_room(tuple(SIZE))
    off = Sonar(OMNI, max_bounces=2, scattering=False, device=device).trace(room, POSE)
    assert np.all(off.kind == KIND_SPECULAR)
    first = Sonar(OMNI, max_bounces=0, device=device).trace(room, POSE)
    assert set(first.kind) == {KIND_SPECULAR, KIND_SCATTERED} and np.all(first.order == 1)
    more = Sonar(OMNI, max_bounces=2, device=device).trace(room, POSE)
    assert more.order.max() == 3 and np.sum(more.kind == KIND_SCATTERED) > np.sum(first.kind == KIND_SCATTERED)


def test_bad_arguments():
    with pytest.raises(ValueError, match="max_bounces"):
        Sonar(OMNI, max_bounces=11)
    with pytest.raises(ValueError, match="power of two"):
        Sonar(OMNI, table_size=1000)


def edge_box_scene():
    """A 0.5 x 0.5 x 1 m mirror box turned 45 deg, its front vertical edge 2 m ahead of the sensor
    at (0, 0, 0.3): no face sends a specular echo back, only its edges can."""
    center = (2.0 + 0.25 * np.sqrt(2.0), 0.0, 0.5)
    return assemble([(box_mesh(center, (0.5, 0.5, 1.0), np.pi / 4), "mirror")], name="edge_box")


def test_edges_echo_only_through_scattering(device):
    """Mirror box corner-on: no arrivals without scattering or with a zero edge band; with the
    default half-wavelength band, echoes come from within that band of the box's edges, and the
    energyscape peaks at the front edge (2 m, 0 deg) within a range bin and 2 deg."""
    scene = edge_box_scene()
    pose = scenes.pose(0.0, 0.0, 0.0, 0.3)
    config = sim.SonarConfig.ertis()
    assert len(Sonar(config, max_bounces=1, scattering=False, device=device).trace(scene, pose)) == 0
    assert len(Sonar(config, max_bounces=1, edge_width_m=0.0, device=device).trace(scene, pose)) == 0
    sonar = Sonar(config, max_bounces=1, ray_count=50_000, device=device)
    got = sonar.trace(scene, pose)
    assert len(got) > 10 and np.all(got.kind == KIND_SCATTERED)
    world = got.point_m @ pose[:3, :3].T + pose[:3, 3]
    corners = scene.mesh.vertices[scene.mesh.edges_unique]  # (E, 2, 3) box edges and face diagonals
    a, ab = corners[:, 0], corners[:, 1] - corners[:, 0]
    t = np.clip(np.einsum("pec,ec->pe", world[:, None] - a[None], ab) / np.einsum("ec,ec->e", ab, ab), 0, 1)
    gap = np.linalg.norm(world[:, None] - (a[None] + t[..., None] * ab[None]), axis=-1)
    length2 = np.einsum("ec,ec->e", ab, ab)
    sharp = np.isclose(length2, 0.25) | np.isclose(length2, 1.0)  # the 12 box edges, not face diagonals
    assert gap[:, sharp].min(axis=1).max() <= sonar.edge_width_m + 1e-3
    image = sonar.energyscape(sonar.record(got, pose_count=1))[0]
    grid = sim.PolarGrid()
    i, j = np.unravel_index(np.argmax(image), image.shape)
    assert abs(grid.range_m[i] - 2.0) <= grid.range_bin_m and abs(np.rad2deg(grid.azimuth_rad[j])) <= 2.0


@pytest.mark.parametrize("x, y, yaw", [(1.0, 3.5, -0.6), (4.5, 1.0, 2.6), (1.5, 1.0, 0.2)])
def test_specular_paths_in_an_l_shaped_room_equal_image_sources(device, x, y, yaw):
    """L-shaped mirror room (6 x 5 m minus a 3 x 3 m notch, 3 m high), sensor at 1.2 m in either
    arm or at the bend: the specular paths up to order 3 equal a float64 image-source method with
    polygon and occlusion checks (tests/reference/image_sources.py), one for one, lengths within
    1e-4 m. Corner paths count once, and only in inside corners; the notch occludes."""
    import trimesh

    from .reference.image_sources import l_room, planes_mesh, specular_paths

    planes = l_room(3.0)
    scene = scenes.from_mesh(trimesh.Trimesh(*planes_mesh(planes), process=False), material="mirror")
    pose = scenes.pose(x, y, yaw, 1.2)
    emitter, receiver = emitter_and_receiver(pose, OMNI)
    forwards = lambda d: (pose[:3, :3].T @ d)[0] >= -1e-6  # noqa: E731 - baffled emitter
    reference = specular_paths(planes, emitter, receiver, 3, leaves=forwards)
    got = Sonar(OMNI, max_bounces=2, ray_count=50_000, scattering=False, device=device).trace(scene, pose)
    got = got.for_pose(0)
    assert len(got) == len(reference), (
        f"found {np.bincount(got.order)}, expected {np.bincount([r[1] for r in reference])}"
    )
    ref_lengths = np.array([r[0] for r in reference])
    order = np.lexsort((got.order, np.round(got.length_m, 4)))
    np.testing.assert_allclose(got.length_m[order], ref_lengths, atol=1e-4)
    np.testing.assert_array_equal(got.order[order], [r[1] for r in reference])
    if (x, y) == (1.0, 3.5):  # in the upper arm the notch hides the far wall x = 6 m (echo at 10 m)
        assert np.min(np.abs(got.length_m[got.order == 1] - 10.0)) > 0.1


@wp.kernel(enable_backward=False)
def _claim_and_count(
    rows: wp.array[wp.int32], counts: wp.array[wp.int32], owner: wp.array2d[wp.int32], sums: wp.array[wp.int32]
):
    tid = wp.tid()
    i = rows[tid]
    if tid % 3 != 0:  # a diverged warp: only some lanes claim
        owner[i, claim_slot(counts, i)] = tid
    add_count(sums, i, tid % 7)


def test_per_ping_counters_give_every_thread_its_own_slot(device):
    """`claim_slot` and `add_count` (on GPUs one atomic per warp for the lanes of one row) against
    per-thread arithmetic: 5,000 threads over 5 rows in runs of 37 and some scattered threads (so
    warps mix rows), two in three of them claiming: every claimant gets a slot of its row, none
    twice, no slot left empty, and the counts and sums are numpy's. Fails if the leader's
    atomic adds one per warp or lanes take the leader's slot."""
    n = 5000
    rows = (np.arange(n) // 37) % 5
    rows[::11] = np.random.default_rng(1).integers(0, 5, len(rows[::11]))
    with wp.ScopedDevice(device):
        counts, sums = wp.zeros(5, dtype=wp.int32), wp.zeros(5, dtype=wp.int32)
        owner = wp.full((5, n), -1, dtype=wp.int32)
        wp.launch(_claim_and_count, dim=n, inputs=[wp.array(rows.astype(np.int32)), counts, owner, sums])
    claim = np.arange(n) % 3 != 0
    np.testing.assert_array_equal(counts.numpy(), np.bincount(rows[claim], minlength=5))
    np.testing.assert_array_equal(sums.numpy(), np.bincount(rows, weights=np.arange(n) % 7, minlength=5))
    got = owner.numpy()
    for i in range(5):
        filled = got[i][got[i] >= 0]
        assert len(filled) == counts.numpy()[i] and (got[i][: len(filled)] >= 0).all()
        np.testing.assert_array_equal(np.sort(filled), np.flatnonzero(claim & (rows == i)))


@wp.kernel(enable_backward=False)
def _image_keys(order: int, images: wp.array[wp.vec3], keys: wp.array[wp.uint64]):
    i = wp.tid()
    keys[i] = image_key(order, images[i])


def test_distinct_image_sources_get_distinct_keys(device):
    """`image_key` (a ping's image sources are told apart by it): 4,000 random image sources
    within 20 m, each with its seven copies mirrored through the sensor's axes and planes and its
    five permutations, all of one order, all get distinct keys; a copy moved by less than half a
    cell of IMAGE_GRID gets its original's. With FNV's xor-and-multiply on whole words, (x, y, z)
    and (-x, -y, z) shared a key a quarter of the time (found by the omni emitter's test against
    pyroomacoustics)."""
    rng = np.random.default_rng(3)
    base = rng.uniform(-20.0, 20.0, (4000, 3))
    signs = np.array(list(itertools.product((1, -1), repeat=3)))
    copies = [base * s for s in signs] + [base[:, list(p)] for p in itertools.permutations(range(3))][1:]
    images = np.concatenate(copies)
    images = np.round(images / 1e-4) * 1e-4  # cell centres: the rounding changes half a cell away
    nudged = images + rng.uniform(-2e-5, 2e-5, images.shape)
    with wp.ScopedDevice(device):
        keys = [wp.zeros(len(images), dtype=wp.uint64) for _ in range(2)]
        for points, out in zip((images, nudged), keys, strict=True):
            wp.launch(_image_keys, dim=len(points), inputs=[3, wp.array(points.astype(np.float32), dtype=wp.vec3), out])
    first, second = (k.numpy() for k in keys)
    assert len(np.unique(first)) == len(first)
    np.testing.assert_array_equal(first, second)
