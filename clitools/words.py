"""How counts read in what the command lines print: `1 shard`, `2 shards`, `12,000 frames`."""

from __future__ import annotations


def counted(count: int, noun: str, plural: str | None = None) -> str:
    """`count` (with thousands separators) and `noun`, plural unless the count is one.

    Args:
        count: How many.
        noun: The singular ("shard", "episode").
        plural: The plural where it is not noun + "s".
    """
    return f"{count:,} {noun if count == 1 else plural or noun + 's'}"
