"""Each ping's noise seed: numpy's SeedSequence of (the run's seed, the ping's index), for all pings
of a batch at once."""

from __future__ import annotations

import numpy as np


def ping_seeds(seed: int, pings: np.ndarray) -> np.ndarray:
    """Noise seed of each ping (int32), from the run's seed and the ping's index alone: the first
    word of `np.random.SeedSequence([seed, i]).generate_state(1)`, lowest 31 bits, computed for
    all pings at once (one SeedSequence a ping took ~20 us of the rendering thread, ~2 % of its
    CPU in a dataset's episode)."""
    pings = np.asarray(pings, dtype=np.int64).reshape(-1)
    if len(pings) and (pings.min() < 0 or pings.max() > MASK32):
        return np.array(
            [np.random.SeedSequence([seed, int(i)]).generate_state(1)[0] & 0x7FFFFFFF for i in pings], dtype=np.int32
        )
    words = [*_uint32_words(seed), pings.astype(np.uint32)]  # the entropy SeedSequence assembles
    return (_seed_sequence_word(words) & np.uint32(0x7FFFFFFF)).astype(np.int32)


# numpy's SeedSequence (numpy/random/bit_generator.pyx, after M. O'Neill's seed_seq_fe): its pool of
# four 32-bit words mixed from the entropy, then one word of state drawn from the pool.
MASK32 = 0xFFFFFFFF
_POOL, _INIT_A, _MULT_A, _INIT_B, _MULT_B = 4, 0x43B0D7E5, 0x931E8875, 0x8B51F9DD, 0x58F38DED
_MIX_L, _MIX_R = np.uint32(0xCA01F9DD), np.uint32(0x4973F715)


def _uint32_words(n: int) -> list[np.uint32]:
    """A non-negative integer as SeedSequence reads it: 32-bit words, least significant first."""
    if n < 0:
        raise ValueError(f"seed must be >= 0, got {n}")
    words = [np.uint32(0)] if n == 0 else []
    while n > 0:
        words.append(np.uint32(n & MASK32))
        n >>= 32
    return words


def _seed_sequence_word(entropy: list) -> np.ndarray:
    """The first uint32 of generate_state for entropy words (scalars, or arrays: one sequence each)."""
    hash_const = _INIT_A

    def hashmix(value):
        nonlocal hash_const
        value = np.asarray(value, dtype=np.uint32) ^ np.uint32(hash_const)
        hash_const = (hash_const * _MULT_A) & MASK32
        value = value * np.uint32(hash_const)
        return value ^ (value >> np.uint32(16))

    def mix(x, y):
        result = _MIX_L * x - _MIX_R * y
        return result ^ (result >> np.uint32(16))

    with np.errstate(over="ignore"):
        pool = [hashmix(entropy[i] if i < len(entropy) else 0) for i in range(_POOL)]
        for src in range(_POOL):
            for dst in range(_POOL):
                if src != dst:
                    pool[dst] = mix(pool[dst], hashmix(pool[src]))
        for src in range(_POOL, len(entropy)):
            for dst in range(_POOL):
                pool[dst] = mix(pool[dst], hashmix(entropy[src]))
        value = pool[0] ^ np.uint32(_INIT_B)
        value = value * np.uint32((_INIT_B * _MULT_B) & MASK32)
        return value ^ (value >> np.uint32(16))
