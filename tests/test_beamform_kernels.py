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
