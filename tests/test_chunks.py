"""Chunks compressed in threads (acoustic_sim.datasets.chunks) against HDF5's own filter pipeline: the
checksum HDF5 stores, the data h5py reads back (and verifies), refusals for what is not handled."""

import subprocess
import sys
import zlib

import h5py
import numpy as np
import pytest
from isal import isal_zlib

from acoustic_sim.datasets.chunks import deflate_planes, encode, fletcher32, pipeline, write_rows
from acoustic_sim.datasets.shards import COMPRESSION


@pytest.mark.parametrize(
    "raw",
    [
        bytes(range(7)),  # an odd byte count
        np.random.default_rng(0).integers(0, 256, 720).astype(np.uint8).tobytes(),  # exactly one block of words
        np.random.default_rng(1).integers(0, 256, 5001).astype(np.uint8).tobytes(),  # blocks and a rest, odd
        b"\xff" * 4000,  # the largest words: the sums wrap and fold
        b"\x00" * 999,  # zero sums
        b"\xff\xff" + b"\x00" * 1000,  # sums that are multiples of 65535
        np.random.default_rng(2).integers(0, 256, 60001).astype(np.uint8).tobytes(),  # several pieces, odd
    ],
    ids=["odd", "one-block", "many-blocks", "all-ones", "zeros", "65535", "pieces"],
)
def test_fletcher32_is_the_checksum_hdf5_stores(tmp_path, raw):
    """HDF5 appends its Fletcher-32 (little-endian) to each chunk it stores; ours of the chunk's
    bytes equals it, for odd sizes, whole blocks and words that make the sums wrap."""
    with h5py.File(tmp_path / "f.h5", "w") as f:
        data = np.frombuffer(raw, np.uint8)
        dataset = f.create_dataset("x", data=data, chunks=(len(data),), fletcher32=True)
        _, stored = dataset.id.read_direct_chunk((0,))
    assert stored[:-4] == raw
    assert fletcher32(raw) == int.from_bytes(stored[-4:], "little")
    assert fletcher32(raw) != fletcher32(raw[:-1] + bytes([raw[-1] ^ 1]))  # one flipped bit shows


def test_fletcher32_from_plain_sums_equals_the_loop_over_blocks():
    """The checksum from the plain sums equals HDF5's block loop (`_fletcher32_by_blocks`) on 300
    random chunks of every length parity, one piece of words or several (`PIECE`), from uniform
    bytes to bytes near 0xFF (where a block's 32-bit sums carry and the loop takes over); fails if
    a sum's fold to 1..65535 is off or a piece's sums join the next one's wrongly."""
    from acoustic_sim.datasets.chunks import NO_CARRY, _fletcher32_by_blocks

    rng = np.random.default_rng(7)
    carried = 0
    for i in range(300):
        low = [0, 128, 240, 254, 255][i % 5]
        raw = rng.integers(low, 256, int(rng.integers(1, [9000, 50000][i % 2]))).astype(np.uint8).tobytes()
        words = np.frombuffer(raw, ">u2", count=len(raw) // 2).astype(np.int64)
        full = len(words) // 360 * 360
        carried += bool((words[:full].reshape(-1, 360) @ np.arange(360, 0, -1) >= NO_CARRY).any())
        assert fletcher32(raw) == _fletcher32_by_blocks(raw), (i, len(raw), low)
    assert 0 < carried < 300  # both ways were taken


@pytest.mark.parametrize(
    ("dtype", "rows", "threads"), [(np.float16, 9, 3), (np.uint8, 9, 3), (np.float16, 70, 3), (np.uint8, 5, 1)]
)
def test_rows_written_in_threads_read_back_through_hdf5(tmp_path, dtype, rows, threads):
    """A shard-like dataset (shuffle, gzip 1, Fletcher-32, one chunk per frame) written with
    `write_rows` (in 3 threads a row or runs of 5 rows at a time, or in this one) reads back equal
    through h5py, which inflates, unshuffles and checks every chunk's checksum, each row in its
    place; the stored chunks (deflated by ISA-L) are at most 5 % larger than HDF5's own for the
    same data, and smaller than the raw rows."""
    rng = np.random.default_rng(2)
    array = (rng.random((rows, 24, 18)) * (3.0 if dtype == np.float16 else 1.5)).astype(dtype)
    with h5py.File(tmp_path / "f.h5", "w") as f:
        ours = f.create_dataset("ours", shape=array.shape, dtype=dtype, chunks=(1, 24, 18), **COMPRESSION)
        write_rows(ours, array, threads=threads)
        theirs = f.create_dataset("theirs", data=array, chunks=(1, 24, 18), **COMPRESSION)
        sizes = [
            (len(ours.id.read_direct_chunk((i, 0, 0))[1]), len(theirs.id.read_direct_chunk((i, 0, 0))[1]))
            for i in range(rows)
        ]
    with h5py.File(tmp_path / "f.h5", "r") as f:
        np.testing.assert_array_equal(f["ours"][()], array)
    raw = array[0].nbytes + 4  # a row and its checksum
    assert all(a <= 1.05 * b + 8 and a < raw for a, b in sizes), sizes


@pytest.mark.parametrize("planes", [1, 2, 4])
def test_planes_of_noise_are_stored_and_the_stream_inflates(planes):
    """`deflate_planes` on byte planes of noise and of runs (the noise one 70,000 bytes: two stored
    blocks): zlib inflates the stream to the bytes, and it is no longer than the noise stored plus
    the runs deflated alone by ISA-L, which a wrong stored-block header, a plane deflated that should be
    stored or a wrong checksum trailer breaks."""
    rng = np.random.default_rng(5)
    noise = rng.integers(0, 256, 70_000, dtype=np.uint8).tobytes()
    runs = np.repeat(rng.integers(0, 4, 700, dtype=np.uint8), 100).tobytes()
    data = b"".join([noise, runs] * 2)[: planes * 70_000]
    out = deflate_planes(data, planes, 1)
    assert zlib.decompress(out) == data
    stored = data.count(noise[:1000]) * (70_000 + 2 * 5)
    deflated = (planes - data.count(noise[:1000])) * len(isal_zlib.compress(runs, 1))
    assert len(out) <= stored + deflated + 64, (len(out), stored, deflated)


def test_energyscape_rows_with_a_stored_plane_read_back_through_hdf5(tmp_path):
    """Paper-sized float16 rows (their low bytes noise, stored; the high bytes deflated) written by
    `write_rows` read back equal through h5py, every checksum checked, each chunk no larger than
    HDF5's own deflate makes it."""
    array = (np.random.default_rng(6).random((4, 240, 181)) ** 8).astype(np.float16)
    with h5py.File(tmp_path / "f.h5", "w") as f:
        ours = f.create_dataset("ours", shape=array.shape, dtype=array.dtype, chunks=(1, 240, 181), **COMPRESSION)
        write_rows(ours, array, threads=2)
        theirs = f.create_dataset("theirs", data=array, chunks=(1, 240, 181), **COMPRESSION)
        sizes = [[len(d.id.read_direct_chunk((i, 0, 0))[1]) for d in (ours, theirs)] for i in range(len(array))]
    with h5py.File(tmp_path / "f.h5", "r") as f:
        np.testing.assert_array_equal(f["ours"][()], array)
    assert all(a <= b for a, b in sizes), sizes


def test_a_damaged_chunk_fails_its_checksum(tmp_path):
    """A bit flipped in the checksum of a chunk we wrote is caught by HDF5 on reading: the check is real."""
    array = np.arange(2 * 50, dtype=np.float16).reshape(2, 50)
    with h5py.File(tmp_path / "f.h5", "w") as f:
        dataset = f.create_dataset("x", shape=array.shape, dtype=array.dtype, chunks=(1, 50), **COMPRESSION)
        data = bytearray(encode(array[1], pipeline(dataset)))
        data[-1] ^= 0x10  # in the stored checksum: the deflated data still inflates
        dataset.id.write_direct_chunk((0, 0), encode(array[0], pipeline(dataset)))
        dataset.id.write_direct_chunk((1, 0), bytes(data))
    with h5py.File(tmp_path / "f.h5", "r") as f:
        np.testing.assert_array_equal(f["x"][0], array[0])
        with pytest.raises(OSError):
            f["x"][1]


def test_what_is_not_handled_is_refused(tmp_path):
    with h5py.File(tmp_path / "f.h5", "w") as f:
        lzf = f.create_dataset("lzf", shape=(2, 4), dtype=np.float32, chunks=(1, 4), compression="lzf")
        with pytest.raises(ValueError, match="not applied here"):
            write_rows(lzf, np.zeros((2, 4), np.float32), threads=2)
        whole = f.create_dataset("whole", shape=(2, 4), dtype=np.float32, chunks=(2, 4), **COMPRESSION)
        with pytest.raises(ValueError, match="chunks of one row"):
            write_rows(whole, np.zeros((2, 4), np.float32), threads=2)


FAULTS_SCRIPT = """
import resource, sys
import h5py
import numpy as np
from acoustic_sim.datasets.chunks import write_rows
from acoustic_sim.datasets.helper_processes import keep_freed_memory
from acoustic_sim.datasets.shards import COMPRESSION
if sys.argv[1] == "keep":
    keep_freed_memory()
# energyscapes of two elevations: a chunk's copies (174 kB) pass malloc's 128 kB mmap threshold
rows = (np.random.default_rng(0).random((60, 2, 240, 181)) ** 8).astype(np.float16)
with h5py.File(sys.argv[2], "w") as f:
    for shard in range(6):  # the faults of shards 1-5, once the process is warm
        if shard == 1:
            before = resource.getrusage(resource.RUSAGE_SELF).ru_minflt
        x = f.create_dataset(f"x{shard}", shape=rows.shape, dtype=rows.dtype, chunks=(1, 2, 240, 181), **COMPRESSION)
        write_rows(x, rows, threads=2)
print((resource.getrusage(resource.RUSAGE_SELF).ru_minflt - before) / (5 * len(rows)))
"""


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="malloc's options are glibc's")
def test_a_process_that_keeps_freed_memory_encodes_without_page_faults(tmp_path):
    """`keep_freed_memory` (generate's worker and helper processes) stops malloc from returning a
    shard's compressed chunks and copies between shards: writing a warm process's shards of
    two-elevation energyscapes in two threads then page-faults little, against many faults a frame
    without it (each a trip into the kernel, contended between threads). Five shards' mean, the
    median of three processes each way: 15-25 against 0.5-1.7 faults a frame on the 2-core CPU. With
    one elevation (87 kB chunks) the two overlapped once the checksum stopped copying a chunk to
    int64 (0.3-8.0 against 0.5-1.7): which arena a thread's blocks come from varies run to run."""
    faults = {
        how: float(
            np.median(
                [
                    float(
                        subprocess.run(
                            [sys.executable, "-c", FAULTS_SCRIPT, how, str(tmp_path / f"{how}{run}.h5")],
                            capture_output=True,
                            text=True,
                            check=True,
                        ).stdout
                    )
                    for run in range(3)
                ]
            )
        )
        for how in ("default", "keep")
    }
    assert faults["default"] > 5 and faults["keep"] < faults["default"] / 3, faults
