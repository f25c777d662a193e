"""What `python -m learn --help` says: the program's description and, per command, its summary
line (help), description and examples (epilog); `cli.build_parser` adds the options."""

from clitools import examples

DESCRIPTION = (
    "The learner (PyTorch): train a network that reads LiDAR scans from sonar energyscapes on a simulated "
    "dataset, score it beside baselines, run it on recordings, export it to ONNX, and the studies (Table 2, "
    "sim-to-real) with their summaries over repeated runs. Each command's --help lists its options and ends "
    "with examples."
)
TRAIN_EXAMPLE = (
    "python -m learn train --data data/paper --out runs/unet --model polar_unet --loss bce --lr 1e-3 "
    "--batch-size 16 --max-train-windows 12000 --epochs 100 --patience 4 --no-augment --device cuda"
)
"""The recipe of the shipped model (learn/pretrained/) and the README's figures (benchmarks/learner_converged.sh)."""
PRETRAINED = "learn/pretrained/polar_unet_k5.pt"
EXAMPLES = examples(
    TRAIN_EXAMPLE,
    f"python -m learn evaluate --checkpoint {PRETRAINED} --data data/drive --out runs/eval",
)

COMMANDS = {
    "train": {
        "help": "train a model on a dataset folder",
        "description": "Train a network on a dataset folder (whole episodes held out for validation), calibrating "
        "its return threshold and keeping the best epoch: OUT holds config.json, last.pt, best.pt, history.csv "
        "and curves.png. The first example is the recipe of the shipped pretrained model.",
        "epilog": examples(
            TRAIN_EXAMPLE,
            "python -m learn train --data data/tiny --out runs/smoke --epochs 2 --device cpu",
        ),
    },
    "evaluate": {
        "help": "metrics, baselines, examples and a report",
        "description": "Score one or more checkpoints beside the echo-peak and empty baselines, overall and per "
        "scenario; OUT gets report.md, metrics.json, per_scenario.csv, per_window.csv and example pictures.",
        "epilog": examples(
            f"python -m learn evaluate --checkpoint {PRETRAINED} --data data/drive --out runs/eval",
            "python -m learn evaluate --checkpoint ours=runs/unet/best.pt --checkpoint paper=runs/paper/best.pt "
            "--data data/drive --out runs/compare",
        ),
    },
    "predict": {
        "help": "predict LiDAR images from shards or energyscapes (.npy)",
        "description": "Run a checkpoint on every window of a dataset folder or of energyscapes (.npy, N x R x A in "
        "time order): OUT (.npz) holds the predicted images and the scans read from them.",
        "epilog": examples(
            f"python -m learn predict --checkpoint {PRETRAINED} --input data/tiny --out pred.npz",
            f"python -m learn predict --checkpoint {PRETRAINED} --input energyscapes.npy --out pred.npz --png pred.png",
        ),
    },
    "export": {
        "help": "write ONNX, checked against torch",
        "description": "Write a checkpoint's network as ONNX (dynamic batch, the return threshold in its metadata), "
        "checked against torch with onnxruntime (extra onnx).",
        "epilog": examples(f"python -m learn export --checkpoint {PRETRAINED} --out unet.onnx"),
    },
    "table2": {
        "help": "the paper's Table 2 layout on the table2 suite",
        "description": "The paper's Table 2: models of window length K = 1, 3 and 5 trained on --train, and K = 5 "
        "fine-tuned on each case, scored on the table2 suite's cases (minimal, many reflectors, noisy input).",
        "epilog": examples(
            "python -m learn table2 --train data/paper --test data/table2 --out runs/table2 --device cuda"
        ),
    },
    "sim2real": {
        "help": "train per bounce variant, score on reality and other test sets",
        "description": "One model per multipath setting of a training suite (bounces_0/, bounces_1/, ...), each scored "
        "on its own validation episodes and on every window of the reality suite and other test sets, beside "
        "the echo peak there.",
        "epilog": examples(
            "python -m learn sim2real --ablation data/ablation --reality data/reality --out runs/s2r --device cuda",
            "python -m learn sim2real --ablation data/randomised --reality data/reality "
            "--test crossengine=data/crossengine --out runs/s2r_randomised --device cuda",
        ),
    },
    "sim2real-summary": {
        "help": "mean and std over repeated sim2real runs",
        "description": "Mean and std of repeated sim2real runs (e.g. one per seed), with paired differences between "
        "the variants.",
        "epilog": examples(
            "python -m learn sim2real-summary runs/s2r_seed0 runs/s2r_seed1 runs/s2r_seed2 --out runs/s2r_all"
        ),
    },
    "table2-summary": {
        "help": "Table 2 over repeated runs, with paired differences",
        "description": "Mean and std of repeated table2 runs (e.g. one per seed), with paired differences between "
        "the rows.",
        "epilog": examples(
            "python -m learn table2-summary runs/table2_seed0 runs/table2_seed1 runs/table2_seed2 --out runs/table2_all"
        ),
    },
    "seeds-summary": {
        "help": "mean and std over repeated evaluations",
        "description": "Mean and std of repeated evaluations (e.g. models of several seeds on one dataset).",
        "epilog": examples(
            "python -m learn seeds-summary runs/seed0/eval runs/seed1/eval runs/seed2/eval --out runs/seeds"
        ),
    },
}
"""Keyword arguments of each command's `add_parser`."""
