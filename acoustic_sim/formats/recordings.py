"""Recordings of real sensors into our processing: raw eRTIS PDM streams -> energyscapes.

    python -m acoustic_sim import ping-*.bin --format pdm --out rec.npy

Each file is one measurement (or `samples_per_ping` words split a long stream into pings, in
time order). The PDM is decoded by `signals.pdm_to_pcm`, and the PCM goes through the same
`beamform.energyscape` as our simulated pings, with the rig's array geometry, call and grid
(`--set sonar...` for another sensor or call). Time zero of a measurement is taken as the start
of the call, as the eRTIS records. Writes the energyscapes (N, R, A) float32 ((N, E, R, A) for
several elevations) to `out`, a picture of the first pings beside it (.png) and what was done
(.json), so `learn predict --input rec.npy` can take them.
"""

from __future__ import annotations

import json
import math
import time
from pathlib import Path

import numpy as np

from clitools.limits import check_fits, check_memory, format_bytes, free_disk_bytes, input_file

from ..config import level_index
from ..engine.signals import pdm_to_pcm

PDM_DECODE_BYTES_PER_BYTE = 64  # a ping being decoded: its bits unpacked, as +-1, filtered (per byte of PDM)


def check_pdm_files(paths: list[str | Path], *, channels: int, samples_per_ping: int | None, rig, out: Path) -> None:
    """Refuse, by `stat` before any is opened, files that are not regular (a FIFO would never end)
    and recordings whose words, decoding and energyscapes this machine's memory (or the disk of
    `out`) cannot hold."""
    sizes = [input_file(path, what="PDM recording", max_bytes=math.inf).stat().st_size for path in paths]
    words = sum(size // max(channels // 8, 1) for size in sizes)
    pings = len(paths) if samples_per_ping is None else max(words // max(samples_per_ping, 1), 1)
    image = 4 * rig.processing.grid.range_count * rig.processing.grid.azimuth_count  # float32 energyscape
    what = f"{len(paths)} PDM file(s) of {format_bytes(sum(sizes))} ({pings:,} ping(s))"
    check_memory(
        sum(sizes) + PDM_DECODE_BYTES_PER_BYTE * max(sizes) + pings * image,
        what=what,
        advice="import fewer files at a time",
    )
    check_fits(
        pings * image,
        available=free_disk_bytes(out),
        what=what,
        room=f"free on the disk of {out}",
        advice="give another --out",
    )


def check_decoding(*, channels: int, pdm_rate_hz: float, samples_per_ping: int | None) -> None:
    """Refuse decoding options no stream has, naming the option: a channel count that is not a
    positive multiple of 8 (a word holds one bit per channel), a PDM rate that is not a positive
    finite number of Hz, a ping of fewer than one word."""
    if channels < 8 or channels % 8:
        raise ValueError(f"--channels {channels}: a PDM word holds one bit per channel; give a positive multiple of 8")
    if not (math.isfinite(pdm_rate_hz) and pdm_rate_hz > 0):
        raise ValueError(f"--pdm-rate {pdm_rate_hz}: give the PDM sample rate, a positive number of Hz (4.5e6)")
    if samples_per_ping is not None and samples_per_ping < 1:
        raise ValueError(f"--samples-per-ping {samples_per_ping}: give a positive number of words per ping")


def read_pdm_pings(paths: list[str | Path], *, channels: int, samples_per_ping: int | None) -> list[np.ndarray]:
    """Raw words of every ping: each file is one ping, or pings of `samples_per_ping` words each."""
    width = channels // 8
    pings = []
    for path in map(Path, paths):
        raw = np.fromfile(path, dtype=np.uint8)
        if raw.size == 0 or raw.size % width:
            raise ValueError(f"{path}: {raw.size} bytes are not whole words of {channels} bits")
        words = raw.reshape(-1, width)
        if samples_per_ping is None:
            pings.append(words)
            continue
        if len(words) % samples_per_ping:
            raise ValueError(f"{path}: {len(words)} words are not whole pings of --samples-per-ping {samples_per_ping}")
        pings += list(words.reshape(-1, samples_per_ping, width))
    lengths = {len(p) for p in pings}
    if len(lengths) > 1:
        raise ValueError(f"pings differ in length ({sorted(lengths)} words): give files of one recording setting")
    return pings


def import_pdm(
    paths: list[str | Path],
    out: str | Path,
    rig,
    *,
    channels: int = 32,
    pdm_rate_hz: float = 4.5e6,
    bit_order: str = "lsb",
    samples_per_ping: int | None = None,
    device: str = "cpu",
) -> dict:
    """Decode raw PDM pings and process them into energyscapes; returns what was written."""
    from ..engine.beamform import energyscape
    from ..render import render_examples

    t0, out = time.perf_counter(), Path(out)
    if out.suffix != ".npy":
        raise ValueError(f"--out names the energyscapes file (.npy), got {out}")
    check_decoding(channels=channels, pdm_rate_hz=pdm_rate_hz, samples_per_ping=samples_per_ping)
    sonar, processing = rig.sonar, rig.processing
    if channels != sonar.microphone_count:
        raise ValueError(
            f"the stream has {channels} channels but the array has {sonar.microphone_count} microphones "
            "(set --channels, or the array with --set sonar.microphones_m=...)"
        )
    decimation = pdm_rate_hz / sonar.chirp.sample_rate_hz
    if abs(decimation - round(decimation)) > 1e-9 or round(decimation) < 1:
        raise ValueError(
            f"the PDM rate {pdm_rate_hz:.0f} Hz is not a whole multiple of the call's sample rate "
            f"{sonar.chirp.sample_rate_hz:.0f} Hz (sonar.chirp.sample_rate_hz)"
        )
    check_pdm_files(paths, channels=channels, samples_per_ping=samples_per_ping, rig=rig, out=out)
    pings = read_pdm_pings(paths, channels=channels, samples_per_ping=samples_per_ping)
    decode = dict(channels=channels, pdm_rate_hz=pdm_rate_hz, decimation=round(decimation), bit_order=bit_order)
    pcm = np.stack([pdm_to_pcm(p, **decode) for p in pings])  # (N, channels, samples)
    energy = energyscape(pcm, sonar, processing, device=device)
    out.parent.mkdir(parents=True, exist_ok=True)
    np.save(out, energy)
    grid, elevations = processing.grid, processing.elevations_deg
    level = level_index(elevations)  # (pings, E, R, A) for several elevations: draw the level one
    images = energy if energy.ndim == 3 else energy[:, level]
    at = "" if energy.ndim == 3 else f" at {elevations[level]:g} deg"
    shown = [(f"ping {i}{at}", images[i], None) for i in range(min(3, len(energy)))]
    picture = render_examples(shown, grid, out.with_suffix(".png"))
    dims = "(pings, range, azimuth)" if energy.ndim == 3 else "(pings, elevation, range, azimuth)"
    record = {
        "what": f"energyscapes {dims} of a raw PDM recording, processed by acoustic_sim",
        "elevation_deg": list(elevations),
        "files": [str(p) for p in paths],
        "pings": len(energy),
        "decode": decode | {"samples_per_ping": samples_per_ping, "pcm_rate_hz": sonar.chirp.sample_rate_hz},
        "range_m": [float(grid.range_min_m), float(grid.range_max_m), len(grid.range_m)],
        "azimuth_deg": [float(grid.azimuth_min_deg), float(grid.azimuth_max_deg), len(grid.azimuth_rad)],
        "rig": rig.to_dict(),
        "seconds": time.perf_counter() - t0,
    }
    out.with_suffix(".json").write_text(json.dumps(record, indent=1, default=str))
    return {"out": str(out), "picture": str(picture), "pings": len(energy), "seconds": record["seconds"]}
