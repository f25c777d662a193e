"""The PDM decoder against a known call put through an independent sigma-delta modulator."""

import numpy as np
import pytest
from scipy.signal import resample_poly

from acoustic_sim.config import ChirpConfig
from acoustic_sim.engine.signals import pdm_to_pcm

FS = 450_000  # PCM rate; the PDM stream runs 10 times faster, as the eRTIS's 4.5 MHz


def sigma_delta(x: np.ndarray) -> np.ndarray:
    """Second-order modulator (two integrators, the 1-bit output fed back to both; quantisation
    noise shaped by (1 - z^-1)^2 away from the audio band): (C, S) in [-1, 1] -> bits (C, S)."""
    i1, i2, v = (np.zeros(len(x)) for _ in range(3))
    bits = np.empty(x.shape, dtype=np.uint8)
    for n in range(x.shape[1]):
        i1 = i1 + x[:, n] - v
        i2 = i2 + i1 - v
        v = np.where(i2 >= 0, 1.0, -1.0)
        bits[:, n] = v > 0
    return bits


@pytest.fixture(scope="module")
def recording():
    """32 channels, each the 25-80 kHz call at its own delay and level, as PCM and as PDM words."""
    call = ChirpConfig.band_25_80khz().samples()
    pcm = np.zeros((32, 1800))
    for c in range(32):
        pcm[c, 40 + 17 * c : 40 + 17 * c + len(call)] = (0.5 - 0.01 * c) * call / np.abs(call).max()
    bits = sigma_delta(resample_poly(pcm, 10, 1, axis=1))  # band-limited upsampling to 4.5 MHz
    return pcm, bits


def words(bits: np.ndarray, order: str) -> np.ndarray:
    rows = bits.T if order == "lsb" else bits[::-1].T  # bit i of a word is channel i, or channel 31 - i
    return np.ascontiguousarray(np.packbits(rows, axis=1, bitorder="little")).view("<u4")[:, 0]


def test_pdm_decodes_a_sigma_delta_modulated_call(recording):
    """Every channel of the call comes back within 2 % RMS of its level (measured: <= 1.0 %), in time."""
    pcm, bits = recording
    decoded = pdm_to_pcm(words(bits, "lsb"), pdm_rate_hz=10 * FS)
    assert decoded.shape == pcm.shape and decoded.dtype == np.float32
    error = np.sqrt(((decoded - pcm) ** 2).mean(axis=1) / (pcm**2).mean(axis=1))
    assert error.max() < 0.02
    # The same stream as bytes, as big-endian words and in the other bit order decodes alike.
    same = words(bits, "lsb")
    assert np.array_equal(pdm_to_pcm(same.view(np.uint8), pdm_rate_hz=10 * FS), decoded)
    assert np.array_equal(pdm_to_pcm(same.astype(">u4"), pdm_rate_hz=10 * FS), decoded)
    assert np.array_equal(pdm_to_pcm(words(bits, "msb"), pdm_rate_hz=10 * FS, bit_order="msb"), decoded)
    # Read in the wrong bit order, channels are swapped: the check above can fail.
    swapped = pdm_to_pcm(words(bits, "msb"), pdm_rate_hz=10 * FS)
    assert np.sqrt(((swapped - pcm) ** 2).mean() / (pcm**2).mean()) > 0.5


@pytest.mark.parametrize(
    "raw, options, message",
    [
        (np.zeros(10, dtype=np.int32), {}, "unsigned integers"),
        (np.zeros(10, dtype=np.uint32), {"channels": 12}, "multiple of 8"),
        (np.zeros(10, dtype=np.uint8), {}, "not whole words"),
        (np.zeros(10, dtype=np.uint32), {"bit_order": "big"}, "bit_order"),
        (np.zeros(10, dtype=np.uint32), {"cutoff_hz": 300e3}, "Nyquist"),
        (np.zeros(10, dtype=np.uint32), {"taps": 500}, "taps must be odd"),
    ],
)
def test_pdm_refuses_what_it_cannot_decode(raw, options, message):
    with pytest.raises(ValueError, match=message):
        pdm_to_pcm(raw, **options)


def test_import_pdm_images_point_reflectors_where_they_are(tmp_path, device):
    """Two pings of point reflectors (2 m at 30 deg, 3 m at -45 deg) recorded by our array, put
    through the sigma-delta modulator as the eRTIS streams them and written as raw files: `import
    --format pdm` peaks within a range bin and 2 deg of each reflector, and matches the energyscape
    of the PCM signals themselves."""
    import json

    import acoustic_sim as sim
    from acoustic_sim.cli import main
    from acoustic_sim.engine.beamform import energyscape
    from acoustic_sim.engine.signals import record
    from tests.test_beamform import reflectors

    config = sim.SonarConfig.ertis()
    signals = record(reflectors([2.0, 3.0], [30.0, -45.0]), config, noise="gaussian", snr_db=40.0, device=device)
    signals = 0.5 * signals / np.abs(signals).max()
    files = []
    for i, ping in enumerate(signals):
        files.append(tmp_path / f"ping-{i}.bin")
        words(sigma_delta(resample_poly(ping, 10, 1, axis=1)), "lsb").tofile(files[-1])
    out = tmp_path / "rec.npy"
    assert main(["import", *map(str, files), "--format", "pdm", "--out", str(out), "--device", device]) == 0
    images, grid = np.load(out), sim.PolarGrid()
    assert images.shape == (2, len(grid.range_m), len(grid.azimuth_rad))
    for image, r, az in zip(images, [2.0, 3.0], [30.0, -45.0], strict=True):
        i, j = np.unravel_index(np.argmax(image), image.shape)
        assert abs(grid.range_m[i] - r) <= grid.range_bin_m and abs(np.rad2deg(grid.azimuth_rad[j]) - az) <= 2.0
    direct = energyscape(signals, config)
    for a, b in zip(images, direct, strict=True):
        assert np.corrcoef(a.ravel(), b.ravel())[0, 1] > 0.99
    record_ = json.loads(out.with_suffix(".json").read_text())
    assert record_["pings"] == 2 and record_["decode"]["decimation"] == 10 and out.with_suffix(".png").exists()
    # Several elevations: (pings, E, R, A), its level slice the planar import's, its picture drawn
    three = tmp_path / "rec3.npy"
    command = ["import", *map(str, files), "--format", "pdm", "--out", str(three), "--device", device]
    assert main([*command, "--set", "processing.elevation_deg=[-20,0,20]"]) == 0
    stack = np.load(three)
    assert stack.shape == (2, 3, *images.shape[1:]) and three.with_suffix(".png").exists()
    np.testing.assert_array_equal(stack[:, 1], images)
    assert json.loads(three.with_suffix(".json").read_text())["elevation_deg"] == [-20.0, 0.0, 20.0]
    # A stream whose words do not fill the array's channels, or a rate that is no multiple of 450 kHz.
    assert main(["import", str(files[0]), "--format", "pdm", "--out", str(out), "--channels", "16"]) == 2
    assert main(["import", str(files[0]), "--format", "pdm", "--out", str(out), "--pdm-rate", "4e6"]) == 2
