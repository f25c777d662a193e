"""`python -m acoustic_sim calibrate`: the rig's surfaces and microphones fitted to recorded pings
(`calibrate.fit_surfaces`), written as a JSON file and a picture beside it."""

from __future__ import annotations

import argparse
import dataclasses
import json
import os
import time
from pathlib import Path

from clitools import HelpFormatter
from clitools.outputs import OVERWRITE_HELP, atomic_folder

from .cli_scene import add_scene_options, scene_from_args
from .cli_text import COMMANDS, MESH_OPTIONS, SET_HELP, VERBOSE_HELP

PATH_OPTIONS = ("recordings", "poses", "svg", "mesh", "materials", "out")


def add_calibrate_parser(sub) -> None:
    cal = sub.add_parser("calibrate", formatter_class=HelpFormatter, **COMMANDS["calibrate"])
    cal.add_argument(
        "recordings",
        help="a .npz with `poses` (N, 4, 4) and `signals` (N, mics, samples), a .npy of signals (with --poses), "
        "a CHIRP file (.h5, with odometry), or a dataset folder or shard made with generate --signals",
    )
    cal.add_argument("--poses", help="of signals in a .npy: their sensor-to-world poses (N, 4, 4) in a .npy")
    cal.add_argument("--episode", type=int, help="of a dataset: the episode (one room) to fit to")
    add_scene_options(cal, MESH_OPTIONS, default=None)
    cal.add_argument(
        "--scene-from-data",
        action="store_true",
        help="of a dataset: the room its episode's record describes (a suite's builder, or crossengine's floor "
        "plan), instead of --scene (default: box_room), --svg or --mesh",
    )
    cal.add_argument("--seed", type=int, default=0, help="seeds a builder's scene")
    cal.add_argument(
        "--frames",
        type=_frame_range,
        metavar="FIRST:STOP",
        help="of a dataset episode, .npz or .npy: only its pings FIRST .. STOP - 1 (e.g. 0:20, a drive's first "
        "two seconds, keeping the rest for testing)",
    )
    cal.add_argument("--pings", type=int, help="fit to at most this many pings, evenly spaced (20-50 suffice)")
    cal.add_argument("--max-bounces", type=int, help="secondary reflections traced (default: tracer.max_bounces)")
    cal.add_argument("--rays", type=int, help="rays per ping (default: tracer.ray_count)")
    cal.add_argument("--no-gains", action="store_true", help="keep every microphone's gain at 0 dB")
    cal.add_argument("--no-delays", action="store_true", help="keep every microphone's delay at 0")
    cal.add_argument(
        "--directivity-knots",
        type=int,
        default=0,
        metavar="N",
        help="also fit the emitter's directivity, piecewise linear between N + 1 knots from its axis to 90 deg "
        "(default 0: the nominal piston's)",
    )
    cal.add_argument(
        "--scattering",
        nargs="?",
        const="waveform",
        choices=("waveform", "energy"),
        help="also fit each surface class's scattering coefficient s, tracing scattered arrivals (diffuse rain and "
        "edge bands) beside the specular paths: slower, and needed where the room scatters (the scene's s > 0 is "
        "the start; a class with s = 0 keeps it). waveform (the default): by the signals, for recordings our "
        "engine made; energy: then s again by the echo energy per millisecond, holding each class's specular "
        "share, for recordings another engine or a real room made (their diffuse echoes share no phase with ours)",
    )
    cal.add_argument(
        "--no-air-absorption",
        action="store_true",
        help="the recordings' air does not absorb (a simulation that left it out)",
    )
    cal.add_argument(
        "--skip-ms",
        type=float,
        default=0.0,
        metavar="MS",
        help="leave each recording's first MS milliseconds out of the fit: the emitter's direct sound and ringing, "
        "which no traced path explains (a call of 2.5 ms heard at the array lasts ~2.7 ms; default 0)",
    )
    cal.add_argument("--set", action="append", metavar="SECTION.FIELD=VALUE", help=SET_HELP)
    cal.add_argument("--device", default="cpu", help="Warp device: cpu, cuda:0, ...")
    cal.add_argument("--out", default="fit.json", help="JSON file to write (and its picture, .png, beside it)")
    cal.add_argument("--overwrite", action="store_true", help=OVERWRITE_HELP)
    cal.add_argument("--verbose", action="store_true", help=VERBOSE_HELP)
    cal.set_defaults(handler=_calibrate)


def _frame_range(text: str) -> tuple[int, int]:
    first, sep, stop = text.partition(":")
    try:
        pair = int(first), int(stop)
    except ValueError:
        pair = None
    if not sep or pair is None or not 0 <= pair[0] < pair[1]:
        raise argparse.ArgumentTypeError(f"give FIRST:STOP with 0 <= FIRST < STOP (e.g. 0:20), got {text!r}")
    return pair


def _calibrate(args) -> int:
    out = Path(args.out)
    if out.suffix != ".json":
        raise ValueError(f"--out {out}: give a .json file (its picture is written beside it as .png)")
    names = [out.name, out.with_suffix(".png").name]
    inputs = [p for p in (args.recordings, args.svg, args.mesh, args.materials) if p]
    with atomic_folder(out.parent, overwrite=args.overwrite, inputs=inputs, expected=names) as stage:
        line = _calibrate_into(args, stage / out.name)
    print(line)
    return 0


def _scene(args):
    """The room the recordings were made in: a dataset episode's own, or the scene options'."""
    from .calibrate import recorded_scene

    if not args.scene_from_data:
        args.scene = args.scene or "box_room"
        return scene_from_args(args)
    options = ("scene", "svg", "mesh", "scene_arg", "up", "units", "materials")
    given = [f"--{name.replace('_', '-')}" for name in options if getattr(args, name)]
    if given:
        raise ValueError(f"--scene-from-data takes the room from the data: drop {' and '.join(given)}")
    return recorded_scene(args.recordings, args.episode)


def _calibrate_into(args, written: Path) -> str:
    import numpy as np

    from . import __version__
    from .calibrate import fit_scattering_energy, fit_surfaces, recordings_and_sonar
    from .config import SimConfig
    from .devices import check_device, quiet_warp
    from .render import render_calibration
    from .settings import apply_settings

    t0 = time.perf_counter()
    quiet_warp(not args.verbose)
    check_device(args.device)
    rig = apply_settings(SimConfig(), args.set or ())
    tracer = rig.tracer
    if args.max_bounces is not None:
        tracer = dataclasses.replace(tracer, max_bounces=args.max_bounces)
    if args.rays is not None:
        tracer = dataclasses.replace(tracer, ray_count=args.rays)
    poses, signals, sonar = recordings_and_sonar(
        args.recordings, args.pings, args.episode, args.poses, rig.sonar, args.frames
    )
    rig = dataclasses.replace(rig, sonar=sonar)  # a CHIRP file's own array
    scene = _scene(args)
    absorption = not args.no_air_absorption
    fit = fit_surfaces(
        scene,
        poses,
        signals,
        rig.sonar,
        tracer,
        fit_gains=not args.no_gains,
        fit_delays=not args.no_delays,
        directivity_knots=args.directivity_knots,
        fit_scattering=bool(args.scattering),
        absorption=absorption,
        skip_s=args.skip_ms * 1e-3,
        device=args.device,
        progress=True,
    )
    waveform = fit
    if args.scattering == "energy":
        fit = fit_scattering_energy(
            scene,
            poses,
            signals,
            rig.sonar,
            fit,
            tracer,
            absorption=absorption,
            skip_s=args.skip_ms * 1e-3,
            device=args.device,
            progress=True,
        )
    middle = len(poses) // 2
    panels = _before_and_after(scene, fit, poses[middle], signals[middle], rig, tracer, absorption, args.device)
    render_calibration(fit, panels, rig.processing.grid, written.with_suffix(".png"))
    options = {k: v for k, v in vars(args).items() if not callable(v)}
    for name in PATH_OPTIONS:  # as the learner records paths: relative to where it ran, never a machine's own
        if options.get(name):
            options[name] = os.path.relpath(Path(options[name]).absolute())
    record = {
        "classes": _classes_record(fit),
        "mic_gain_db": np.round(fit.mic_gain_db, 4).tolist(),
        "mic_delay_us": np.round(fit.mic_delay_s * 1e6, 5).tolist(),
        "directivity": {
            "angle_deg": fit.directivity_deg.tolist(),
            "fitted": np.round(fit.directivity, 5).tolist(),
            "nominal": np.round(fit.directivity_nominal, 5).tolist(),
            "piston_radius_mm": round(fit.piston_radius_m(rig.sonar) * 1e3, 3) if len(fit.directivity) else None,
        },
        "energy": _energy_record(fit.energy, waveform),
        "air_absorption": absorption,  # a suite naming this fit simulates the same air
        "loss": fit.loss,
        "signatures": fit.signatures,
        "pings": len(poses),
        "scene": scene.describe(),
        "sim": dataclasses.replace(rig, tracer=tracer).to_dict(),
        "options": options,
        "package_version": __version__,
        "created": time.strftime("%Y-%m-%dT%H:%M:%S%z"),
    }
    written.write_text(json.dumps(record, indent=1))
    fitted = ", ".join(
        f"{n} {r:.3f} (was {r0:.3f})" for n, r, r0 in zip(fit.classes, fit.reflection, fit.nominal, strict=True)
    )
    scattering = ", ".join(f"{n} {s:.3f} (was {s0:.3f})" for n, (s, s0) in fit.fitted_scattering().items())
    fitted += f"; s {scattering}" if scattering else ""
    return (
        f"{len(poses)} pings, {fit.signatures} signatures: R {fitted}; relative error {fit.loss[0]:.3g} -> "
        f"{fit.loss[-1]:.3g}; wrote {args.out} and its picture in {time.perf_counter() - t0:.1f} s"
    )


def _classes_record(fit) -> dict:
    """Per fitted class its R and where it started, and its s and start where s was fitted."""
    record = {
        name: {"reflection": float(r), "nominal": float(r0)}
        for name, r, r0 in zip(fit.classes, fit.reflection, fit.nominal, strict=True)
    }
    for name, (s, s0) in fit.fitted_scattering().items():
        record[name] |= {"scattering": s, "scattering_nominal": s0}
    return record


def _energy_record(energy, waveform) -> dict | None:
    """Where the energy stage ran: the waveform stage's classes, and the bins (recorded, simulated
    before and after, noise)."""
    if energy is None:
        return None
    rounded = {k: [float(f"{v:.5g}") for v in getattr(energy, k)] for k in ("recorded", "before", "after")}
    start_ms = [round(float(t) * 1e3, 4) for t in energy.bin_start_s]
    loss = [energy.loss_before, energy.loss_after]
    noise = float(f"{energy.noise:.5g}")
    return {
        "waveform": _classes_record(waveform),
        "bin_start_ms": start_ms,
        **rounded,
        "noise_per_bin": noise,
        "loss": loss,
    }


def _before_and_after(scene, fit, pose, recorded, rig, tracer, absorption: bool, device) -> list:
    """One ping's energyscape as recorded and as simulated with the scene's own and the fitted
    coefficients, gains and delays, each beamformed for the nominal array as the recording is:
    (title, energyscape (R, A))."""
    import numpy as np

    from .engine.beamform import energyscape
    from .engine.sonar import Sonar

    specular = dataclasses.replace(tracer, scattering=bool(fit.scattering_fitted.any()))  # as the fit traced
    panels = [("recorded", recorded)]
    for title, room, array in (
        ("simulated, nominal", scene, rig.sonar),
        ("simulated, fitted", fit.scene(scene), fit.sonar(rig.sonar)),
    ):
        sonar = Sonar(array, specular, device=device)
        panels.append((title, sonar.record(sonar.trace(room, pose), pose_count=1, absorption=absorption)[0]))
    signals = np.stack([np.asarray(s, np.float32) for _, s in panels])  # one beamformer call for the three
    images = energyscape(signals, rig.sonar, rig.processing, device=device)
    return [(title, image) for (title, _), image in zip(panels, images, strict=True)]
