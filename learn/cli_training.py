"""The options of the commands that train (`learn train`, and the studies that train) and the
`LearnConfig` a run is made of: the options, whose defaults are a base config (the config classes'
or a recorded run's), then `--set`."""

from __future__ import annotations

import dataclasses


def run_config(args):
    """The run's LearnConfig: the options (whose defaults are `--config`'s file or the config
    classes'), then each `--set` in turn (`clitools`'s grammar, as `python -m acoustic_sim`'s)."""
    from clitools import apply_settings

    from .augment import AugmentConfig
    from .config import LearnConfig

    base = args.base_config
    train = dataclasses.replace(
        base.train,
        epochs=args.epochs,
        batch_size=args.batch_size,
        lr=args.lr,
        loss=args.loss,
        patience=args.patience,
        monitor=args.monitor,
        val_fraction=args.val_fraction,
        split_by=args.split_by,
        seed=args.seed,
        split_seed=args.split_seed,
        max_train_windows=args.max_train_windows,
        max_val_windows=args.max_val_windows,
        amp=not args.no_amp,
        max_minutes=args.max_minutes,
        cuda_graphs=args.cuda_graphs,
    )
    config = LearnConfig(
        model=dataclasses.replace(
            base.model, name=args.model, frames=args.frames, width=args.width, history=args.history
        ),
        data=dataclasses.replace(
            base.data, frames=args.frames, label=args.label, history=args.history, history_stride=args.history_stride
        ),
        augment=AugmentConfig.none() if args.no_augment else base.augment,
        train=train,
    )
    return apply_settings(config, args.set or ())


def add_training_options(p, base) -> None:
    """The options of the commands that train; their defaults are `base`'s (a LearnConfig)."""
    from .config import LOSSES, MONITORS, SPLITS
    from .models import MODEL_NAMES

    model, data, train = base.model, base.data, base.train
    p.set_defaults(base_config=base)
    p.add_argument("--model", default=model.name, choices=MODEL_NAMES, help="network")
    p.add_argument("--frames", type=int, default=model.frames, help="window length K")
    p.add_argument("--width", type=int, default=model.width, help="base channels of polar_unet")
    p.add_argument("--label", default=data.label, choices=["middle", "last"], help="label frame of a window")
    p.add_argument(
        "--history", type=int, default=data.history, help="polar_memory: frames before the window it also reads"
    )
    p.add_argument("--history-stride", type=int, default=data.history_stride, help="frames between two history frames")
    p.add_argument("--epochs", type=int, default=train.epochs, help="most epochs")
    p.add_argument("--batch-size", type=int, default=train.batch_size, help="windows per step")
    p.add_argument("--lr", type=float, default=train.lr, help="Adam learning rate")
    p.add_argument("--loss", default=train.loss, choices=LOSSES, help="mse (the paper) or bce (logit models)")
    p.add_argument("--patience", type=int, default=train.patience, help="epochs without a better --monitor")
    p.add_argument(
        "--monitor",
        default=train.monitor,
        choices=list(MONITORS),
        help="validation metric for best.pt and stopping (scan_f1 at 0.10 m; ssim is the paper's)",
    )
    p.add_argument(
        "--val-fraction",
        type=float,
        default=train.val_fraction,
        help="share of episodes held out for validation (early stopping and the threshold read them)",
    )
    p.add_argument("--split-by", default=train.split_by, choices=SPLITS, help="what validation holds out whole")
    p.add_argument(
        "--max-train-windows", type=int, default=train.max_train_windows, help="windows per epoch (unset: all)"
    )
    p.add_argument("--max-val-windows", type=int, default=train.max_val_windows, help="windows validated per epoch")
    p.add_argument(
        "--max-minutes", type=float, default=train.max_minutes, help="time budget per model: no epoch starts after it"
    )
    p.add_argument(
        "--seed",
        type=int,
        default=train.seed,
        help="initialisation and batch order; also the split unless --split-seed",
    )
    p.add_argument(
        "--split-seed", type=int, default=train.split_seed, help="the validation split's own seed (default: --seed)"
    )
    p.add_argument("--no-amp", action="store_true", default=not train.amp, help="no bfloat16 autocast on GPUs")
    p.add_argument(
        "--cuda-graphs",
        action="store_true",
        default=train.cuda_graphs,
        help="training steps as CUDA graphs (torch.compile; GPUs only)",
    )
    p.add_argument(
        "--no-augment",
        action="store_true",
        help="train on the windows as simulated (the paper's way); --set augment.* then adds single ones",
    )
    p.add_argument("--device", default="cpu", help="cpu or cuda[:i]")
    p.add_argument("--quiet", action="store_true", help="no progress bars (the per-epoch lines stay)")
    p.add_argument(
        "--set",
        action="append",
        metavar="SECTION.FIELD=VALUE",
        help="any config field, after the options above (repeatable; e.g. train.pos_weight=5, data.floor_db=50, "
        "augment.floor_jitter_db=10, augment=none, model.row_contrast=true, train.max_val_windows=none)",
    )
    p.add_argument(
        "--config",
        metavar="RUN/config.json",
        help="start from the settings a run recorded (to repeat it): they become the defaults of the options above",
    )
