"""The simulation engine: a scene and poses in, LiDAR ranges and sonar energyscapes out.

One stage per file, in the order data flows: `scene` (meshes on the device), `poses` (pose
checks), `lidar` (the LiDAR), `paths` (the acoustic path tracer: echoes, held in `echoes`),
`signals` (the recorder: echoes -> microphone signals), `beamform` (matched filter and
delay-and-sum: signals -> energyscapes) and `sonar` (the three composed). `kernels/` holds the
Warp kernels alone. The engine imports neither `datasets` nor `formats`; its public names are
re-exported by `acoustic_sim`.
"""
