"""HDF5 chunks compressed on every core: the shard's filters (shuffle, deflate, Fletcher-32)
applied here, in threads, and the finished chunks stored with `write_direct_chunk`.

h5py runs HDF5's filters under one lock per process, one chunk at a time: on the H100 machine
compressing a shard cost ~3 ms per frame, more than simulating it. Deflate here is ISA-L's
(python-isal), which releases the GIL, so threads compress chunks side by side; its output is the
zlib stream any inflater reads, so the file is the same HDF5 any reader (h5py, MATLAB) opens and
checks.
"""

from __future__ import annotations

import struct
from concurrent.futures import ThreadPoolExecutor

import h5py
import numpy as np
from isal import isal_zlib

BLOCK = 360  # words per Fletcher block (HDF5's: the most sums that cannot overflow 32 bits)
PIECE = 80 * BLOCK  # words summed at once by `fletcher32` (115 kB of uint32: below malloc's mmap threshold)
# Deflating is most of a shard's writing, and writing the largest host cost of generation (38-45 s
# summed over the workers for 25,000 frames on two H100s, benchmarks/results/multi_gpu/
# h100x2_session27). On a `paper` shard's shuffled float16 energyscapes ISA-L's level 1 took
# 0.19 ms a frame for 57.8 KB, zlib's level 1 with its run-length strategy (used here before)
# 0.71 ms for the same 57.8 KB, zlib-ng's 0.37 ms, libdeflate's level 2 0.58 ms for 53.9 KB; LiDAR
# images 0.03 against 0.06 ms (0.8 against 0.5 KB). ISA-L's levels go to 3: HDF5's above it is 3.
ISAL_MAX_LEVEL = isal_zlib.ISAL_BEST_COMPRESSION
ROWS_A_CALL = 16  # rows a compressing thread takes at once (write_rows)
# After the shuffle filter a float's low mantissa bytes lie together, as noise: a paper energyscape's
# low plane deflated to 99.7 % of itself in 0.115 of the chunk's 0.175 ms (2-core CPU). A plane
# whose first SAMPLE bytes deflate to more than STORE_ABOVE of themselves is stored as it is.
SAMPLE = 4096
STORE_ABOVE = 0.95
ZLIB_HEADER = b"\x78\x01"  # deflate, 32 kB window (RFC 1950)
LAST_EMPTY_BLOCK = b"\x01\x00\x00\xff\xff"  # a final stored block of no bytes (RFC 1951)


# A block's sum of running sums below this cannot carry the 32-bit sums of HDF5's loop past 2^32
# (with both sums folded below 2^17 before it): only blocks of words near 0xFFFF come close.
NO_CARRY = (1 << 32) - (BLOCK + 1) * 0x1FFFE
# Word j of a block is in BLOCK - j of its running sums; their sum, at most 65535 * 360 * 361 / 2,
# fits 32 bits: uint32 products and sums are exact and take half an int64 copy's memory traffic.
RAMP = np.arange(BLOCK, 0, -1, dtype=np.uint32)
# Past this many words sum2's int64 terms could overflow (65535 n^2 < 2^63); such chunks take the loop
MAX_WORDS = 10_000_000


def fletcher32(data: bytes) -> int:
    """HDF5's Fletcher-32 checksum of `data` (H5_checksum_fletcher32): big-endian 16-bit words
    summed in blocks of 360, the sums folded to 16 bits after each block; an odd last byte counts
    as the high byte of a word.

    Folding keeps each sum's value modulo 65535 (2^16 = 1 there) and a positive sum positive, so
    where no block carries its 32-bit sums past 2^32 the checksum follows from the plain sums:
    sum1 = sum of the words, sum2 = sum of (n - i) word_i, each taken to 1..65535 (0 if zero).
    Writing a shard checks thousands of chunks: this costs a few passes of numpy, where HDF5's
    loop over blocks in Python cost ~0.4 ms a chunk (benchmarks/results/generate_cuda.md)."""
    # Per block b: its words' sum S_b and the sum of its running sums W_b = sum_j (L_b - j) w_bj
    # (what HDF5's 32-bit sums must hold). Then sum2 = sum_b W_b + L_b * (the words' sum before b).
    # A cumsum over the words made the same sums: a paper shard's checksums cost 0.094 ms a frame
    # on the 2-core CPU that way, 0.064 this way (checksums were 11 % of generation's busy host
    # time on two H200s, benchmarks/results/multi_gpu/session35). The copies go by PIECE words,
    # which malloc keeps between chunks.
    n = len(data) // 2
    if n > MAX_WORDS:
        return _fletcher32_by_blocks(data)
    words = np.frombuffer(data, dtype=">u2", count=n)
    sums, weighted = [], []
    for start in range(0, n, PIECE):
        piece = words[start : start + PIECE]
        full = len(piece) // BLOCK * BLOCK
        if full == len(piece):
            blocks = piece.astype(np.uint32)
        else:  # a last, shorter block of L words, right-aligned: its word j then weighs L - j
            blocks = np.zeros(full + BLOCK, dtype=np.uint32)
            blocks[:full] = piece[:full]
            blocks[full + BLOCK - (len(piece) - full) :] = piece[full:]
        blocks = blocks.reshape(-1, BLOCK)
        sums.append(blocks.sum(axis=1, dtype=np.int64))
        weighted.append(np.einsum("ij,j->i", blocks, RAMP))
    if sums:
        block_sums, block_weighted = (np.concatenate(x) if len(x) > 1 else x[0] for x in (sums, weighted))
        block_weighted = block_weighted.astype(np.int64)
        if (block_weighted >= NO_CARRY).any():
            return _fletcher32_by_blocks(data)
        before = np.cumsum(block_sums) - block_sums  # each block's words' running sum on entry
        short = -n % BLOCK  # words the last block lacks: its running sums count `before` that much less
        total = int(block_sums.sum())
        summed = int(block_weighted.sum() + BLOCK * before.sum() - short * before[-1])
    else:  # fewer than two bytes
        total = summed = 0
    if len(data) % 2:  # the odd last byte, as the high byte of a last word
        total += data[-1] << 8
        summed += total
    sum1, sum2 = (0 if s == 0 else (s - 1) % 0xFFFF + 1 for s in (total, summed))
    return (sum2 << 16) | sum1


def _fletcher32_by_blocks(data: bytes) -> int:
    """`fletcher32` as HDF5's loop computes it, block by block (32-bit sums, folded after each)."""
    words = np.frombuffer(data, dtype=">u2", count=len(data) // 2).astype(np.int64)
    full = len(words) // BLOCK * BLOCK
    blocks = [words[:full].reshape(-1, BLOCK)] if full else []
    if full < len(words):
        blocks.append(words[full:][None])
    sum1 = sum2 = 0
    for block in blocks:  # per block: its sum, and the sum of its running sums
        weights = np.arange(block.shape[1], 0, -1, dtype=np.int64)
        for total, running in zip(block.sum(axis=1).tolist(), (block @ weights).tolist(), strict=True):
            sum2 = (sum2 + block.shape[1] * sum1 + running) & 0xFFFFFFFF
            sum1 = sum1 + total
            sum1 = (sum1 & 0xFFFF) + (sum1 >> 16)
            sum2 = (sum2 & 0xFFFF) + (sum2 >> 16)
    if len(data) % 2:
        sum1 += data[-1] << 8
        sum2 += sum1
        sum1 = (sum1 & 0xFFFF) + (sum1 >> 16)
        sum2 = (sum2 & 0xFFFF) + (sum2 >> 16)
    sum1 = (sum1 & 0xFFFF) + (sum1 >> 16)
    sum2 = (sum2 & 0xFFFF) + (sum2 >> 16)
    return (sum2 << 16) | sum1


def pipeline(dataset: h5py.Dataset) -> list[tuple[int, tuple]]:
    """The dataset's filters in the order HDF5 applies them when writing: (filter id, values)."""
    plist = dataset.id.get_create_plist()
    filters = [plist.get_filter(i)[:3:2] for i in range(plist.get_nfilters())]
    known = {h5py.h5z.FILTER_SHUFFLE, h5py.h5z.FILTER_DEFLATE, h5py.h5z.FILTER_FLETCHER32}
    unknown = [f for f, _ in filters if f not in known]
    if unknown:
        raise ValueError(f"{dataset.name}: filters {unknown} are not applied here (only shuffle, deflate, fletcher32)")
    return filters


def deflate_planes(data: bytes, planes: int, level: int) -> bytes:
    """A zlib stream of `data`, `planes` byte planes of equal length back to back (as the shuffle
    filter leaves them): each plane deflated, or kept in stored blocks where a sample of it does not
    deflate (noise). Any inflater reads it as one stream, as it reads a single `compress`'s."""
    plane = len(data) // planes
    view, parts = memoryview(data), [ZLIB_HEADER]
    for start in range(0, len(data), plane):
        piece = view[start : start + plane]
        if len(isal_zlib.compress(piece[:SAMPLE], level)) > STORE_ABOVE * min(SAMPLE, len(piece)):
            for at in range(0, len(piece), 0xFFFF):  # stored blocks: a header byte, LEN, ~LEN, the bytes
                block = piece[at : at + 0xFFFF]
                parts += [struct.pack("<BHH", 0, len(block), 0xFFFF ^ len(block)), block]
        else:  # raw deflate ending on a byte boundary, not final (a sync flush)
            squeeze = isal_zlib.compressobj(level, isal_zlib.DEFLATED, -15)
            parts += [squeeze.compress(piece), squeeze.flush(isal_zlib.Z_SYNC_FLUSH)]
    parts += [LAST_EMPTY_BLOCK, struct.pack(">I", isal_zlib.adler32(data))]
    return b"".join(parts)


def encode(chunk: np.ndarray, filters: list[tuple[int, tuple]]) -> bytes:
    """One chunk's bytes as stored after `filters`."""
    data = np.ascontiguousarray(chunk).tobytes()
    size, planes = chunk.dtype.itemsize, 1
    for code, values in filters:
        if code == h5py.h5z.FILTER_SHUFFLE and size > 1:  # byte k of every element, then byte k + 1
            data = np.frombuffer(data, np.uint8).reshape(-1, size).T.tobytes()
            planes = size
        elif code == h5py.h5z.FILTER_DEFLATE and planes > 1 and len(data) >= planes * SAMPLE:
            data = deflate_planes(data, planes, min(values[0], ISAL_MAX_LEVEL))
        elif code == h5py.h5z.FILTER_DEFLATE:
            data = isal_zlib.compress(data, min(values[0], ISAL_MAX_LEVEL))
        elif code == h5py.h5z.FILTER_FLETCHER32:
            data += struct.pack("<I", fletcher32(data))
    return data


def write_rows(dataset: h5py.Dataset, array: np.ndarray, threads: int) -> None:
    """Fill `dataset`, chunked one row of its first axis per chunk, with `array`: runs of rows
    filtered in `threads` threads (in this one for one), each chunk stored as it is. A thread
    takes up to ROWS_A_CALL rows a call: one call a row spent ~0.03 of a frame's ~0.25 ms
    handing rows between threads."""
    if dataset.shape != array.shape or dataset.chunks != (1, *array.shape[1:]):
        raise ValueError(f"{dataset.name}: need shape {array.shape} in chunks of one row, got {dataset.chunks}")
    filters = pipeline(dataset)
    array = np.asarray(array, dtype=dataset.dtype)
    rest = (0,) * (array.ndim - 1)
    if threads <= 1:
        for i, row in enumerate(array):
            dataset.id.write_direct_chunk((i, *rest), encode(row, filters))
        return
    step = max(1, min(ROWS_A_CALL, len(array) // (4 * threads)))  # enough runs to keep the threads even
    runs = (array[i : i + step] for i in range(0, len(array), step))
    with ThreadPoolExecutor(threads) as pool:
        done = pool.map(lambda rows: [encode(row, filters) for row in rows], runs)
        for i, data in enumerate(data for encoded in done for data in encoded):
            dataset.id.write_direct_chunk((i, *rest), data)
