"""Command line: `python -m acoustic_sim render|calibrate|generate|import|export ...` (the words of its help in
cli_text.py); handlers import the heavy modules (Warp, scenes, h5py) themselves."""

from __future__ import annotations

import argparse
import dataclasses
import json
import sys
import time
from pathlib import Path

from clitools import HelpFormatter, counted, run_command
from clitools.errors import interrupt_after
from clitools.outputs import OVERWRITE_HELP, atomic_folder

from .cli_calibrate import add_calibrate_parser
from .cli_scene import add_scene_options, check_mesh_options, scene_from_args
from .cli_text import COMMANDS, DESCRIPTION, EXAMPLES, MESH_OPTIONS, SET_HELP, VERBOSE_HELP
from .extras import MissingExtra  # no heavy imports: a plain exception class


def _render(args) -> int:
    from .render import check_picture_name

    out = Path(args.out)
    check_picture_name(out)
    check_mesh_options(args)  # before anything is written
    inputs = [p for p in (args.svg, args.mesh, args.materials) if p]
    names = [out.name, out.with_suffix(".json").name]  # the picture and its settings, published together
    with atomic_folder(out.parent, overwrite=args.overwrite, inputs=inputs, expected=names) as stage:
        done = _render_into(args, stage / out.name)
    print(done)
    return 0


def _render_into(args, picture: Path) -> str:
    """Draw the picture and its settings file at `picture`; returns the line to print."""
    import numpy as np
    import warp as wp

    from .devices import check_device, quiet_warp

    quiet_warp(not args.verbose)
    import scenes

    from .config import SimConfig
    from .datasets.plan import check_scan, check_seed
    from .engine.lidar import Lidar, lidar_image
    from .render import render_lidar
    from .settings import apply_settings

    t0 = time.perf_counter()
    check_device(args.device)
    rig = apply_settings(SimConfig(), args.set or ())
    check_seed(args.seed, "--seed")
    if args.sonar and np.ndim(rig.processing.elevation_deg):
        raise ValueError("render --sonar draws one energyscape a ping: set processing.elevation_deg to one angle")
    check_scan(args.frames, rig, "--frames: a drive")  # before the drive and its scan are made
    scene = scene_from_args(args)
    poses = scenes.trajectory(scene, frames=args.frames, dt=args.dt, speed=args.speed, seed=args.seed)
    if not 0 <= args.frame < len(poses):
        raise ValueError(f"--frame must lie in 0..{len(poses) - 1}")
    flags = {"noise": args.lidar_noise, "noise_m": args.lidar_noise_m}
    config = dataclasses.replace(rig.lidar, **{k: v for k, v in flags.items() if v is not None})
    rig = dataclasses.replace(rig, lidar=config)
    with wp.ScopedDevice(args.device):
        ranges = Lidar(config, seed=args.seed).scan(scene, poses)
    grid = rig.processing.grid
    if args.sonar:
        label = lidar_image(ranges[args.frame], config, grid)[0]
        return _render_sonar(args, rig, scene, poses[args.frame], label, t0, picture)
    out = render_lidar(scene, poses, ranges, config, lidar_image(ranges, config, grid), grid, picture, frame=args.frame)
    _write_render_config(out, rig, args)
    return (
        f"{scene!r}: {counted(len(poses), 'pose')}, {counted(ranges.size, 'LiDAR ray')} on {args.device}; "
        f"wrote {args.out} and its settings in {out.with_suffix('.json').name} in {time.perf_counter() - t0:.1f} s"
    )


def _write_render_config(picture, rig, args) -> None:
    """The picture's full rig (asdict of the configs as used) and the command's options, as
    PICTURE.json beside it, so a picture can be made again."""
    options = {k: v for k, v in vars(args).items() if not callable(v)}
    text = json.dumps({"picture": Path(picture).name, "options": options, "sim": rig.to_dict()}, indent=1)
    Path(picture).with_suffix(".json").write_text(text)


def _render_sonar(args, rig, scene, pose, lidar, t0, picture: Path) -> str:
    """The sonar picture: the same ping simulated with max_bounces 0 and with --max-bounces."""
    from .engine.sonar import Sonar
    from .render import render_sonar

    tracer = rig.tracer if args.rays is None else dataclasses.replace(rig.tracer, ray_count=args.rays)
    results = []
    bounces = sorted({0, rig.tracer.max_bounces if args.max_bounces is None else args.max_bounces})
    for order in bounces:
        sonar = Sonar(rig.sonar, tracer, max_bounces=order, device=args.device)
        arrivals = sonar.trace(scene, pose)
        signals = sonar.record(arrivals, pose_count=1, noise="gaussian", seed=args.seed)
        results.append((f"max_bounces={order}", arrivals.for_pose(0), sonar.energyscape(signals, rig.processing)[0]))
    out = render_sonar(scene, pose, results, lidar, rig.processing.grid, picture)
    _write_render_config(out, dataclasses.replace(rig, tracer=tracer), args)
    return (
        f"{scene!r}: sonar ping at frame {args.frame} with max_bounces {' and '.join(str(b) for b in bounces)}; "
        f"wrote {args.out} and its settings in {out.with_suffix('.json').name} in {time.perf_counter() - t0:.1f} s"
    )


def _generate(args) -> int:
    try:
        return _generate_dataset(args)
    except KeyboardInterrupt:
        return _interrupted(args.out)


def _generate_dataset(args) -> int:
    from .devices import quiet_warp

    quiet_warp(not args.verbose, start=False)  # Warp starts in the worker processes (so they can be forked)
    from .datasets.generate import generate
    from .datasets.suites import load_suite

    if args.suite in ("crossengine", "crossengine_rough"):
        return _generate_crossengine(args)
    suite = load_suite(args.suite)
    if args.max_bounces is not None:
        if len({p.max_bounces for p in suite.variants.values()}) > 1:
            raise ValueError(f"suite {suite.name!r} varies max_bounces across its variants; drop --max-bounces")
        variants = {k: dataclasses.replace(p, max_bounces=args.max_bounces) for k, p in suite.variants.items()}
        suite = dataclasses.replace(suite, variants=variants)
    if args.variants:
        names = [v.strip() for v in args.variants.split(",")]
        unknown = [v for v in names if v not in suite.variants]
        if unknown or len(set(names)) != len(names):
            raise ValueError(f"--variants: suite {suite.name!r} has variants {list(suite.variants)}, got {names}")
        suite = dataclasses.replace(suite, variants={v: suite.variants[v] for v in names})
    if args.set:
        suite = dataclasses.replace(suite, settings=suite.settings + tuple(args.set))
    summary = generate(
        suite,
        args.out,
        frames=args.frames,
        shards=args.shards,
        seed=args.seed,
        device=args.device,
        workers=args.workers,
        ray_address=args.ray_address,
        ray_tasks_per_gpu=args.ray_tasks_per_gpu,
        keep_signals=args.signals,
        keep_arrivals=args.arrivals,
        progress=not args.quiet,
    )
    return _report(summary)


def _interrupted(out: str) -> int:
    """Ctrl-C in `generate`: the workers are stopped and the lock released by then; one line says
    what was kept and how to go on (exit code 130, as a shell reports SIGINT)."""
    done = sorted(Path(out).rglob("shard-*.h5")) if Path(out).is_dir() else []
    if done:
        print(f"interrupted: {out} keeps {len(done)} finished shard(s); the same command resumes it", file=sys.stderr)
    else:
        print(f"interrupted before any shard was finished: nothing is kept in {out}", file=sys.stderr)
    return 130


def _report(summary: dict) -> int:
    print(
        f"{summary['suite']}: {counted(summary['frames'], 'frame')} in {counted(summary['shards'], 'shard')} "
        f"under {summary['out']} "
        f"({summary['shards_written']} written, {summary['shards_skipped']} already complete) in "
        f"{summary['seconds']:.1f} s, {summary['frames_per_s']:,.1f} frames/s on {', '.join(summary['devices'])}"
    )
    parts = summary.get("seconds_by_part")
    if parts and summary["shards_written"]:
        started = {"fork": " forked", "spawn": " spawned"}.get(summary.get("worker_start"), "")
        workers = ""
        if summary.get("workers", 1) > 1:  # and where each one's host work ran (helpers: cores to spare)
            helpers = summary.get("helpers", 0)
            workers = f" summed over {summary['workers']}{started} workers"
            each = counted(helpers, "helper process", "helper processes")
            workers += f" ({each} each)" if helpers else " (host work in threads)"
        shown = {k: v for k, v in parts.items() if k != "start-up" or v}  # no workers started: no start-up
        print(f"time by part{workers}: " + ", ".join(f"{k} {v:.1f} s" for k, v in shown.items()))
    return 0


def _generate_crossengine(args) -> int:
    from .formats.crossengine import elevations_of, generate_crossengine

    own = {"--max-bounces": args.max_bounces, "--shards": args.shards}
    own |= {"--arrivals": args.arrivals, "--ray-address": args.ray_address, "--variants": args.variants}
    own["--ray-tasks-per-gpu"] = args.ray_tasks_per_gpu if args.ray_tasks_per_gpu != 1 else None
    if given := [k for k, v in own.items() if v not in (None, False)]:
        raise ValueError(f"the {args.suite} test set is another engine's: {', '.join(given)} does not apply to it")
    summary = generate_crossengine(
        args.out,
        frames=1000 if args.frames is None else args.frames,  # --frames 0 is refused, not the default
        seed=args.seed,
        device=args.device,
        workers=args.workers,
        progress=not args.quiet,
        rough=args.suite == "crossengine_rough",
        elevation_deg=elevations_of(args.set or (), args.suite),
        keep_signals=args.signals,
    )
    return _report(summary)


def _import(args) -> int:
    from .devices import check_device, quiet_warp

    quiet_warp(not args.verbose)
    from .config import SimConfig
    from .settings import apply_settings

    check_device(args.device)
    rig = apply_settings(SimConfig(), args.set or ())
    if args.format == "chirp":
        return _import_chirp(args, rig)
    from .formats.recordings import import_pdm

    out = Path(args.out)
    written = [out.name, out.with_suffix(".png").name, out.with_suffix(".json").name]
    with atomic_folder(out.parent, overwrite=args.overwrite, inputs=args.recordings, expected=written) as stage:
        done = import_pdm(
            args.recordings,
            stage / out.name,
            rig,
            channels=args.channels,
            pdm_rate_hz=args.pdm_rate,
            bit_order=args.bit_order,
            samples_per_ping=args.samples_per_ping,
            device=args.device,
        )
    print(
        f"{counted(done['pings'], 'ping')} -> {out} (energyscapes), {out.with_suffix('.png')} "
        f"in {done['seconds']:.1f} s; "
        f"next: python -m learn predict --checkpoint MODEL.pt --input {out} --out pred.npz --png pred.png"
    )
    return 0


def _import_chirp(args, rig) -> int:
    from .formats.chirp import import_chirp

    if len(args.recordings) != 1:
        raise ValueError(f"--format chirp imports one recording (.h5) at a time, got {len(args.recordings)} files")
    if args.overwrite:
        raise ValueError(
            "--overwrite is for --format pdm: a CHIRP import makes a new dataset folder and never writes into one "
            "that holds files (two imports would mix); give a new --out"
        )
    done = import_chirp(
        args.recordings[0],
        args.out,
        rig,
        plane_tolerance_m=args.plane_tolerance,
        episode_gap_s=args.episode_gap,
        device=args.device,
    )
    lidar = f"labels from {done['lidar']}" if done["lidar"] else "no LiDAR, empty labels"
    print(
        f"{counted(done['pings'], 'ping')} -> {done['out']} ({counted(done['episodes'], 'episode')}; {lidar}, "
        f"{done['returns_per_scan']:.0f} returns per scan; poses: {done['poses']}) in {done['seconds']:.1f} s; "
        f"next: python -m learn evaluate --checkpoint MODEL.pt --data {done['out']} --out EVAL"
    )
    return 0


def _export(args) -> int:
    if args.format == "chirp":
        from .formats.chirp import export_chirp

        done = export_chirp(args.dataset, args.out, overwrite=args.overwrite)
        print(
            f"{done['frames']} frames of {args.dataset} -> {done['out']} (CHIRP: microphone signals, "
            f"{done['points']:,} LiDAR points, poses)"
        )
        return 0
    from .formats.mcap_export import export_mcap

    done = export_mcap(args.dataset, args.out, overwrite=args.overwrite)
    print(f"{done['frames']} frames of {args.dataset} -> {done['out']} ({', '.join(done['topics'])})")
    return 0


class _Parser(argparse.ArgumentParser):
    """A parser whose description may be a function, called only when its help is shown: generate's
    lists the suites, whose module imports scenes (trimesh, SciPy: ~1 s)."""

    def format_help(self) -> str:
        if callable(self.description):
            self.description = self.description()
        return super().format_help()


def _suites() -> str:
    from .datasets.suites import SUITES

    listed = "; ".join(f"{name}: {suite.description.rstrip('.')}" for name, suite in SUITES.items())
    return COMMANDS["generate"]["description"].format(suites=listed)


def build_parser() -> argparse.ArgumentParser:
    from .config import NOISE_KINDS, TracerConfig

    tracer = TracerConfig()

    parser = argparse.ArgumentParser(
        prog="python -m acoustic_sim", description=DESCRIPTION, formatter_class=HelpFormatter, epilog=EXAMPLES
    )
    parser.add_argument("--debug", action="store_true", help="show the full trace of an error (anywhere on the line)")
    sub = parser.add_subparsers(dest="command", required=True, metavar="COMMAND", parser_class=_Parser)
    render = sub.add_parser("render", formatter_class=HelpFormatter, **COMMANDS["render"])
    add_scene_options(render, MESH_OPTIONS)
    render.add_argument("--seed", type=int, default=0, help="seeds the scene, trajectory and noise")
    render.add_argument("--frames", type=int, default=100, help="trajectory length in poses")
    render.add_argument("--dt", type=float, default=0.1, help="time between poses [s]")
    render.add_argument("--speed", type=float, default=0.3, help="robot speed [m/s]")
    render.add_argument("--frame", type=int, default=0, help="which pose's scan to draw")
    render.add_argument("--lidar-noise", choices=NOISE_KINDS, help="LiDAR range noise (default: lidar.noise)")
    render.add_argument("--lidar-noise-m", type=float, help="noise std / half-width [m] (default: lidar.noise_m)")
    render.add_argument(
        "--sonar",
        action="store_true",
        help="draw a sonar ping (echo points, energyscape) instead of the LiDAR view, "
        "with max_bounces 0 beside --max-bounces",
    )
    render.add_argument(
        "--max-bounces",
        type=int,
        help=f"secondary reflections for --sonar (default: tracer.max_bounces, {tracer.max_bounces})",
    )
    render.add_argument(
        "--rays", type=int, help=f"rays per ping for --sonar (default: tracer.ray_count, {tracer.ray_count})"
    )
    render.add_argument("--set", action="append", metavar="SECTION.FIELD=VALUE", help=SET_HELP)
    render.add_argument("--device", default="cpu", help="Warp device: cpu, cuda:0, ...")
    render.add_argument("--out", default="scene.png", help="PNG to write (and its settings, .json, beside it)")
    render.add_argument("--overwrite", action="store_true", help=OVERWRITE_HELP)
    render.add_argument("--verbose", action="store_true", help=VERBOSE_HELP)
    render.set_defaults(handler=_render)

    add_calibrate_parser(sub)

    gen = sub.add_parser("generate", formatter_class=HelpFormatter, **COMMANDS["generate"] | {"description": _suites})
    gen.add_argument(
        "--suite",
        required=True,
        help="a suite listed above, crossengine, crossengine_rough, or a suite file (.toml/.json; its "
        "scenarios may be mesh files of your building: mesh = FILE)",
    )
    gen.add_argument("--out", required=True, help="output folder")
    gen.add_argument("--frames", type=int, default=None, help="frames per variant (default: the suite's)")
    gen.add_argument("--shards", type=int, default=None, help="shards per variant (default: one per 250 frames)")
    gen.add_argument("--max-bounces", type=int, default=None, help="override the suite's secondary bounces")
    gen.add_argument("--variants", default=None, help="only these variants, comma-separated (e.g. bounces_0,bounces_3)")
    gen.add_argument(
        "--set", action="append", metavar="SECTION.FIELD=VALUE", help=SET_HELP + " (after each variant's physics)"
    )
    gen.add_argument("--device", default="auto", help="auto (all GPUs, else CPU), cpu or cuda:i")
    gen.add_argument("--workers", type=int, default=1, help="parallel shard writers (processes)")
    gen.add_argument("--seed", type=int, default=0, help="seeds every scene, drive and noise")
    gen.add_argument(
        "--ray-address", default=None, help="run the shard tasks on this Ray cluster ('auto' or host:port)"
    )
    gen.add_argument(
        "--ray-tasks-per-gpu",
        type=int,
        default=1,
        help="with --ray-address: shard tasks sharing one GPU (each holds 1/N of it; default 1)",
    )
    gen.add_argument("--signals", action="store_true", help="also store the raw microphone signals (float16)")
    gen.add_argument("--arrivals", action="store_true", help="also store every traced echo (slow on a GPU)")
    gen.add_argument("--quiet", action="store_true", help="no progress bar (for logs; the summary lines stay)")
    gen.add_argument("--verbose", action="store_true", help=VERBOSE_HELP)
    gen.set_defaults(handler=_generate)

    from .formats import EPISODE_GAP_S, PLANE_TOLERANCE_M

    imp = sub.add_parser("import", formatter_class=HelpFormatter, **COMMANDS["import"])
    imp.add_argument("recordings", nargs="+", help="raw PDM files in time order, or one CHIRP file")
    imp.add_argument("--format", required=True, choices=["pdm", "chirp"], help="what the files hold")
    imp.add_argument("--out", required=True, help="pdm: energyscapes file to write (.npy); chirp: dataset folder")
    imp.add_argument("--overwrite", action="store_true", help="pdm: " + OVERWRITE_HELP)
    imp.add_argument("--channels", type=int, default=32, help="microphones in the stream (bits per word)")
    imp.add_argument("--pdm-rate", type=float, default=4.5e6, help="PDM sample rate [Hz]")
    imp.add_argument("--bit-order", choices=["lsb", "msb"], default="lsb", help="lsb: bit i of a word is channel i")
    imp.add_argument("--samples-per-ping", type=int, default=None, help="split each file into pings of this many words")
    imp.add_argument(
        "--plane-tolerance",
        type=float,
        default=PLANE_TOLERANCE_M,
        help="chirp: LiDAR points within this height of the sonar's plane make the 2D scan [m]",
    )
    imp.add_argument(
        "--episode-gap",
        type=float,
        default=EPISODE_GAP_S,
        help="chirp: a longer pause between pings starts a new episode [s]",
    )
    imp.add_argument("--set", action="append", metavar="SECTION.FIELD=VALUE", help=SET_HELP)
    imp.add_argument("--device", default="cpu", help="Warp device for the processing")
    imp.add_argument("--verbose", action="store_true", help=VERBOSE_HELP)
    imp.set_defaults(handler=_import)

    exp = sub.add_parser("export", formatter_class=HelpFormatter, **COMMANDS["export"])
    exp.add_argument("dataset", help="dataset folder (shard-*.h5)")
    exp.add_argument("--format", required=True, choices=["mcap", "chirp"], help="what to write")
    exp.add_argument("--out", required=True, help="file to write (.mcap or .h5)")
    exp.add_argument("--overwrite", action="store_true", help=OVERWRITE_HELP)
    exp.set_defaults(handler=_export)
    return parser


USER_ERRORS = (ValueError, TypeError, KeyError, OSError, MissingExtra)
"""Bad input, files or settings (SceneError and DatasetError are ValueErrors), or an optional
extra that is not installed (MissingExtra names it): one `error:` line, exit code 2; `--debug`
shows the trace. Any other ImportError is a bug and keeps its trace."""


def main(argv: list[str] | None = None) -> int:
    argv = sys.argv[1:] if argv is None else list(argv)

    def command() -> int:
        args = build_parser().parse_args([a for a in argv if a != "--debug"])  # --debug: anywhere on the line
        with interrupt_after():  # trimesh, which scenes imports, would swallow a Ctrl-C
            import scenes  # noqa: F401  (every command's scenes, datasets or engine import it)
        return args.handler(args)

    return run_command(command, argv, USER_ERRORS)


if __name__ == "__main__":
    sys.exit(main())
