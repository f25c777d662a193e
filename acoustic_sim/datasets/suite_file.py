"""Suite files (TOML or JSON) read with every field checked: a wrong type, an unknown key or a
file that is no suite is refused naming the file and the field, before anything is planned.

`read_suite_file` returns the file's tables as plain values of the types `suites.load_suite`
builds a Suite from; the values' ranges are the Suite's, Scenario's and Physics' own checks. A
physics table's `calibration` (a fit `calibrate` wrote) is turned into its `surfaces` here.
"""

from __future__ import annotations

import dataclasses
import json
import tomllib
import typing
from pathlib import Path

import numpy as np

from clitools import read_value
from clitools.limits import input_file

from .physics import Physics

SUITE_FILE_MAX_BYTES = 1_000_000
"""A suite names its scenarios, physics and settings in a few kilobytes; a file a thousand times
larger is not a suite (and a FIFO or a device is refused before it is opened)."""

SUITE_FIELDS = {
    "base": "a suite name",
    "name": "a string",
    "description": "a string",
    "frames": "a whole number up to 2**63 - 1",  # int64, as every count a shard stores
    "episode_frames": "a whole number up to 2**63 - 1",
    "dt_s": "a number",
    "speed_m_s": "a number or [low, high]",
    "sensor_height_m": "a number or [low, high]",
    "turn_rate_rad_s": "a number or [low, high]",
    "settings": "a list of strings",
    "scenarios": "a list of tables",
    "variants": "a table of tables",
    "physics": "a table",
}
"""Each top-level key of a suite file and what it takes."""

SCENARIO_FIELDS = {"name": "a string", "builder": "a string", "params": "a table", "vary": "a table"}
SCENARIO_FIELDS |= {"weight": "a number"}
SCENARIO_FIELDS |= {"mesh": "a string", "materials": "a string", "up": "a string", "units": "a string"}  # a mesh file


def read_suite_file(path: Path, named: list[str]) -> dict:
    """The tables of suite file `path` (.toml or .json), every key known and every value of its
    type; `named` are the suites a `base` may name. Raises FileNotFoundError or ValueError naming
    the file and the field."""
    input_file(path, what="suite file", max_bytes=SUITE_FILE_MAX_BYTES, bound="a suite is a few kilobytes")
    kind = path.suffix[1:].upper()
    try:
        text = path.read_text(encoding="utf-8")
        data = tomllib.loads(text) if path.suffix == ".toml" else json.loads(text)
    except UnicodeDecodeError:
        raise ValueError(f"suite file {path} is not text (UTF-8); give a {kind} file") from None
    except (tomllib.TOMLDecodeError, json.JSONDecodeError) as err:
        raise ValueError(f"suite file {path} is not valid {kind}: {err}") from None
    except RecursionError:
        raise ValueError(
            f"suite file {path} nests lists or tables deeper than its reader can follow; a suite nests a few levels"
        ) from None
    if not isinstance(data, dict):
        raise ValueError(f"suite file {path} holds a {type(data).__name__}, not a table of suite fields")
    if unknown := sorted(set(data) - set(SUITE_FIELDS)):
        raise ValueError(f"suite file {path}: unknown keys {unknown}; allowed: {sorted(SUITE_FIELDS)}")
    for key, value in data.items():
        _check(value, SUITE_FIELDS[key], f"{path}: {key}")
    if "base" in data and data["base"] not in named:
        raise ValueError(f"{path}: base {data['base']!r} is not a suite; named suites are {named}")
    for i, scenario in enumerate(data.get("scenarios", [])):
        where = f"{path}: scenarios[{i}]"
        if unknown := sorted(set(scenario) - set(SCENARIO_FIELDS)):
            raise ValueError(f"{where}: unknown keys {unknown}; allowed: {sorted(SCENARIO_FIELDS)}")
        needed = ("name",) if "mesh" in scenario else ("name", "builder")  # a mesh file is its scene's builder
        if missing := [k for k in needed if k not in scenario]:
            or_mesh = ' (or its mesh file: mesh = "building.obj")' if "builder" in missing else ""
            raise ValueError(f"{where}: give its {' and '.join(missing)}{or_mesh}")
        for key, value in scenario.items():
            _check(value, SCENARIO_FIELDS[key], f"{where} ({scenario['name']!r}) {key}")
    tables = [("physics", data.get("physics", {}))] + [
        (f"variants.{k}", v) for k, v in data.get("variants", {}).items()
    ]
    for where, table in tables:
        _calibrated_surfaces(table, path, f"{path}: {where}")
        _check_physics(table, f"{path}: {where}")
    return data


CALIBRATION_MAX_BYTES = 1_000_000  # a fit is a few kilobytes (a loss per step, a gain per microphone)


def _calibrated_surfaces(table: dict, path: Path, where: str) -> None:
    """A physics table's `calibration = "FIT.json"` (a file `calibrate` wrote; a relative path is
    beside the suite file) becomes its `surfaces`: each fitted class's reflection R (and scattering,
    where fitted), drawn per episode from [R (1 - f), min(1, R (1 + f))] with `calibration_spread = f`
    (default 0: R itself);
    its microphones' gains and delays (`mic_gain_db`, `mic_delay_s`); and where it fitted the
    emitter's directivity, the closest piston's radius r, drawn from [r (1 - f), r (1 + f)] (`vary`);
    a fit made with an omnidirectional emitter (`sonar.emitter_pattern=omni`) simulates one too
    (its R were fitted with the paths such an emitter sends backwards). A fit made of recordings
    whose air absorbs nothing (`calibrate --no-air-absorption`) turns `air_absorption` off. A list
    of fits (several rooms of one building, one sensor) spans them: each class's R and s from the
    lowest fit's (1 - f) to the highest's (1 + f), the radius likewise, and each microphone's gain
    and delay their mean over the fits that give them."""
    spread = table.pop("calibration_spread", None)
    if "calibration" not in table:
        if spread is not None:
            raise ValueError(f"{where}: calibration_spread needs calibration = FIT.json (a file calibrate wrote)")
        return
    names = table.pop("calibration")
    if isinstance(names, str):
        names = [names]
    _check(names, "a list of strings", f"{where}.calibration")
    if not names:
        raise ValueError(f"{where}.calibration: name a fit (FIT.json) or a list of them, got an empty list")
    if spread is None:
        spread = 0.0
    _check(spread, "a number", f"{where}.calibration_spread")
    if not 0 <= spread < 1:
        raise ValueError(f"{where}.calibration_spread: a fraction of R (and s) in [0, 1), got {spread}")
    fits = [_read_fit(path.parent / name, where) for name in names]
    for name in ("mic_gain_db", "mic_delay_s"):
        given = [fit[name] for fit in fits if fit[name]]
        if given and name in table:
            raise ValueError(f"{where}: {name} and calibration both give the microphones' {name.split('_')[1]}s")
        if len({len(values) for values in given}) > 1:
            raise ValueError(f"{where}.calibration: the fits give {name} for different numbers of microphones")
        if given:
            table[name] = np.mean(given, axis=0).tolist()
    airs = {fit["air_absorption"] for fit in fits}
    if len(airs) > 1:
        raise ValueError(f"{where}.calibration: some fits were made with air absorption and some without")
    if airs == {False}:
        if table.get("air_absorption") is True:
            raise ValueError(f"{where}: air_absorption and calibration (made without air absorption) disagree")
        table["air_absorption"] = False
    radii = [fit["radius"] for fit in fits if fit["radius"] is not None]
    if radii:
        vary = table.setdefault("vary", {})
        _check(vary, "a table", f"{where}.vary")
        if "sonar.emitter_radius_m" in vary:
            raise ValueError(f"{where}: vary.sonar.emitter_radius_m and calibration both give the emitter's radius")
        vary["sonar.emitter_radius_m"] = [min(radii) * (1 - spread), max(radii) * (1 + spread)]
    patterns = sorted({fit["emitter_pattern"] for fit in fits})
    if patterns != ["piston"]:
        vary = table.setdefault("vary", {})
        _check(vary, "a table", f"{where}.vary")
        if "sonar.emitter_pattern" in vary:
            raise ValueError(f"{where}: vary.sonar.emitter_pattern and calibration both give the emitter's pattern")
        vary["sonar.emitter_pattern"] = {"choice": patterns}
    surfaces = table.setdefault("surfaces", {})
    _check(surfaces, "a table of tables", f"{where}.surfaces")
    spans: dict[tuple[str, str], list[float]] = {}
    for fit in fits:
        for cls, values in fit["classes"].items():
            for key, value in values.items():
                spans.setdefault((cls, key), []).append(value)
    for (cls, key), values in spans.items():
        if key in surfaces.get(cls, {}):
            raise ValueError(f"{where}: surfaces.{cls}.{key} and calibration both give {cls}' {key}")
        surfaces.setdefault(cls, {})[key] = [min(values) * (1 - spread), min(1.0, max(values) * (1 + spread))]


def _read_fit(fit_path: Path, where: str) -> dict:
    """What a suite takes of a fit `calibrate` wrote: per class R (and s), the microphones' gains
    [dB] and delays [s] (empty where not fitted), the nearest piston's radius [m] (or None), whether
    its air absorbed and its emitter's pattern."""
    input_file(fit_path, what="calibration", max_bytes=CALIBRATION_MAX_BYTES, bound="a fit is a few kilobytes")
    try:
        fit = json.loads(fit_path.read_text(encoding="utf-8"))
        classes = {
            cls: {k: float(values[k]) for k in ("reflection", "scattering") if k in values}
            for cls, values in fit["classes"].items()
        }
        if any("reflection" not in values for values in classes.values()):
            raise KeyError("reflection")
        radius_mm = (fit.get("directivity") or {}).get("piston_radius_mm")
        return {
            "classes": classes,
            "mic_gain_db": [float(v) for v in fit.get("mic_gain_db", [])],
            "mic_delay_s": [float(v) * 1e-6 for v in fit.get("mic_delay_us", [])],
            "radius": None if radius_mm is None else float(radius_mm) * 1e-3,
            "air_absorption": bool(fit.get("air_absorption", not fit.get("options", {}).get("no_air_absorption"))),
            "emitter_pattern": str(fit.get("sim", {}).get("sonar", {}).get("emitter_pattern", "piston")),
        }
    except (UnicodeDecodeError, json.JSONDecodeError, KeyError, TypeError, ValueError, AttributeError):
        raise ValueError(
            f"{where}.calibration: {fit_path} is not a fit `calibrate` wrote (classes with reflection)"
        ) from None


def _check(value, kind: str, where: str) -> None:
    """Refuse `value` unless it is `kind` (a description from SUITE_FIELDS or SCENARIO_FIELDS)."""
    number = isinstance(value, int | float) and not isinstance(value, bool)
    ok = {
        "a suite name": isinstance(value, str),
        "a string": isinstance(value, str),
        "a whole number up to 2**63 - 1": number and float(value).is_integer() and abs(value) <= 2**63 - 1,
        "a number": number,
        "a number or [low, high]": number or _pair(value),
        "a list of strings": isinstance(value, list) and all(isinstance(v, str) for v in value),
        "a list of tables": isinstance(value, list) and all(isinstance(v, dict) for v in value),
        "a table of tables": isinstance(value, dict) and all(isinstance(v, dict) for v in value.values()),
        "a table": isinstance(value, dict),
    }[kind]
    if not ok:
        raise ValueError(f"{where} must be {kind}, got {json.dumps(value, default=str)[:80]}")


def _pair(value) -> bool:
    return (
        isinstance(value, list)
        and len(value) == 2
        and all(isinstance(v, int | float) and not isinstance(v, bool) for v in value)
    )


def _check_physics(table: dict, where: str) -> None:
    """Refuse unknown Physics fields and values not of their type (their ranges are Physics' own
    checks): `max_bounces = "abc"` is named here, not left to a float() deep inside."""
    hints = typing.get_type_hints(Physics)
    fields = [f.name for f in dataclasses.fields(Physics)]
    if unknown := sorted(set(table) - set(fields)):
        raise ValueError(f"{where}: unknown physics fields {unknown}; Physics has {fields}")
    for key, value in table.items():
        if key in ("vary", "surfaces"):
            _check(value, "a table", f"{where}.{key}")
        elif key in ("snr_db", "temperature_c"):
            _check(value, "a number or [low, high]", f"{where}.{key}")
        else:
            try:
                read_value(json.dumps(value), hints[key])
            except ValueError as err:
                raise ValueError(f"{where}.{key}: {err}") from None
