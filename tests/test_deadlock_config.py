"""The deadlock and detour rules are set from a scenario file's ``deadlock:`` section: the section
mirrors :class:`DeadlockPolicy` field by field, is validated like every other section, and is what
the closed loop's resolver runs with."""

from __future__ import annotations

import dataclasses
import re

import numpy as np
import pytest
import yaml
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from swarmpc.config import DeadlockConfig, ScenarioError, load_scenario, scenario_from_dict, scenario_to_yaml
from swarmpc.scenarios import builtin_scenario
from swarmpc.simulation.controller import deadlock_resolver
from swarmpc.simulation.deadlock import DeadlockPolicy, DeadlockResolver
from swarmpc.simulation.loop import simulate

AGENTS = [{"start": [-1.0, 0.0], "goal": [1.0, 0.0]}, {"start": [1.0, 0.2], "goal": [-1.0, 0.2]}]


def _scenario(deadlock: object) -> object:
    return scenario_from_dict({"agents": AGENTS, "deadlock": deadlock})


# ----------------------------------------------------------------------------------- the mapping
def test_the_section_has_the_policy_fields_with_the_policy_defaults():
    policy_fields = {field.name: field.default for field in dataclasses.fields(DeadlockPolicy)}
    section = DeadlockConfig()
    assert set(DeadlockConfig.model_fields) == set(policy_fields)
    for name, default in policy_fields.items():
        value = getattr(section, name)
        assert value == default and type(value) is type(default), name
    assert DeadlockPolicy.from_config(section) == DeadlockPolicy()


def test_every_field_is_described():
    for name, info in DeadlockConfig.model_fields.items():
        assert info.description, name


def test_a_scenario_without_the_section_runs_the_library_default_policy():
    scn = scenario_from_dict({"agents": AGENTS})
    assert scn.deadlock == DeadlockConfig()
    assert deadlock_resolver(scn).policy == DeadlockPolicy()


def test_the_resolver_of_a_scenario_runs_its_section():
    scn = _scenario({"patience": 7, "angle_deg": 60, "progress_window": 20, "free_goal_patience": None,
                     "side_steps": False, "enabled": False})
    policy = deadlock_resolver(scn).policy
    assert policy == DeadlockPolicy(patience=7, angle_deg=60.0, progress_window=20, free_goal_patience=None,
                                    side_steps=False, enabled=False)


def test_the_library_constructor_keeps_working():
    policy = DeadlockPolicy(patience=9, untie_knots=False)
    assert DeadlockResolver(2, 2, policy).policy is policy
    assert DeadlockResolver(2, 2).policy == DeadlockPolicy()


# ----------------------------------------------------------------------------------- the file
SECTION = """\
deadlock:
  enabled: true
  patience: 6
  hold: 20
  angle_deg: 60.0
  progress_window: 25
  free_goal_patience: null
  untie_knots: false
"""


def test_a_deadlock_section_round_trips_through_a_file(tmp_path):
    text = yaml.safe_dump({"agents": AGENTS}, sort_keys=False) + SECTION
    file = tmp_path / "s.yaml"
    file.write_text(text)
    scn = load_scenario(file)
    assert (scn.deadlock.patience, scn.deadlock.hold, scn.deadlock.angle_deg) == (6, 20, 60.0)
    assert scn.deadlock.progress_window == 25 and scn.deadlock.free_goal_patience is None
    assert scn.deadlock.untie_knots is False and scn.deadlock.lift == DeadlockConfig().lift
    # written out with every default filled in, and read back equal
    written = scenario_to_yaml(scn)
    assert set(yaml.safe_load(written)["deadlock"]) == set(DeadlockConfig.model_fields)
    again = tmp_path / "again.yaml"
    again.write_text(written)
    assert load_scenario(again) == scn
    assert scenario_to_yaml(load_scenario(again)) == written


def test_with_updates_reaches_the_section():
    scn = scenario_from_dict({"agents": AGENTS}).with_updates(**{"deadlock.enabled": False})
    assert scn.deadlock.enabled is False and scn.deadlock.patience == DeadlockPolicy().patience


# ----------------------------------------------------------------------------------- validation
@pytest.mark.parametrize(
    ("section", "message"),
    [
        ({"patience": 0}, "deadlock.patience: Input should be greater than or equal to 1"),
        ({"patience": 2.5}, "deadlock.patience: Input should be a valid integer"),
        ({"patience": True}, "deadlock.patience: expected an integer, got a boolean"),
        ({"lonely_patience": "12"}, "deadlock.lonely_patience: expected an integer, got text"),
        ({"hold": 10**30}, "deadlock.hold: Input should be less than or equal to 100000"),
        ({"escalate_after": -1}, "deadlock.escalate_after: Input should be greater than or equal to 0"),
        ({"progress_window": 0}, "deadlock.progress_window: Input should be greater than or equal to 1"),
        ({"free_goal_patience": -1}, "deadlock.free_goal_patience: Input should be greater than or equal to 0"),
        ({"speed_threshold": 0}, "deadlock.speed_threshold: Input should be greater than 0"),
        ({"detour": -1.0}, "deadlock.detour: Input should be greater than 0"),
        ({"lift": float("inf")}, "deadlock.lift: must be finite, got inf"),
        ({"neighbour_radius": float("nan")}, "deadlock.neighbour_radius: must be finite, got nan"),
        ({"approach_radius": 1e9}, "deadlock.approach_radius: magnitude must be <= 1e+06"),
        ({"angle_deg": 181}, "deadlock.angle_deg: Input should be less than or equal to 180"),
        ({"corridor_margin": -0.1}, "deadlock.corridor_margin: Input should be greater than or equal to 0"),
        ({"enabled": 0}, "deadlock.enabled: expected true or false, got a number"),
        ({"untie_knots": "yes"}, "deadlock.untie_knots: expected true or false, got text"),
        ({"patiense": 4}, "deadlock.patiense: unknown key"),
        ("off", "deadlock: Input should be a valid dictionary"),
    ],
)
def test_a_bad_value_is_one_line_naming_the_field(section, message):
    with pytest.raises(ScenarioError) as caught:
        _scenario(section)
    text = str(caught.value)
    assert "\n" not in text and text.startswith(message), text


_values = st.one_of(st.floats(allow_nan=True, allow_infinity=True), st.integers(-3, 10**7), st.booleans(),
                   st.none(), st.text(max_size=3), st.lists(st.integers(0, 3), max_size=2))
_sections = st.dictionaries(st.sampled_from([*DeadlockConfig.model_fields, "bogus"]), _values, max_size=4)


@settings(max_examples=200, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(_sections)
def test_random_sections_validate_or_fail_with_one_line_naming_a_key(section):
    try:
        scn = _scenario(section)
    except ScenarioError as err:
        text = str(err)
        assert "\n" not in text
        key = re.match(r"[^.\[]*", text.split(": ", 1)[0].removeprefix("deadlock.")).group(0)
        assert text.startswith("deadlock.") and key in section, text
    else:
        assert DeadlockPolicy.from_config(scn.deadlock) == DeadlockPolicy(**{**dataclasses.asdict(DeadlockPolicy()),
                                                                              **section})


def test_a_bad_value_in_a_file_names_the_field(tmp_path):
    file = tmp_path / "bad.yaml"
    file.write_text(yaml.safe_dump({"agents": AGENTS}) + "deadlock: {hold: -3}\n")
    with pytest.raises(ScenarioError, match=r"^deadlock\.hold: Input should be greater than or equal to 1$"):
        load_scenario(file)


# ----------------------------------------------------------------------------------- behaviour
def _head_on_pair(keep_right: bool = False):
    """circle M = 2 (centralised): two agents swapping head-on, which meet and stop nose to nose
    unless they keep right; the reactive rule detours them within the run (tests/test_deadlock.py)."""
    updates = {"solver.method": "centralized", "stop.max_steps": 300}
    return builtin_scenario("circle", agents=2).with_updates(
        **updates, **({} if keep_right else {"deadlock.keep_right_deg": 0.0}))


def test_the_reactive_rule_untangles_a_head_on_pair():
    summary = simulate(_head_on_pair()).summary
    assert summary["all_reached"] and summary["collisions"] == 0
    assert summary["deadlocks"] >= 1 and summary["steps"] < 300


def test_keeping_right_by_default_the_head_on_pair_passes_without_a_jam_and_sooner():
    reactive = simulate(_head_on_pair()).summary
    default = simulate(_head_on_pair(keep_right=True)).summary
    assert default["all_reached"] and default["collisions"] == 0
    assert default["deadlocks"] == 0 and default["steps"] < reactive["steps"]


@pytest.mark.parametrize(
    "section",
    [{"enabled": False}, {"patience": 100_000, "lonely_patience": 100_000}],
    ids=["disabled", "endless-patience"],  # keep_right_deg: 0 in _head_on_pair
)
def test_without_the_rule_the_head_on_pair_stays_jammed(section):
    scn = _head_on_pair()
    jammed = scn.with_updates(**{f"deadlock.{key}": value for key, value in section.items()})
    result = simulate(jammed)
    assert not result.summary["all_reached"] and result.summary["deadlocks"] == 0
    assert result.summary["collisions"] == 0
    # at rest, nose to nose, each still about a radius or more from its goal
    final = result.states[-1]
    goals = jammed.goal_states()
    assert np.linalg.norm(final[:, 2:], axis=1).max() < 0.05
    assert np.linalg.norm(final[:, :2] - goals[:, :2], axis=1).min() > 1.0
