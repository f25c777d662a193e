"""The randomised suite: every draw lands in its range, is the same across variants, reaches the
simulation and is recorded; and `reality` stays disjoint from every training suite's scenes."""

import dataclasses
import inspect
import json

import h5py
import numpy as np
import pytest

import scenes
from acoustic_sim.datasets.generate import generate
from acoustic_sim.datasets.physics import Physics
from acoustic_sim.datasets.suites import SUITES, episode_drive


def _ends(spec) -> list:
    """Every value a scenario parameter can take, as (low, high) intervals or single values."""
    if isinstance(spec, dict):
        return [(v, v) for v in spec["choice"]]
    if isinstance(spec, list) and len(spec) == 2 and all(isinstance(v, int | float) for v in spec):
        return [tuple(spec)]
    return [(spec, spec)]


def _disjoint(a, b) -> bool:
    """Whether two parameter specs share no value (intervals meeting at one end count as apart)."""
    if isinstance(a, list | tuple) and isinstance(b, list | tuple) and len(a) == len(b) == 3:  # sizes
        return any(_disjoint(x, y) for x, y in zip(a, b, strict=True))
    for lo_a, hi_a in _ends(a):
        for lo_b, hi_b in _ends(b):
            if isinstance(lo_a, str) or isinstance(lo_b, str) or lo_a is None or lo_b is None:
                if lo_a == lo_b:
                    return False
            elif (lo_a < hi_b and lo_b < hi_a) or lo_a == lo_b == hi_a == hi_b:
                return False
    return True


def _params(scenario) -> dict:
    defaults = {
        k: v.default
        for k, v in inspect.signature(scenes.BUILDERS[scenario.builder]).parameters.items()
        if v.default is not inspect.Parameter.empty and k != "seed"
    }
    return defaults | scenario.params | scenario.vary


@pytest.mark.parametrize("training", ["paper", "ablation", "table2", "randomised"])
def test_reality_scenes_are_disjoint_from_every_training_suite(training):
    """Each reality scenario differs from each training scenario of its builder in at least one
    parameter's whole range: no reality scene could have been drawn for training."""
    for held_out in SUITES["reality"].scenarios:
        for seen in SUITES[training].scenarios:
            if seen.builder != held_out.builder:
                continue
            a, b = _params(held_out), _params(seen)
            apart = [k for k in a.keys() & b.keys() if _disjoint(a[k], b[k])]
            assert apart, f"reality {held_out.name} overlaps {training} {seen.name}"


def test_disjointness_check_can_fail():
    office = SUITES["paper"].scenarios[4]  # office_medium
    assert not _disjoint(_params(office)["size"], [[9.0, 12.0], [7.0, 9.0], 3.0])  # reality's old office_large
    assert _disjoint(_params(office)["size"], [[10.0, 12.0], [8.0, 9.0], 3.0])


def test_randomised_draws_are_in_range_shared_by_variants_simulated_and_recorded(tmp_path, device):
    suite = SUITES["randomised"]
    small = {
        k: dataclasses.replace(p, ray_count=500)
        for k, p in suite.variants.items()
        if k in ("bounces_0", "bounces_1to6")
    }
    polygon = [s for s in suite.scenarios if s.builder == "polygon_room"][:2]
    suite = dataclasses.replace(suite, scenarios=tuple(polygon), variants=small, episode_frames=2)
    generate(suite, tmp_path / "d", frames=4, seed=2, device=device, progress=False)
    records = {}
    for variant in small:
        with h5py.File(next((tmp_path / "d" / variant).glob("shard-*.h5"))) as f:
            records[variant] = json.loads(f.attrs["episodes"])
            heights = f["pose"][:, 2, 3]
    for flat, deep in zip(records["bounces_0"], records["bounces_1to6"], strict=True):
        assert flat["drive"] == deep["drive"] and flat["surfaces"] == deep["surfaces"]
        assert flat["draws"]["sonar.emitter_m"] == deep["draws"]["sonar.emitter_m"]
        assert 1 <= deep["draws"]["tracer.max_bounces"] <= 6 and flat["tracer_config"]["max_bounces"] == 0
        assert 0.001 <= flat["sonar_config"]["emitter_radius_m"] <= 0.02
        assert 0.15 <= flat["drive"]["sensor_height_m"] <= 0.6 and 0.2 <= flat["drive"]["speed_m_s"] <= 0.5
        walls = flat["surfaces"]["walls"]
        assert 0.5 <= walls["reflection"] <= 0.99 and 0.0 <= walls["scattering"] <= 0.5
        materials = {m["name"]: m for m in json.loads(flat["scene"])["materials"]}
        assert materials["painted_wall:walls"]["acoustic_reflection"] == walls["reflection"]
    np.testing.assert_allclose(heights[-2:], records["bounces_1to6"][-1]["drive"]["sensor_height_m"])


def test_drive_and_surface_ranges_are_checked():
    assert episode_drive({"speed_m_s": [0.2, 0.5]}, 1) == episode_drive({"speed_m_s": [0.2, 0.5]}, 1)
    with pytest.raises(ValueError, match="sensor_height_m must be >= 0"):
        dataclasses.replace(SUITES["tiny"], sensor_height_m=[-0.1, 0.3])
    with pytest.raises(ValueError, match="expected"):
        dataclasses.replace(SUITES["tiny"], speed_m_s=[0.5, 0.2])
    with pytest.raises(ValueError, match=r"energy fractions lie in 0\.\.1"):
        Physics(surfaces={"walls": {"reflection": [0.5, 1.2]}})
    with pytest.raises(ValueError, match="classes are"):
        Physics(surfaces={"roof": {"reflection": [0.5, 0.9]}})
