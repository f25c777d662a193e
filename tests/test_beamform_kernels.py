"""Beamformer kernels: scratch arrays need no zero fill; the GPU's envelope kernel gives the CPU's bits."""

import numpy as np
import warp as wp

import acoustic_sim as sim
import acoustic_sim.engine.beamform as beamform
from acoustic_sim.engine.kernels import beamform as kernels

CONFIG = sim.SonarConfig.ertis()


def test_energyscape_does_not_depend_on_what_scratch_memory_held(device, monkeypatch):
    """Energyscapes (E = 1 and 3) are the same bits when every array the beamformer takes with
    `empty` starts out NaN: the beamform kernel writes the bins off the band too (zeros), so the
    inverse FFT never reads stale memory (a GPU's memory pool hands back used blocks). Fails if
    one off-band bin is left unwritten."""
    ping = (
        0.01 * np.random.default_rng(1).standard_normal((1, CONFIG.microphone_count, CONFIG.record_samples))
    ).astype(np.float32)
    clean = [beamform.energyscape(ping, CONFIG, elevation_deg=e, device=device) for e in (0.0, (-15.0, 0.0, 15.0))]
    calls = beamform.device_calls

    def nan_filled(target):
        zeros, empty, launch, launch_tiled = calls(target)

        def empty_nan(shape, dtype):
            out = empty(shape, dtype=dtype)
            out.fill_(dtype(np.nan, np.nan) if dtype == wp.vec2f else np.nan)
            return out

        return zeros, empty_nan, launch, launch_tiled

    monkeypatch.setattr(beamform, "device_calls", nan_filled)
    for want, elevation in zip(clean, (0.0, (-15.0, 0.0, 15.0)), strict=True):
        got = beamform.energyscape(ping, CONFIG, elevation_deg=elevation, device=device)
        assert np.isfinite(got).all() and np.array_equal(got, want)


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
