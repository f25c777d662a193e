"""One `--set` grammar for both command lines: the same text gives the same value, or the same
refusal, whether `python -m acoustic_sim` applies it to its SimConfig or `python -m learn train`
to its LearnConfig.

TABLE is the grammar, one row per (text, field type, answer). Each row runs through each command
line's own settings path (acoustic_sim.settings.apply_settings on the SimConfig tree, learn.cli's
run_config on the parsed `learn train` arguments), on a probe section that holds a field of every
type, grafted onto each real root. Every field of both real trees then reads its own value back,
and one row runs through each command line as a real subprocess.
"""

from __future__ import annotations

import dataclasses
import json
import math
import subprocess
import sys
import typing
from typing import Literal

import pytest

import clitools
from acoustic_sim.config import ConfigError, LidarConfig, SimConfig
from acoustic_sim.settings import apply_settings as sim_apply_settings
from learn import cli as learn_cli
from learn import config as learn_config
from learn.augment import AugmentConfig


@dataclasses.dataclass(frozen=True, kw_only=True)
class Preset:
    """A section with one preset, as LidarConfig.multibeam_64x1024 or AugmentConfig.none."""

    size: int = 1

    @classmethod
    def small(cls) -> Preset:
        return cls(size=0)


TYPES = {
    "int": (int, 0),
    "float": (float, 0.0),
    "bool": (bool, False),
    "str": (str, ""),
    "int | None": (int | None, None),
    "float | None": (float | None, None),
    "Literal": (Literal["db", "max", "none"], "max"),
    "Literal | None": (Literal[None, "max", "db"], None),
    "tuple[float, ...]": (tuple[float, ...], ()),
    "tuple[float, float, float]": (tuple[float, float, float], (0.0, 0.0, 0.0)),
    "tuple[tuple[float, float, float], ...]": (tuple[tuple[float, float, float], ...], ()),
    "float | tuple[float, ...]": (float | tuple[float, ...], 0.0),
    "section": (Preset, Preset()),
}
"""Field type of a TABLE row -> (annotation, default) of its field in the probe section."""

FIELD = {kind: f"f{i}" for i, kind in enumerate(TYPES)}
Probe = dataclasses.make_dataclass(
    "Probe",
    [(FIELD[k], hint, dataclasses.field(default_factory=lambda d=default: d)) for k, (hint, default) in TYPES.items()],
    frozen=True,
    kw_only=True,
)


class Refused(typing.NamedTuple):
    """A row's answer when the text is refused: words the message holds (after "--set '...': ")."""

    words: str


LIST = "a list like [1, 2], each item a number"
TABLE = [
    # numbers: an int field takes integral values only, a float field any number
    ("3", "int", 3),
    ("-2", "int", -2),
    (" 7 ", "int", 7),
    ("1e3", "int", 1000),
    ("2.0", "int", 2),
    ("1.5", "int", Refused("'1.5' is not a valid value: give an integer")),
    ("true", "int", Refused("give an integer")),
    ("none", "int", Refused("'none' is not a valid value: give an integer")),
    ("nan", "int", Refused("give an integer")),
    ("3e-4", "float", 3e-4),
    ("-2", "float", -2.0),
    ("1e3", "float", 1000.0),
    (".5", "float", 0.5),
    ("nan", "float", math.nan),  # read as a number: the config itself refuses it by name
    ("NaN", "float", math.nan),
    ("inf", "float", math.inf),
    ("-Infinity", "float", -math.inf),
    ("true", "float", Refused("'true' is not a valid value: give a number")),
    ("none", "float", Refused("give a number")),
    ("[1]", "float", Refused("give a number")),
    # booleans: true or false in any case, nothing else
    ("true", "bool", True),
    ("False", "bool", False),
    ("TRUE", "bool", True),
    ("1", "bool", Refused("'1' is not a valid value: give true or false")),
    ("0", "bool", Refused("give true or false")),
    ("yes", "bool", Refused("give true or false")),
    ("no", "bool", Refused("give true or false")),
    ("none", "bool", Refused("give true or false")),
    # strings: as written, or unquoted
    ("polar_unet", "str", "polar_unet"),
    ('"two words"', "str", "two words"),
    ("'single'", "str", "single"),
    ("none", "str", "none"),
    ("3", "str", "3"),
    # null: none or null, any case, for an optional field only
    ("none", "int | None", None),
    ("null", "int | None", None),
    ("NONE", "int | None", None),
    ("5", "int | None", 5),
    ("x", "int | None", Refused("'x' is not a valid value: give an integer or none")),
    ("null", "float | None", None),
    ("1e3", "float | None", 1000.0),
    ("x", "float | None", Refused("'x' is not a valid value: give a number or none")),
    # Literals: a choice, bare or quoted, spelled as it is
    ("db", "Literal", "db"),
    ('"max"', "Literal", "max"),
    ("'db'", "Literal", "db"),
    ("none", "Literal", "none"),  # a choice named "none" where None is no choice
    ("log", "Literal", Refused("'log' is not a valid value: give one of 'db', 'max', 'none'")),
    ("DB", "Literal", Refused("give one of 'db', 'max', 'none'")),
    ("none", "Literal | None", None),
    ("max", "Literal | None", "max"),
    ("log", "Literal | None", Refused("give one of 'max', 'db' or none")),
    # tuples: JSON lists, nested, each item read as its type
    ("[1, 2]", "tuple[float, ...]", (1.0, 2.0)),
    ("[]", "tuple[float, ...]", ()),
    ("[1, NaN]", "tuple[float, ...]", (1.0, math.nan)),
    ("1", "tuple[float, ...]", Refused(f"'1' is not a valid value: give {LIST}")),
    ('[1, "a"]', "tuple[float, ...]", Refused(f"give {LIST}")),
    ("(1, 2)", "tuple[float, ...]", Refused(f"give {LIST}")),
    ("[0, 0.1, 2]", "tuple[float, float, float]", (0.0, 0.1, 2.0)),
    ("[0, 1]", "tuple[float, float, float]", Refused("give a list of 3 items: a number, a number, a number")),
    ("[[0, 0, 0], [0.1, 0, 0]]", "tuple[tuple[float, float, float], ...]", ((0.0, 0.0, 0.0), (0.1, 0.0, 0.0))),
    ("[[0, 0]]", "tuple[tuple[float, float, float], ...]", Refused("give a list like [1, 2], each item a list of 3")),
    # unions: the first type that reads the text
    ("5", "float | tuple[float, ...]", 5.0),
    ("[0, 10]", "float | tuple[float, ...]", (0.0, 10.0)),
    ("x", "float | tuple[float, ...]", Refused(f"give a number or {LIST}")),
    # sections: a preset by name
    ("small", "section", Preset.small()),
    ("big", "section", Refused("a section takes a preset (small) or section.field=value")),
]


def _with_probe(root_class):
    """`root_class` with one more section, `probe`, holding a field of every TABLE type."""
    probe = ("probe", Probe, dataclasses.field(default_factory=Probe))
    return dataclasses.make_dataclass(f"Probe{root_class.__name__}", [probe], bases=(root_class,), frozen=True)


def _sim(settings: list[str], root=None):
    """What `python -m acoustic_sim render/generate --set ...` makes of the settings."""
    return sim_apply_settings(root if root is not None else SimConfig(), settings)


def _learn(settings: list[str]):
    """What `python -m learn train --set ...` makes of the settings (its own parser and run_config)."""
    argv = ["train", "--data", "nowhere", "--out", "nowhere"]
    return learn_cli.run_config(
        learn_cli.build_parser().parse_args([*argv, *(a for s in settings for a in ("--set", s))])
    )


def _answer(apply, setting: str):
    """The value a setting gave the probe field, or the refusal (its message after the setting)."""
    try:
        root = apply([setting])
    except ValueError as err:
        prefix = f"--set {setting!r}: "
        assert str(err).startswith(prefix), str(err)
        return Refused(str(err).removeprefix(prefix)), type(err)
    path, _, _ = setting.partition("=")
    return getattr(root.probe, path.split(".")[1]), None


@pytest.mark.parametrize(("text", "kind", "want"), TABLE, ids=[f"{k}={t}" for t, k, _ in TABLE])
def test_both_command_lines_read_a_setting_alike(text, kind, want, monkeypatch):
    """The row's text set on the probe field of its type: the same value (of the same type, nan
    included: compared by repr) or the same refusal on both command lines, and the row's answer."""
    monkeypatch.setattr(learn_config, "LearnConfig", _with_probe(learn_config.LearnConfig))
    sim_root = _with_probe(SimConfig)()
    setting = f"probe.{FIELD[kind]}={text}"
    sim, sim_error = _answer(lambda s: _sim(s, sim_root), setting)
    learn, learn_error = _answer(_learn, setting)
    assert repr(sim) == repr(learn), (sim, learn)
    if isinstance(want, Refused):
        assert isinstance(sim, Refused) and want.words in sim.words, sim
        assert sim_error is ConfigError and learn_error is clitools.SettingsError  # each CLI's error class
    else:
        assert repr(sim) == repr(want), (sim, want)


def test_the_table_covers_every_type_and_both_answers():
    """Every field type of the probe has rows that read and rows that are refused (but a string,
    which takes any text)."""
    for kind in TYPES:
        answers = {isinstance(want, Refused) for _, k, want in TABLE if k == kind}
        assert answers == ({False} if kind == "str" else {False, True}), kind
    assert len(TABLE) >= 60


def _leaves(config, above: str = ""):
    """(dotted path, annotation, value) of every field that is no section."""
    hints = typing.get_type_hints(type(config))
    for f in dataclasses.fields(config):
        value = getattr(config, f.name)
        if dataclasses.is_dataclass(value):
            yield from _leaves(value, f"{above}{f.name}.")
        else:
            yield f"{above}{f.name}", hints[f.name], value


def _as_text(value) -> str:
    """A value as one would write it after `--set path=`."""
    if value is None:
        return "none"
    if isinstance(value, bool):
        return str(value).lower()
    if isinstance(value, tuple):
        return json.dumps(value)
    return value if isinstance(value, str) else repr(value)


@pytest.mark.parametrize("cli", ["acoustic_sim", "learn"])
def test_every_field_of_both_trees_reads_its_own_value_back(cli):
    """Each field of the real SimConfig and LearnConfig, set to its value as written, reads as
    exactly that value (type included), and leaves the whole tree as it was."""
    root, apply = (SimConfig(), _sim) if cli == "acoustic_sim" else (_learn([]), _learn)
    leaves = list(_leaves(root))
    kinds = {str(hint) for _, hint, _ in leaves}
    assert {"<class 'int'>", "<class 'float'>", "<class 'bool'>"} <= kinds and any("Literal" in k for k in kinds)
    for path, hint, value in leaves:
        text = _as_text(value)
        assert repr(clitools.read_value(text, hint)) == repr(value), (path, text)
        assert apply([f"{path}={text}"]) == root, path


@pytest.mark.parametrize(
    ("cli", "setting", "words"),
    [
        ("acoustic_sim", "tracer.max_bounces", "--set wants section.field=value (sections: lidar, sonar, tracer, "),
        ("learn", "train.lr", "--set wants section.field=value (sections: model, data, augment, train), got"),
        ("acoustic_sim", "=3", "--set wants section.field=value"),
        ("learn", "=3", "--set wants section.field=value"),
        ("acoustic_sim", "optics.gain=1", "no section 'optics'; the sections are lidar, sonar, tracer, processing"),
        ("learn", "optim.lr=1", "no section 'optim'; the sections are model, data, augment, train"),
        ("acoustic_sim", "tracer.rays=5", "tracer has no field 'rays'; it has max_bounces, ray_count,"),
        ("learn", "train.speed=1", "train has no field 'speed'; it has epochs, batch_size, lr,"),
        ("acoustic_sim", "processing.grid.bins=3", "processing.grid has no field 'bins'; it has range_min_m,"),
        ("acoustic_sim", "tracer.max_bounces.x=1", "tracer.max_bounces is a value, not a section"),
        ("learn", "train.lr.x=1", "train.lr is a value, not a section"),
        ("acoustic_sim", "lidar=velodyne", "a section takes a preset (hokuyo_ust20lx, multibeam_64x1024)"),
        ("learn", "augment=strong", "a section takes a preset (none) or section.field=value"),
        ("learn", "train=fast", "train is a section without presets: give train.field=value"),
        ("acoustic_sim", "processing.grid=1", "processing.grid is a section without presets"),
        ("acoustic_sim", "processing.speed_of_sound=nan", "ProcessingConfig.speed_of_sound must be finite"),
        ("learn", "train.pos_weight=nan", "train.pos_weight must be a finite number > 0, got nan"),
        ("acoustic_sim", "tracer.max_bounces=11", "0..10"),
        ("learn", "model.frames=3", "model.frames and data.frames must agree: set the window length with --frames"),
    ],
)
def test_names_and_forms_are_refused_naming_the_choices(cli, setting, words):
    """A malformed setting or an unknown name is refused naming what there is; a value the grammar
    reads but the config refuses (nan, out of range) is refused by the config, by name."""
    with pytest.raises(ValueError) as err:
        (_sim if cli == "acoustic_sim" else _learn)([setting])
    assert words in str(err.value) and setting in str(err.value)


def test_presets_and_nested_paths_apply_on_both():
    """A section preset by name and a setting below it, applied in order."""
    sim = _sim(["lidar=multibeam_64x1024", "lidar.noise=gaussian", "processing.grid.range_max_m=4"])
    assert sim.lidar == dataclasses.replace(LidarConfig.multibeam_64x1024(), noise="gaussian")
    assert sim.processing.grid.range_max_m == 4.0 and sim.lidar != SimConfig().lidar
    learn = _learn(["augment=none", "augment.mirror=0.25", "train.max_val_windows=null"])
    assert learn.augment == dataclasses.replace(AugmentConfig.none(), mirror=0.25)
    assert learn.train.max_val_windows is None


@pytest.mark.parametrize(
    ("cli", "argv"),
    [
        ("acoustic_sim", ["render", "--scene", "box_room", "--frames", "3", "--set", "tracer.max_bounces=1.5"]),
        ("learn", ["train", "--data", "nowhere", "--set", "train.epochs=1.5"]),
    ],
)
def test_a_refused_setting_is_one_error_line_from_either_command_line(cli, argv, tmp_path):
    """The TABLE's ("1.5", int) row on a real int field, as a user runs it: exit code 2 and one
    `error:` line that is the same on both command lines but for the setting's name."""
    command = [sys.executable, "-m", cli, *argv, "--out", str(tmp_path / "out")]
    done = subprocess.run(command, capture_output=True, text=True, timeout=300)
    setting = argv[-1]
    assert done.returncode == 2 and "Traceback" not in done.stderr, done.stderr[-2000:]
    assert (
        done.stderr.strip().splitlines()[-1] == f"error: --set {setting!r}: '1.5' is not a valid value: give an integer"
    )
    assert not (tmp_path / "out").exists()
