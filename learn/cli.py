"""Command line: `python -m learn COMMAND ...` (train, evaluate, predict, export, the studies and their
summaries); handlers import the heavy modules themselves."""

from __future__ import annotations

import argparse
import json
import sys
import time

from clitools import HelpFormatter, counted, run_command
from clitools.outputs import OVERWRITE_HELP, atomic_folder

from . import MissingExtra
from .cli_text import COMMANDS, DESCRIPTION, EXAMPLES
from .cli_training import add_training_options, run_config


def _train(args) -> int:
    from .train import train

    summary = train(
        args.data,
        args.out,
        run_config(args),
        device=args.device,
        resume=args.resume,
        folds=args.folds,
        progress=not args.quiet,
        init_from=args.init_from,
        overwrite=args.overwrite,
        tensorboard=args.tensorboard,
        inputs=(args.config,),
    )
    if summary:
        from .progress import summary_line

        for s in summary["folds"] if "folds" in summary else [summary]:
            print(summary_line(s))
    return 0


def _evaluate(args) -> int:
    from .evaluate import evaluate
    from .odometry import OdometryNoise

    inputs = [*(c.partition("=")[2] or c for c in args.checkpoint), args.data]  # --checkpoint NAME=PATH or PATH
    with atomic_folder(args.out, overwrite=args.overwrite, inputs=inputs, expected=["metrics.json"]) as stage:
        report = evaluate(
            args.checkpoint,
            args.data,
            stage,
            device=args.device,
            split=args.split,
            from_frame=args.from_frame,
            threshold=args.threshold,
            progress=not args.quiet,
            odometry_noise=OdometryNoise.from_drift(args.odometry_drift),
            odometry_seed=args.odometry_seed,
            grids=not args.no_grids,
        )
    skipped = f", from frame {args.from_frame} of each episode" if args.from_frame else ""
    print(f"{counted(report['windows'], 'window')} ({report['split']} split{skipped}) of {report['data']}:")
    for name, r in report["results"].items():
        m = r["all"]
        print(
            f"  {name:>12}: scan F1 {m['scan_f1']['mean']:.3f}, beam accuracy {m['beam_accuracy']['mean']:.3f}, "
            f"missed {m['missed']['mean']:.2f}, false {m['false']['mean']:.2f}, Chamfer {m['chamfer_m']['mean']:.3f} m"
        )
    print(f"report: {args.out}/report.md")
    return 0


def _predict(args) -> int:
    from .predict import prediction_summary, run_predict

    t0 = time.perf_counter()
    if args.stream:  # frame by frame with state, as a robot runs it (learn.stream)
        from .stream_predict import run_predict_stream as run_predict
    run = run_predict(
        args.checkpoint,
        args.input,
        args.out,
        device=args.device,
        png=args.png,
        threshold=args.threshold,
        mcap=args.mcap,
        overwrite=args.overwrite,
        progress=not args.quiet,
    )
    print(prediction_summary(run, args.input, time.perf_counter() - t0))
    return 0


def _export(args) -> int:
    from .checkpoint import load_checkpoint
    from .export import export_onnx
    from .models import trained_elevations

    model, ckpt = load_checkpoint(args.checkpoint)
    info = export_onnx(
        model,
        args.out,
        frames=ckpt["data_config"]["frames"],
        range_count=len(ckpt["range_m"]),
        azimuth_count=len(ckpt["azimuth_rad"]),
        elevation_deg=trained_elevations(ckpt["model_config"].get("elevation_deg")),
        threshold=args.threshold if args.threshold is not None else ckpt.get("threshold"),
        verbose=args.verbose,
        overwrite=args.overwrite,
        inputs=(args.checkpoint,),
    )
    print(json.dumps(info))
    return 0


def _table2(args) -> int:
    from .studies import table2

    table2(
        args.train,
        args.test,
        args.out,
        config=run_config(args),
        device=args.device,
        progress=not args.quiet,
    )
    print(f"wrote {args.out}/table2.md")
    return 0


def _sim2real(args) -> int:
    from .studies import sim2real

    sim2real(
        args.ablation,
        {"reality": args.reality, **_named_folders(args.test or [])},
        args.out,
        config=run_config(args),
        device=args.device,
        progress=not args.quiet,
        score_only=args.score_only,
        variants=args.variants.split(",") if args.variants else None,
    )
    print(f"wrote {args.out}/sim2real.md")
    return 0


def named_folder(text: str) -> tuple[str, str]:
    """A named test set from the command line, `NAME=FOLDER`, as (name, folder); ValueError
    when either part is missing. The study analyses in benchmarks/ read theirs with it too."""
    name, sep, folder = text.partition("=")
    if not sep or not name or not folder:
        raise ValueError(f"give NAME=FOLDER, got {text!r}")
    return name, folder


def _named_folders(items: list[str]) -> dict:
    named = {}
    for item in items:
        name, _, folder = item.partition("=")  # as named_folder reads it
        if not (name and folder) or name in named or name == "reality":
            raise ValueError(f"--test wants NAME=FOLDER with a new name (not reality), got {item!r}")
        named[name] = folder
    return named


def _sim2real_summary(args) -> int:
    from .studies import sim2real_summary

    sim2real_summary(args.runs, args.out, overwrite=args.overwrite)
    print(f"wrote {args.out}/sim2real.md")
    return 0


def _table2_summary(args) -> int:
    from .studies import table2_summary

    table2_summary(args.runs, args.out, overwrite=args.overwrite)
    print(f"wrote {args.out}/table2.md")
    return 0


def _seeds_summary(args) -> int:
    from .studies import seeds_summary

    seeds_summary(args.reports, args.out, overwrite=args.overwrite)
    print(f"wrote {args.out}/summary.md")
    return 0


def _threshold_option(p) -> None:
    help_ = "return threshold in (0, 1] (default: the checkpoint's calibrated one)"
    p.add_argument("--threshold", type=float, default=None, help=help_)


def build_parser(base=None) -> argparse.ArgumentParser:
    """The command line; `base` (a LearnConfig, default: the config classes' defaults) gives the
    defaults of the training options."""
    if base is None:
        from .config import LearnConfig

        base = LearnConfig()
    fmt = HelpFormatter
    parser = argparse.ArgumentParser(
        prog="python -m learn", description=DESCRIPTION, formatter_class=fmt, epilog=EXAMPLES
    )
    common = argparse.ArgumentParser(add_help=False)
    common.add_argument("--debug", action="store_true", help="show the full trace of an error")
    sub = parser.add_subparsers(dest="command", required=True, metavar="COMMAND")
    p = sub.add_parser("train", formatter_class=fmt, parents=[common], **COMMANDS["train"])
    p.add_argument("--data", required=True, help="dataset folder (shard-*.h5)")
    p.add_argument("--out", required=True, help="run folder (checkpoints, history, curves)")
    p.add_argument("--folds", type=int, default=1, help="k-fold cross-validation over episodes")
    p.add_argument("--resume", action="store_true", help="continue from OUT/last.pt")
    p.add_argument("--overwrite", action="store_true", help="replace a run already in OUT")
    p.add_argument("--init-from", default=None, help="start from this checkpoint's weights (fine-tuning)")
    p.add_argument(
        "--tensorboard", action="store_true", help="also log every epoch (metrics, example windows) in OUT/tensorboard"
    )
    add_training_options(p, base)
    p.set_defaults(handler=_train)
    p = sub.add_parser("evaluate", formatter_class=fmt, parents=[common], **COMMANDS["evaluate"])
    p.add_argument(
        "--checkpoint",
        required=True,
        action="append",
        help="a .pt file; repeat (as NAME=PATH) to compare models side by side; the first draws the examples",
    )
    p.add_argument("--data", required=True, help="dataset folder")
    p.add_argument("--out", required=True, help="report folder")
    p.add_argument("--overwrite", action="store_true", help=OVERWRITE_HELP)
    p.add_argument("--split", default="auto", choices=["auto", "val", "all"], help="auto: val on the training data")
    p.add_argument(
        "--from-frame",
        type=int,
        default=0,
        metavar="N",
        help="score only the windows starting N or more frames into their episode (e.g. past the pings a "
        "calibration was fitted to)",
    )
    p.add_argument("--device", default="cpu", help="cpu or cuda[:i]")
    p.add_argument("--quiet", action="store_true", help="no progress bars")
    p.add_argument(
        "--odometry-drift",
        type=float,
        default=0.0,
        help="models with memory and the occupancy grids read poses as odometry with this drift (0.05: 5 %%)",
    )
    p.add_argument("--odometry-seed", type=int, default=0, help="seed of the odometry drift, drawn per episode")
    p.add_argument("--no-grids", action="store_true", help="leave out the occupancy-grid baselines")
    _threshold_option(p)
    p.set_defaults(handler=_evaluate)
    p = sub.add_parser("predict", formatter_class=fmt, parents=[common], **COMMANDS["predict"])
    p.add_argument("--checkpoint", required=True, help="the model (.pt) to run")
    p.add_argument(
        "--input", required=True, help="dataset folder, or .npy of energyscapes (N, R, A) or (N, E, R, A) in time order"
    )
    p.add_argument("--out", required=True, help=".npz to write")
    p.add_argument(
        "--png",
        default=None,
        help="also draw four predictions spread over the input here (.png), beside their LiDAR truth where the "
        "input holds one",
    )
    p.add_argument(
        "--mcap", default=None, help="also write the scans as ROS 2 LaserScans on /scan_pred (.mcap; extra ros)"
    )
    p.add_argument("--overwrite", action="store_true", help=OVERWRITE_HELP)
    p.add_argument("--device", default="cpu", help="cpu or cuda[:i]")
    p.add_argument("--quiet", action="store_true", help="no progress bar (the summary line stays)")
    p.add_argument(
        "--stream",
        action="store_true",
        help="run frame by frame with state, as a robot would (a model with memory needs poses); --input may "
        "also be an MCAP bag with /sonar/energyscape (or one topic per elevation) and /tf; --mcap then holds /tf too",
    )
    _threshold_option(p)
    p.set_defaults(handler=_predict)
    p = sub.add_parser("export", formatter_class=fmt, parents=[common], **COMMANDS["export"])
    p.add_argument("--checkpoint", required=True, help="the model (.pt) to export")
    p.add_argument("--out", required=True, help=".onnx to write")
    p.add_argument("--overwrite", action="store_true", help=OVERWRITE_HELP)
    p.add_argument("--verbose", action="store_true", help="show torch's exporter warnings")
    _threshold_option(p)
    p.set_defaults(handler=_export)
    p = sub.add_parser("table2", formatter_class=fmt, parents=[common], **COMMANDS["table2"])
    p.add_argument("--train", required=True, help="training dataset (e.g. the paper suite)")
    p.add_argument("--test", required=True, help="table2 suite folder (minimal/, many/, noisy/)")
    p.add_argument("--out", required=True, help="folder for the runs, table2.md and table2.json")
    add_training_options(p, base)
    p.set_defaults(handler=_table2)
    p = sub.add_parser("sim2real", formatter_class=fmt, parents=[common], **COMMANDS["sim2real"])
    p.add_argument(
        "--ablation",
        required=True,
        help="training suite with bounce variants: ablation or randomised (bounces_0/, bounces_1/, ...)",
    )
    p.add_argument("--reality", required=True, help="reality suite folder")
    p.add_argument(
        "--test",
        action="append",
        metavar="NAME=FOLDER",
        help="another test set to score every model on, e.g. crossengine=data/crossengine (repeatable)",
    )
    p.add_argument(
        "--score-only",
        action="store_true",
        help="train nothing: score the runs already in OUT/VARIANT (trained by `learn train`)",
    )
    p.add_argument("--variants", help="comma-separated variants to train or score (default: every one in --ablation)")
    p.add_argument("--out", required=True, help="folder for one run per variant, sim2real.md and sim2real.json")
    add_training_options(p, base)
    p.set_defaults(handler=_sim2real)
    p = sub.add_parser("sim2real-summary", formatter_class=fmt, parents=[common], **COMMANDS["sim2real-summary"])
    p.add_argument("runs", nargs="+", help="sim2real output folders (e.g. one per seed)")
    p.add_argument("--out", required=True, help="folder for sim2real.md and its picture")
    p.add_argument("--overwrite", action="store_true", help=OVERWRITE_HELP)
    p.set_defaults(handler=_sim2real_summary)
    p = sub.add_parser("table2-summary", formatter_class=fmt, parents=[common], **COMMANDS["table2-summary"])
    p.add_argument("runs", nargs="+", help="table2 output folders (e.g. one per seed)")
    p.add_argument("--out", required=True, help="folder for table2.md")
    p.add_argument("--overwrite", action="store_true", help=OVERWRITE_HELP)
    p.set_defaults(handler=_table2_summary)
    p = sub.add_parser("seeds-summary", formatter_class=fmt, parents=[common], **COMMANDS["seeds-summary"])
    p.add_argument("reports", nargs="+", help="evaluate output folders (metrics.json), e.g. one per seed")
    p.add_argument("--out", required=True, help="folder for summary.md")
    p.add_argument("--overwrite", action="store_true", help=OVERWRITE_HELP)
    p.set_defaults(handler=_seeds_summary)
    return parser


USER_ERRORS = (ValueError, TypeError, KeyError, OSError, FloatingPointError, MissingExtra)
"""Bad input, files or settings, or a missing optional extra: one `error:` line and exit code 2
(the trace with --debug)."""


def main(argv: list[str] | None = None) -> int:
    argv = sys.argv[1:] if argv is None else list(argv)

    def command() -> int:
        args = build_parser(_recorded_config(argv)).parse_args(argv)  # --config's file is read before parsing
        return args.handler(args)

    return run_command(command, argv, USER_ERRORS)


def _recorded_config(argv: list[str]):
    """The LearnConfig of `--config FILE` when the command line names one (before the parser is
    built: its settings are the options' defaults), else None."""
    first = argparse.ArgumentParser(add_help=False)
    first.add_argument("--config")
    named = first.parse_known_args(argv)[0].config
    if named is None:
        return None
    from .config import read_run_config

    return read_run_config(named)


if __name__ == "__main__":
    sys.exit(main())
