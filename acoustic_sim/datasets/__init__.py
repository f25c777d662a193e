"""The dataset pipeline: suites of scenes and physics variants become sharded HDF5 datasets.

`suites` and `physics` (what to simulate), `plan` (episodes -> shard tasks, the plan id),
`episode` (one episode through the engine), `workers` and `generate` (local processes or Ray,
resume, lock, damaged-shard repair), `shards` and `chunks` (the files: the only interface to
`learn`), `manifest` (manifest and dataset card). Uses the engine; never the formats.
"""
