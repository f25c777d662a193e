"""What `python -m acoustic_sim --help` says: the program's description and, per command, its
summary line (help), description and examples (epilog); `cli.build_parser` adds the options."""

from clitools import examples

DESCRIPTION = (
    "The simulator: draw scenes and sonar pings (render), fit its surfaces and microphones to recordings of a "
    "known room (calibrate), simulate datasets of LiDAR and sonar frames (generate), turn real recordings into "
    "energyscapes or datasets (import), and write datasets for robotics tools (export). Each command's --help "
    "lists its options and ends with examples."
)
EXAMPLES = examples(
    "python -m acoustic_sim render --scene office --out office.png",
    "python -m acoustic_sim generate --suite tiny --out data/tiny",
)
SET_HELP = (
    "change the rig: lidar.*, sonar.*, tracer.*, processing.* (repeatable; e.g. tracer.max_bounces=1, "
    "processing.grid.range_max_m=4, sonar.atmosphere.temperature_c=30, lidar=multibeam_64x1024 for a preset)"
)
VERBOSE_HELP = "show Warp's messages (start-up, compiles); SONAR2LIDAR_WARP_VERBOSE=1 does so everywhere"
MESH_OPTIONS = {  # render's options for --mesh (scenes.from_mesh's arguments); None: not given (auto)
    "--up": {"help": "--mesh: the file's up axis, auto (the default: y for glTF, z for others), z or y"},
    "--units": {
        "help": "--mesh: the file's unit, auto (the default: metres, refused if absurd for a building), m, cm, mm, "
        "in or ft",
    },
    "--materials": {
        "metavar": "TABLE.toml",
        "help": "--mesh: TOML file whose [materials] table maps the file's material names or globs to ours",
    },
}

COMMANDS = {
    "render": {
        "help": "draw a scene from above with its trajectory and a LiDAR scan, or a sonar ping (--sonar)",
        "description": "Draw a scene from above with the robot's trajectory and one pose's LiDAR scan, beside that "
        "scan's polar image; --sonar: one sonar ping's echoes and energyscapes, without and with secondary "
        "reflections. Writes OUT (.png) and the settings that made it (.json) beside it.",
        "epilog": examples(
            "python -m acoustic_sim render --scene office --frames 150 --frame 60 --out office.png",
            "python -m acoustic_sim render --sonar --scene office --frames 40 --frame 30 --out sonar.png",
        ),
    },
    "generate": {
        "help": "simulate a dataset suite into HDF5 shards (resumable)",
        "description": "Simulate a suite of scenarios (scenes, robot drives, LiDAR and sonar) into HDF5 shards, "
        "with manifest.json and a dataset card (README.md, card.png) per dataset; a progress bar counts the "
        "frames. Rerunning the same command skips finished shards. Suites: {suites}; crossengine: a test set "
        "from another engine (pyroomacoustics' image sources in empty L, T, U, junction and hall rooms; 1,000 "
        "frames by default; scoring only); crossengine_rough: the same with rough walls (diffuse backscatter "
        "from random wall scatterers).",
        "epilog": examples(
            "python -m acoustic_sim generate --suite tiny --out data/tiny",
            "python -m acoustic_sim generate --suite paper --frames 12500 --workers 4 --device cuda:0 --out data/paper",
        ),
    },
    "calibrate": {
        "help": "fit the scene's surface reflection and the microphones' gains to recorded pings",
        "description": "Fit the energy reflection coefficient of each surface class (walls, floor, ceiling, "
        "objects) and every microphone's gain to recorded microphone signals of pings at known poses in a room "
        "whose geometry the scene gives (its materials are the starting point, their scattering taken as "
        "known). The specular paths are traced once; the fit minimises the squared error between simulated "
        "and recorded signals. "
        "RECORDINGS: a .npz with `poses` (N, 4, 4) and `signals` (N, mics, samples) recorded by the rig's "
        "sonar, or a dataset folder (or shard) made with `generate --signals` (one --episode of it). "
        "Writes OUT (.json: the fitted and nominal values, the loss at each step, the "
        "settings) and a picture beside it (.png: the loss, the coefficients, one ping's energyscape recorded "
        "and simulated before and after). Scattered echoes, the emitter's directivity and the microphones' "
        "delays are not fitted yet.",
        "epilog": examples(
            "python -m acoustic_sim calibrate rec.npz --scene box_room --scene-arg size=[6,4,3] --out fit.json",
        ),
    },
    "import": {
        "help": "turn a real sensor's recording into energyscapes (raw eRTIS PDM) or a dataset (CHIRP)",
        "description": "pdm: decode raw 1-bit PDM microphone streams (one word of channel bits per PDM sample; one "
        "file per ping unless --samples-per-ping splits them) to PCM, and process them with the rig's array, "
        "call and grid into energyscapes, as the simulator's pings are. Writes OUT (.npy), a picture (.png) "
        "and the settings (.json) for `learn predict --input OUT`. "
        "chirp: a CHIRP recording (.h5, read with cosys-chirppy: extra `chirp`, CC BY-NC-SA) into a dataset "
        "folder OUT for `learn evaluate --data OUT` and `learn predict --input OUT`: the microphone signals "
        "through our processing with the file's array and sample rate and the rig's call and grid; the LiDAR "
        "points within --plane-tolerance of the sonar's plane as a 2D scan on the rig's LiDAR azimuths "
        "(nearest point per beam), rasterised as the simulator's labels; poses from the odometry.",
        "epilog": examples(
            "python -m acoustic_sim import rec/ping-0001.bin rec/ping-0002.bin --format pdm --out rec.npy",
            "python -m acoustic_sim import data/sim.h5 --format chirp --out data/recording",
        ),
    },
    "export": {
        "help": "write a dataset for robotics tools (MCAP of ROS 2 messages) or the eRTIS lab (CHIRP)",
        "description": "mcap: every frame of a dataset folder as ROS 2 messages in an MCAP file, without a ROS "
        "install (extra `ros`): sensor_msgs/LaserScan on /scan, sensor_msgs/Image (32FC1, range x azimuth) on "
        "/sonar/energyscape (a dataset of several elevations: one topic per elevation, "
        "/sonar/energyscape/elevation_m20_deg ...), tf2_msgs/TFMessage world -> sensor on /tf, stamped with the "
        "drive's times. "
        "Open it in Foxglove. chirp: a dataset generated with --signals as one CHIRP file (.h5, the eRTIS "
        "lab's format; cosys-chirppy reads it): the microphone signals with the array's positions and "
        "sample rate, the call, the LiDAR as x, y, z, intensity points, the poses as odometry, Unix times "
        "of the drive.",
        "epilog": examples(
            "python -m acoustic_sim export data/tiny --format mcap --out drive.mcap",
            "python -m acoustic_sim export data/tiny_signals --format chirp --out data/sim.h5",
        ),
    },
}
"""Keyword arguments of each command's `add_parser`; generate's description names the suites."""
