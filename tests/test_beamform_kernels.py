"""Beamformer kernels: the GPU's envelope kernel gives the CPU's bits."""

import numpy as np
import pytest
import warp as wp

import acoustic_sim as sim
import acoustic_sim.engine.beamform as beamform
from acoustic_sim.engine.kernels import beamform as kernels

CONFIG = sim.SonarConfig.ertis()


@pytest.mark.skipif(not wp.is_cpu_available(), reason="this Warp build compiles no CPU kernels (a GPU-only bundle)")
def test_gpu_envelope_kernel_gives_the_cpu_kernels_bits():
    """`envelope_rows` (GPUs: a block per beam row, the row in shared memory) and
    `envelope_on_grid` (the CPU's) give the same bits for 2 pings x 2 elevations x 7 azimuths of
    random envelopes on the default range grid, run on the CPU in one thread (each block's
    range bins in turn); every range bin, the low-pass and the samples past `valid` in play.
    Fails if the tiled kernel drops the FIR's last tap."""
    former = beamform.beamformer(CONFIG, samples=CONFIG.record_samples, device="cpu")
    pings, elevations, azimuths, valid = 2, 2, 7, former.baseband_samples
    rng = np.random.default_rng(3)
    rows = rng.random((pings * elevations * azimuths, former.size), dtype=np.float32)
    ranges = former.grid.range_m.copy()
    ranges[-1] = (valid - 3) / former._samples_per_m  # a window that runs past the valid samples
    inputs = [
        wp.array(rows, dtype=float, device="cpu"),
        valid,
        former._lowpass,
        wp.array(ranges.astype(np.float32), dtype=float, device="cpu"),
        former._samples_per_m,
    ]
    shape = (pings * elevations, len(ranges), azimuths)
    want = wp.zeros(shape, dtype=float, device="cpu")
    wp.launch(
        kernels.envelope_on_grid,
        dim=(shape[0], shape[2], shape[1]),
        inputs=[*inputs, elevations],
        outputs=[want],
        device="cpu",
    )
    got = wp.zeros(shape, dtype=float, device="cpu")
    wp.launch_tiled(
        kernels.envelope_rows(valid),
        dim=[shape[0] * shape[2]],
        inputs=inputs,
        outputs=[got],
        block_dim=beamform.ENVELOPE_BLOCK_DIM,
        device="cpu",
    )
    assert np.all(want.numpy() > 0)
    assert np.array_equal(got.numpy(), want.numpy())


@pytest.mark.skipif(not wp.is_cpu_available(), reason="this Warp build compiles no CPU kernels (a GPU-only bundle)")
def test_gpu_delay_and_sum_kernel_gives_the_cpu_kernels_beams():
    """`delay_and_sum_tiles` (GPUs: a block per tile of band bins and 8 looks, the pings' spectra
    staged in shared memory 4 at a time) and `delay_and_sum` (the CPU's: a thread per look and
    bin) give the same beams for 6 pings (a last stage of 2) of random spectra, every band bin and
    look of 3 elevations (543 looks: a last block of 7), run on the CPU in one thread; the bins
    off the band stay untouched. Fails if a tile drops its last bin, a stage its last ping or
    the block its last look."""
    former = beamform.beamformer(
        CONFIG, samples=CONFIG.record_samples, device="cpu", processing=sim.ProcessingConfig(elevation_deg=(-20, 0, 20))
    )
    pings, mics, looks = 6, CONFIG.microphone_count, former._looks
    assert looks % beamform.LOOKS_PER_BLOCK and pings % kernels.STAGE_PINGS
    column, _, width = (t.numpy() for t in former._band_tiles)
    assert len(set(width)) > 1 and np.diff(column).max() > kernels.TILE_BINS  # partial tiles, two runs
    rng = np.random.default_rng(4)
    spectra = wp.array(rng.standard_normal((pings * mics, former.size, 2), dtype=np.float32), dtype=wp.vec2f)
    steering = [former._band_hz, former._matched, former._delays, pings]
    want = wp.zeros((pings * looks, former.size), dtype=wp.vec2f, device="cpu")
    wp.launch(
        former._beamform,
        dim=(looks, former._band_bin.shape[0]),
        inputs=[spectra, former._band_bin, *steering],
        outputs=[want],
        device="cpu",
    )
    got = wp.zeros_like(want)
    blocks, wp.config.enable_cpu_blocks = wp.config.enable_cpu_blocks, True
    try:
        wp.launch_tiled(
            kernels.delay_and_sum_tiles(mics, beamform.LOOKS_PER_BLOCK),
            dim=[len(column), -(-looks // beamform.LOOKS_PER_BLOCK)],
            inputs=[spectra, *former._band_tiles, *steering],
            outputs=[got],
            block_dim=kernels.TILE_BINS * beamform.LOOKS_PER_BLOCK,
            device="cpu",
        )
    finally:
        wp.config.enable_cpu_blocks = blocks
    want, got = want.numpy(), got.numpy()
    band = former._band_bin.numpy()
    assert np.abs(want[:, band]).min() > 0 and not np.delete(got, band, axis=1).any()
    np.testing.assert_allclose(got, want, rtol=0, atol=1e-6 * np.abs(want).max())


def test_float16_conversion_is_numpys(device):
    """`to_float16` rounds like numpy's float32 -> float16 cast, bit for bit: ties to even,
    subnormals, the largest half, overflow to inf, signed zeros, on 200,000 random values over
    the half range and the edge cases."""
    rng = np.random.default_rng(9)
    values = np.concatenate(
        [
            rng.standard_normal(100_000) * 10.0 ** rng.uniform(-9, 5, 100_000),
            np.float16(rng.standard_normal(100_000)).astype(np.float32) * (1 + 2.0**-11),  # halfway cases
            [65504.0, 65520.0, 1e6, -1e6, 6e-8, 3e-8, 2.9e-8, 0.0, -0.0, 1.0 + 2.0**-11, 1.0 + 3 * 2.0**-11],
        ]
    ).astype(np.float32)
    with wp.ScopedDevice(device):
        halves = wp.empty(len(values), dtype=wp.float16)
        wp.launch(kernels.to_float16, dim=len(values), inputs=[wp.array(values, dtype=float)], outputs=[halves])
    np.testing.assert_array_equal(halves.numpy().view(np.uint16), values.astype(np.float16).view(np.uint16))


def test_float16_energyscapes_are_the_float32_ones_rounded(device):
    """`Sonar.simulate(dtype=float16)` (on a GPU converted there before the copy) gives the float32
    energyscapes as numpy rounds them, for 3 pings in a box room with noise."""
    import scenes

    sonar = sim.Sonar(CONFIG, max_bounces=1, ray_count=2000, device=device)
    poses = np.stack([scenes.pose(1.5 + 0.5 * i, 1.5, 0.3, 0.4 * i) for i in range(3)])
    room = scenes.box_room(size=(4.0, 3.0, 2.5))
    full = sonar.simulate(room, poses, noise="gaussian", seed=2).energyscape
    half = sonar.simulate(room, poses, noise="gaussian", seed=2, dtype=np.float16).energyscape
    assert half.dtype == np.float16 and full.dtype == np.float32
    np.testing.assert_array_equal(half.view(np.uint16), full.astype(np.float16).view(np.uint16))
    with pytest.raises(ValueError, match="float32 or float16"):
        sonar.simulate(room, poses, dtype=np.float64)


def test_float16_energyscapes_convert_on_the_sonars_device_not_the_default(device):
    """The float16 conversion once ran on Warp's default device: a sonar on a second GPU made an
    illegal memory access (generate --device auto on two GPUs). With the default set to the CPU,
    a GPU sonar's float16 energyscapes are still its float32 ones rounded."""
    import scenes

    if not device.startswith("cuda"):
        pytest.skip("needs a CUDA device, to set the default to another one (the CPU)")
    sonar = sim.Sonar(CONFIG, max_bounces=1, ray_count=2000, device=device)
    poses = np.stack([scenes.pose(1.5 + 0.5 * i, 1.5, 0.3, 0.4 * i) for i in range(3)])
    room = scenes.box_room(size=(4.0, 3.0, 2.5))
    full = sonar.simulate(room, poses, seed=2).energyscape
    with wp.ScopedDevice("cpu"):
        half = sonar.simulate(room, poses, seed=2, dtype=np.float16).energyscape
    np.testing.assert_array_equal(half.view(np.uint16), full.astype(np.float16).view(np.uint16))
