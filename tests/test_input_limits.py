"""Bounded, strict scenario input: every hostile or mistaken input is refused before any work,
quickly, with one line that starts with the field (or the file) it is about."""

from __future__ import annotations

import copy
import os
import subprocess
import sys
import threading
import time
from pathlib import Path
from typing import Any

import numpy as np
import pytest
import yaml
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

import swarmpc.scenarios as scenarios_module
from swarmpc.config import (
    MAX_AGENTS,
    MAX_FACETS,
    MAX_FILE_BYTES,
    MAX_HORIZON,
    MAX_OBSTACLES,
    MAX_SEED,
    MAX_STEPS,
    MAX_YAML_DEPTH,
    Scenario,
    ScenarioError,
    load_scenario,
    parse_yaml_text,
    scenario_from_dict,
)
from swarmpc.scenarios import BUILTINS, builtin_parameters, builtin_scenario, packing_bound
from swarmpc.simulation.loop import simulate

EXAMPLES = Path(__file__).resolve().parents[1] / "examples"
SWARMPC = Path(sys.executable).with_name("swarmpc")
BASE: dict[str, Any] = {"agents": [{"start": [-1, -1], "goal": [1, 1]}, {"start": [1, -1], "goal": [-1, 1]}]}

# the classic "billion laughs": a few hundred bytes that expand to 9^9 (~ 4 x 10^8) strings
LETTERS = "abcdefghi"
BILLION_LAUGHS = 'a: &a ["lol","lol","lol","lol","lol","lol","lol","lol","lol"]\n' + "".join(
    f"{LETTERS[k]}: &{LETTERS[k]} [{','.join([f'*{LETTERS[k - 1]}'] * 9)}]\n" for k in range(1, 9)
)


def with_(**changes: Any) -> dict[str, Any]:
    return {**copy.deepcopy(BASE), **changes}


def refused(data: Any) -> str:
    """The message of the ScenarioError ``data`` raises (asserting it is one line)."""
    with pytest.raises(ScenarioError) as caught:
        scenario_from_dict(data)
    message = str(caught.value)
    assert message and len(message.splitlines()) == 1, message
    return message


def refused_file(path: Path) -> str:
    with pytest.raises(ScenarioError) as caught:
        load_scenario(path)
    message = str(caught.value)
    assert len(message.splitlines()) == 1, message
    return message


def write(tmp_path: Path, text: str, name: str = "s.yaml") -> Path:
    path = tmp_path / name
    path.write_text(text)
    return path


# ------------------------------------------------------------------ the YAML layer
class TestYamlBounds:
    def test_billion_laughs_is_refused_quickly(self, tmp_path):
        assert len(BILLION_LAUGHS) < 600
        path = write(tmp_path, BILLION_LAUGHS)
        started = time.perf_counter()
        message = refused_file(path)
        assert time.perf_counter() - started < 2.0
        assert message.startswith(f"{path}: ") and "aliases expanded" in message

    def test_moderate_aliases_still_load(self):
        text = "agents:\n- &p {start: [0, 0], goal: [1, 1]}\n- {start: [3, 3], goal: [5, 5]}\n"
        assert parse_yaml_text(text, "x.yaml")["agents"][0] == {"start": [0, 0], "goal": [1, 1]}

    @pytest.mark.parametrize("depth", [MAX_YAML_DEPTH + 1, 2000, 200_000])
    def test_deep_nesting_is_refused_without_recursion_error(self, tmp_path, depth):
        path = write(tmp_path, "agents: " + "[" * depth + "]" * depth)
        message = refused_file(path)
        assert message.startswith(f"{path}: nested deeper than {MAX_YAML_DEPTH} levels")

    def test_nesting_at_the_bound_parses(self):
        depth = MAX_YAML_DEPTH - 1  # the top-level mapping is one level
        data = parse_yaml_text("x: " + "[" * depth + "]" * depth, "x.yaml")
        assert isinstance(data["x"], list)

    def test_aliases_cannot_deepen_past_the_bound(self):
        half = MAX_YAML_DEPTH // 2 + 2
        text = f"a: &a {'[' * half}1{']' * half}\nb: {'[' * half}*a{']' * half}\n"
        with pytest.raises(ScenarioError, match="nested deeper"):
            parse_yaml_text(text, "x.yaml")

    def test_an_alias_inside_its_own_anchor_is_refused(self):
        with pytest.raises(ScenarioError, match="x.yaml: an alias refers to a node that contains it"):
            parse_yaml_text("a: &x [1, *x]\n", "x.yaml")

    @pytest.mark.parametrize("text,key,first,line", [
        ("dt: 0.1\nhorizon: 5\ndt: 0.2\n", "'dt'", 1, 3),
        ("solver:\n  rho: 1\n  tol: 0.1\n  rho: 2\n", "'rho'", 2, 4),
        ("agents:\n- {start: [0, 0], goal: [1, 1], start: [2, 2]}\n", "'start'", 2, 2),
        ("1: a\n1.0: b\n", "1.0", 1, 2),  # equal as Python keys
    ])
    def test_duplicate_keys_name_the_key_and_line(self, text, key, first, line):
        with pytest.raises(ScenarioError) as caught:
            parse_yaml_text(text, "d.yaml")
        assert str(caught.value) == f"d.yaml: duplicate key {key} (first at line {first}) at line {line}"

    def test_merge_keys_may_override(self):
        data = parse_yaml_text("base: &b {rho: 1, tol: 0.1}\nsolver:\n  <<: *b\n  rho: 2\n", "m.yaml")
        assert data["solver"] == {"rho": 2, "tol": 0.1}

    @pytest.mark.parametrize("text", [
        "x: !!python/object/apply:os.system ['echo hacked']\n",
        "x: !!python/name:os.system\n",
        "x: !custom 1\n",
    ])
    def test_tags_never_run(self, text):
        with pytest.raises(ScenarioError, match=r"^t.yaml: malformed YAML at line 1$"):
            parse_yaml_text(text, "t.yaml")

    @pytest.mark.parametrize("text", ["seed: " + "9" * 5000 + "\n", "dt: 2001-02-30\n"])
    def test_values_yaml_cannot_convert_are_one_line(self, text):
        with pytest.raises(ScenarioError, match=r"^v.yaml: cannot read a value \(ValueError\) at line 1$"):
            parse_yaml_text(text, "v.yaml")

    def test_text_above_the_size_bound(self):
        with pytest.raises(ScenarioError, match="more than a scenario file may have"):
            parse_yaml_text("#" * (MAX_FILE_BYTES + 1), "big.yaml")


# ------------------------------------------------------------------ what may be opened
class TestFileKinds:
    def test_a_fifo_is_refused_without_blocking(self, tmp_path):
        fifo = tmp_path / "pipe.yaml"
        os.mkfifo(fifo)
        outcome: list[BaseException | None] = []

        def load() -> None:
            try:
                load_scenario(fifo)
            except BaseException as err:  # noqa: BLE001 - handed to the test thread
                outcome.append(err)
            else:
                outcome.append(None)

        worker = threading.Thread(target=load, daemon=True)
        worker.start()
        worker.join(timeout=5)
        assert not worker.is_alive(), "load_scenario blocked on a FIFO"
        assert isinstance(outcome[0], ScenarioError)
        assert str(outcome[0]) == f"{fifo}: cannot read scenario file (a FIFO, not a regular file)"

    def test_a_directory(self, tmp_path):
        folder = tmp_path / "folder.yaml"
        folder.mkdir()
        assert refused_file(folder) == f"{folder}: cannot read scenario file (a directory, not a regular file)"

    @pytest.mark.skipif(not Path("/dev/null").exists(), reason="no /dev/null")
    def test_a_device(self):
        assert refused_file(Path("/dev/null")).endswith("(a character device, not a regular file)")

    def test_an_oversized_file_is_refused_before_reading(self, tmp_path):
        path = tmp_path / "big.yaml"
        with open(path, "wb") as handle:  # sparse: nothing to read, only the size says no
            handle.truncate(MAX_FILE_BYTES + 1)
        message = refused_file(path)
        assert message == (f"{path}: {MAX_FILE_BYTES + 1} bytes, more than a scenario file may have "
                           f"({MAX_FILE_BYTES} bytes)")

    def test_a_fifty_megabyte_list_is_refused_by_size(self, tmp_path):
        path = tmp_path / "list.yaml"
        path.write_text("agents: [" + "1," * (25 * 1024 * 1024) + "1]\n")
        started = time.perf_counter()
        assert "more than a scenario file may have" in refused_file(path)
        assert time.perf_counter() - started < 1.0

    def test_a_missing_file(self, tmp_path):
        path = tmp_path / "missing.yaml"
        assert refused_file(path) == f"{path}: cannot read scenario file (FileNotFoundError)"


# ------------------------------------------------------------------ strictly typed numbers
REAL_FIELDS = [
    (lambda v: with_(dt=v), "dt"),
    (lambda v: with_(kappa=v), "kappa"),
    (lambda v: with_(delta=v), "delta"),
    (lambda v: with_(delta=[0.3, v]), "delta[1]"),
    (lambda v: with_(weights={"Q": v}), "weights.Q"),
    (lambda v: with_(weights={"R": [[1, 0], [0, v]]}), "weights.R[1][1]"),
    (lambda v: {"agents": [{"start": [0, v], "goal": [1, 1]}]}, "agents[0].start[1]"),
    (lambda v: with_(limits={"speed": v}), "limits.speed"),
    (lambda v: with_(solver={"rho": v}), "solver.rho"),
    (lambda v: with_(stop={"goal_tolerance": v}), "stop.goal_tolerance"),
    (lambda v: with_(disturbance={"tightening": v}), "disturbance.tightening"),
    (lambda v: with_(obstacles=[{"box": {"center": [v, 3], "half_size": [0.1, 0.1]}}]), "obstacles[0].box.center[0]"),
]
INT_FIELDS = [
    (lambda v: with_(horizon=v), "horizon"),
    (lambda v: with_(seed=v), "seed"),
    (lambda v: with_(dim=v), "dim"),
    (lambda v: with_(solver={"max_iter": v}), "solver.max_iter"),
    (lambda v: with_(stop={"max_steps": v}), "stop.max_steps"),
]


class TestStrictNumbers:
    @pytest.mark.parametrize("build,field", REAL_FIELDS)
    @pytest.mark.parametrize("value,kind", [(True, "a boolean"), (False, "a boolean"), ("1.5", "text")])
    def test_booleans_and_text_are_not_numbers(self, build, field, value, kind):
        assert refused(build(value)) == f"{field}: expected a number, got {kind}"

    @pytest.mark.parametrize("build,field", INT_FIELDS)
    @pytest.mark.parametrize("value", [True, "3"])
    def test_booleans_and_text_are_not_integers(self, build, field, value):
        assert refused(build(value)).startswith(f"{field}: expected an integer")

    @pytest.mark.parametrize("build,field", INT_FIELDS)
    def test_a_fraction_is_not_an_integer(self, build, field):
        assert refused(build(2.5)).startswith(f"{field}: ")

    def test_integers_stay_welcome_where_reals_are_expected(self):
        scn = scenario_from_dict(with_(dt=1, kappa=10, delta=[1, 1], weights={"Q": 2}))
        assert (scn.dt, scn.kappa, scn.delta, scn.weights.Q) == (1.0, 10.0, [1.0, 1.0], 2.0)
        assert isinstance(scn.dt, float)

    def test_a_whole_real_is_an_integer(self):
        assert scenario_from_dict(with_(horizon=12.0)).horizon == 12

    @pytest.mark.parametrize("value", [1, "yes"])
    def test_booleans_are_booleans(self, value):
        assert refused(with_(solver={"adaptive_rho": value})).startswith("solver.adaptive_rho: expected true or false")

    def test_yaml_spellings(self, tmp_path):
        text = yaml.safe_dump(BASE) + "dt: '0.1'\n"
        assert refused_file(write(tmp_path, text)) == "dt: expected a number, got text"
        text = yaml.safe_dump(BASE) + "kappa: yes\n"  # YAML 1.1: a boolean
        assert refused_file(write(tmp_path, text)) == "kappa: expected a number, got a boolean"


# ------------------------------------------------------------------ bounded sizes
def agents_in_a_row(count: int) -> list[dict[str, list[float]]]:
    return [{"start": [float(i), 0.0], "goal": [float(i), 5.0]} for i in range(count)]


class TestSizeLimits:
    def test_horizon(self):
        assert scenario_from_dict(with_(horizon=MAX_HORIZON)).horizon == MAX_HORIZON
        assert refused(with_(horizon=MAX_HORIZON + 1)).startswith("horizon: ")

    def test_a_huge_horizon_is_refused_instantly(self):
        started = time.perf_counter()
        assert refused(with_(horizon=100_000_000)).startswith("horizon: ")
        assert time.perf_counter() - started < 0.5

    def test_agents(self):
        assert scenario_from_dict({"agents": agents_in_a_row(MAX_AGENTS)}).num_agents == MAX_AGENTS
        assert refused({"agents": agents_in_a_row(MAX_AGENTS + 1)}) == (
            f"agents: at most {MAX_AGENTS} agents, got {MAX_AGENTS + 1}")

    def test_max_steps(self):
        assert scenario_from_dict(with_(stop={"max_steps": MAX_STEPS})).stop.max_steps == MAX_STEPS
        assert refused(with_(stop={"max_steps": MAX_STEPS + 1})).startswith("stop.max_steps: ")

    def test_seed(self):
        assert scenario_from_dict(with_(seed=MAX_SEED)).seed == MAX_SEED
        assert refused(with_(seed=MAX_SEED + 1)).startswith("seed: ")

    def test_the_memory_estimate_names_the_step_cap(self):
        data = {"agents": agents_in_a_row(MAX_AGENTS), "stop": {"max_steps": MAX_STEPS}}
        message = refused(data)
        assert message.startswith("stop.max_steps: ") and "GiB" in message

    def test_the_memory_estimate_names_the_horizon(self):
        polytope = {"polytope": {"G": [[1.0, k / 64] for k in range(MAX_FACETS)], "g": [-500.0] * MAX_FACETS}}
        data = {"agents": agents_in_a_row(MAX_AGENTS), "horizon": MAX_HORIZON, "stop": {"max_steps": 10},
                "obstacles": [polytope] * MAX_OBSTACLES}
        message = refused(data)
        assert message.startswith("horizon: ") and "GiB" in message

    def test_obstacles_and_facets(self):
        box = {"box": {"center": [0, 50], "half_size": [0.1, 0.1]}}
        assert refused(with_(obstacles=[box] * (MAX_OBSTACLES + 1))).startswith("obstacles: at most")
        rows = MAX_FACETS + 1
        polytope = {"polytope": {"G": [[1, 0]] * rows, "g": [-9] * rows}}
        assert refused(with_(obstacles=[polytope])).startswith("obstacles[0].polytope.G: at most")


# ------------------------------------------------------------------ overflowing numbers
class TestOverflow:
    @pytest.mark.parametrize("data,field", [
        (with_(obstacles=[{"polytope": {"G": [[1e308, 1e308]], "g": [1]}}]), "obstacles[0].polytope.G[0][0]"),
        (with_(weights={"Q": 1e200}), "weights.Q"),
        (with_(weights={"R": [[1e160, 0], [0, 1]]}), "weights.R[0][0]"),
        ({"agents": [{"start": [1e9, 0], "goal": [1, 1]}]}, "agents[0].start[0]"),
        (with_(workspace={"lower": [-1e7, -3], "upper": [3, 3]}), "workspace.lower[0]"),
        (with_(kappa=10**400), "kappa"),  # an int too large for a float: no OverflowError
        (with_(dt=-(10**30)), "dt"),
    ])
    def test_magnitudes_are_bounded(self, data, field):
        assert refused(data).startswith(f"{field}: magnitude must be <= 1e+06")

    def test_zero_rows_are_refused(self):
        data = with_(obstacles=[{"polytope": {"G": [[1, 0], [0, 0]], "g": [9, 9]}}])
        assert refused(data).startswith("obstacles[0].polytope.G[1]: row norm must be finite and > 0")


# ------------------------------------------------------------------ names are file names
class TestNames:
    @pytest.mark.parametrize("name", ["..", ".", "", "a/b", "/abs", "../../x", "a\nb", "x" * 300, "a\\b",
                                      ".hidden", "-rf", "tab\tname", "space name", "nul\x00"])
    def test_unsafe_names(self, name):
        message = refused(with_(name=name))
        assert message.startswith("name: must be 1 to 100 of")

    @pytest.mark.parametrize("name", ["paper-2d", "circle-8", "sphere-8", "random-3d-16-s0", "spread-3d-1024-s0",
                                      "unnamed", "run_v1.2+fast", "x" * 100])
    def test_safe_names(self, name):
        assert scenario_from_dict(with_(name=name)).name == name

    def test_a_name_with_a_newline_stays_one_line(self):
        assert "\\n" in refused(with_(name="ok\nswarmpc: error: forged"))


# ------------------------------------------------------------------ one unforgeable line
class TestMessages:
    @pytest.mark.parametrize("key", ["a\nb", "x\rswarmpc: error: forged", "line\u2028sep", "dt: fine", "\x1b[31mred"])
    def test_unknown_keys_are_quoted_on_one_line(self, key):
        message = refused({**BASE, key: 1})
        assert message.endswith(": unknown key") and message.startswith("'")
        assert "\n" not in message and "\r" not in message and "\x1b" not in message

    def test_a_nested_key_with_a_newline(self):
        message = refused(with_(solver={"rho\nswarmpc: error: x": 1}))
        assert message.startswith("solver.'rho\\nswarmpc") and len(message.splitlines()) == 1

    @pytest.mark.parametrize("data,field", [
        (with_(obstacles=[{"polytope": {"G": [[1, 0], [1]], "g": [1, 1]}}]), "obstacles[0].polytope.G"),
        (with_(weights={"Q": [[1, 0], [0]]}), "weights.Q"),
        (with_(weights={"R": [[1, 0], [0]]}), "weights.R"),
        (with_(weights={"Qf": [[1, 0, 0, 0]] * 3 + [[0, 0, 0]]}), "weights.Qf"),
    ])
    def test_ragged_matrices_name_the_field(self, data, field):
        assert refused(data).startswith(f"{field}: ")

    def test_non_text_keys(self):
        assert refused({**BASE, 1: 2}) == "scenario: keys must be text, got 1"

    def test_scenario_errors_are_always_one_line(self):
        assert str(ScenarioError("a\nb\r\nc\u2029d")) == "a\\nb\\r\\nc\\u2029d"

    def test_a_huge_value_gives_a_bounded_line(self):
        message = refused(with_(delta=[-1.0] * 100_000))
        assert message.startswith("delta: ") and len(message) <= 500


# ------------------------------------------------------------------ built-in generators
class TestBuiltinArguments:
    def test_unknown_arguments(self):
        with pytest.raises(ScenarioError) as caught:
            builtin_scenario("paper-2d", foo=1)
        assert str(caught.value) == "foo: not an argument of built-in 'paper-2d' (accepts: delta, seed)"

    @pytest.mark.parametrize("name", ["paper-2d", "paper-3d", "wall-door", "pillars", "u-trap"])
    def test_fixed_built_ins_take_no_size(self, name):
        for key in ("agents", "dim"):
            with pytest.raises(ScenarioError, match=f"^{key}: not an argument of built-in '{name}'"):
                builtin_scenario(name, **{key: 2})

    def test_none_means_not_given(self):
        assert builtin_scenario("paper-2d", agents=None, dim=None, seed=None) == builtin_scenario("paper-2d")
        assert builtin_scenario("paper-2d", seed=7).seed == 7  # every built-in takes a seed

    @pytest.mark.parametrize("name,key,value", [
        ("circle", "agents", 0), ("random", "agents", MAX_AGENTS + 1), ("spread", "agents", 99999999999999999999),
        ("circle", "agents", 8.0), ("circle", "agents", True), ("circle", "dim", 4), ("random", "dim", 0),
        ("random", "seed", -1), ("random", "seed", 99999999999999999999), ("paper-2d", "seed", "3"),
        ("paper-2d", "delta", 0.0), ("paper-2d", "delta", float("nan")), ("circle", "delta", float("inf")),
        ("circle", "radius", -1.0), ("random", "box_scale", 1e9), ("random", "clearance", -0.1),
        ("random", "min_gap", "0.5"),
    ])
    def test_values_out_of_range_name_the_argument(self, name, key, value):
        started = time.perf_counter()
        with pytest.raises(ScenarioError) as caught:
            builtin_scenario(name, **{key: value})
        assert str(caught.value).startswith(f"{key}: ") and len(str(caught.value).splitlines()) == 1
        assert time.perf_counter() - started < 1.0

    def test_every_built_in_declares_its_arguments(self):
        for name in BUILTINS:
            assert "seed" in builtin_parameters(name) and "delta" in builtin_parameters(name)
        assert set(builtin_parameters("circle")) >= {"agents", "dim", "radius"}

    def test_the_largest_swarms_generate(self):
        assert builtin_scenario("circle", agents=MAX_AGENTS).num_agents == MAX_AGENTS
        assert builtin_scenario("spread", agents=MAX_AGENTS, seed=3).num_agents == MAX_AGENTS

    def test_an_impossible_random_box_fails_in_bounded_time(self):
        started = time.perf_counter()
        with pytest.raises(ScenarioError, match="^agents: 300 agents do not fit"):
            builtin_scenario("random", agents=300, dim=2)
        assert time.perf_counter() - started < 30.0

    def test_more_agents_than_the_packing_bound_are_refused_before_sampling(self, monkeypatch):
        class NoDraws:
            def uniform(self, *_args: Any) -> Any:
                raise AssertionError("sampled a swarm the packing bound refuses")

        monkeypatch.setattr(scenarios_module.np.random, "default_rng", lambda *_args: NoDraws())
        with pytest.raises(ScenarioError, match="^agents: 300 agents do not fit"):
            builtin_scenario("random", agents=300, dim=2)
        with pytest.raises(ScenarioError, match="^agents: 400 agents do not fit"):
            builtin_scenario("random", agents=400, dim=3)


@settings(max_examples=60, deadline=None)
@given(st.integers(0, 10_000), st.integers(1, 3), st.floats(0.2, 1.0))
def test_no_point_set_spaced_apart_beats_the_packing_bound(seed, dim, spacing):
    """Points packed greedily, every pair at least ``spacing`` apart along some axis, never
    outnumber the bound, and a grid of exactly that pitch (the tightest packing) reaches it."""
    rng = np.random.default_rng(seed)
    sides = rng.uniform(0.0, 3.0, dim)
    grid = np.stack(np.meshgrid(*[np.arange(0.0, side + 1e-12, spacing) for side in sides]), -1).reshape(-1, dim)
    points = np.empty((0, dim))
    for p in np.concatenate([grid[rng.random(len(grid)) < 0.5], rng.uniform(0.0, sides, (300, dim))]):
        if not len(points) or np.max(np.abs(points - p), axis=1).min() >= spacing:
            points = np.vstack([points, p])
    assert len(points) <= packing_bound(sides, spacing) == len(grid)


# ------------------------------------------------------------------ changed in place
class NoSolve:
    def plan(self, *_args: Any) -> Any:
        raise AssertionError("simulate solved a scenario it should have refused")


class TestMutation:
    @pytest.mark.parametrize("mutate,field", [
        (lambda scn: scn.agents[0].start.append(1.0), "agents[0].start"),
        (lambda scn: scn.agents[0].start.__setitem__(0, 1e9), "agents[0].start[0]"),
        (lambda scn: scn.agents.append(scn.agents[1]), "agents[4].start"),
        (lambda scn: scn.agents.clear(), "agents"),
        (lambda scn: scn.workspace.lower.__setitem__(0, "x"), "workspace.lower[0]"),
    ])
    def test_simulate_refuses_a_mutated_scenario_before_any_solve(self, mutate, field):
        scn = builtin_scenario("paper-2d")
        mutate(scn)
        with pytest.raises(ScenarioError) as caught:
            simulate(scn, solver=NoSolve())
        assert str(caught.value).startswith(f"{field}: ")

    def test_a_foreign_object_is_refused(self):
        scn = builtin_scenario("paper-2d")
        scn.agents.append(object())
        with pytest.raises(ScenarioError):
            scn.revalidated()

    @pytest.mark.parametrize("name", list(BUILTINS))
    def test_revalidating_changes_nothing(self, name):
        scn = builtin_scenario(name)
        again = scn.revalidated()
        assert again == scn and again is not scn
        assert repr(again.model_dump()) == repr(scn.model_dump())  # same values, same types


# ------------------------------------------------------------------ nothing legitimate is lost
class TestStillLoads:
    @pytest.mark.parametrize("name", list(BUILTINS))
    def test_every_built_in(self, name):
        assert isinstance(builtin_scenario(name), Scenario)

    @pytest.mark.parametrize("path", sorted(EXAMPLES.glob("*.yaml")), ids=lambda p: p.name)
    def test_every_example(self, path):
        scn = load_scenario(path)
        assert scn.num_agents >= 1 and scenario_from_dict(yaml.safe_load(path.read_text())) == scn


# ------------------------------------------------------------------ laws
yaml_alphabet = st.sampled_from(list("[]{}:,-&*!|>'\"#?<\n ab01.x") + ["dt", "agents", "start", "<<", "!!", "\t"])


class TestLaws:
    @settings(max_examples=300, deadline=None, suppress_health_check=[HealthCheck.too_slow])
    @given(st.one_of(st.text(max_size=120), st.lists(yaml_alphabet, max_size=60).map("".join)))
    def test_any_text_loads_or_is_one_line(self, text):
        try:
            data = parse_yaml_text(text, "fuzz.yaml")
            scenario_from_dict(data, source="fuzz.yaml")
        except ScenarioError as err:
            assert str(err) and len(str(err).splitlines()) == 1

    @settings(max_examples=100, deadline=None)
    @given(st.sampled_from(REAL_FIELDS), st.one_of(st.booleans(), st.text(max_size=5)))
    def test_no_boolean_or_text_passes_for_a_number(self, case, value):
        build, field = case
        assert refused(build(value)).startswith(f"{field}: expected a number")

    @settings(max_examples=60, deadline=None)
    @given(st.integers(-(2**70), 2**70))
    def test_circle_agents_generate_or_name_the_argument(self, agents):
        if 1 <= agents <= 64:
            assert builtin_scenario("circle", agents=agents).num_agents == agents
        elif not 1 <= agents <= MAX_AGENTS:
            with pytest.raises(ScenarioError, match="^agents: must be between 1 and"):
                builtin_scenario("circle", agents=agents)


# ------------------------------------------------------------------ through the command line
@pytest.mark.skipif(not SWARMPC.exists(), reason="the swarmpc console script is not installed")
class TestCommandLine:
    @pytest.mark.parametrize("text,needle", [
        (BILLION_LAUGHS, "aliases expanded"),
        (yaml.safe_dump(BASE) + "dt: 0.1\ndt: 0.2\n", "duplicate key 'dt'"),
        (yaml.safe_dump({**BASE, "horizon": True}), "horizon: expected an integer"),
        (yaml.safe_dump({**BASE, "name": "../../x"}), "name: must be"),
    ])
    def test_one_line_exit_2_and_nothing_written(self, tmp_path, text, needle):
        path = write(tmp_path, text)
        started = time.perf_counter()
        done = subprocess.run([str(SWARMPC), "run", str(path)], capture_output=True, text=True, cwd=tmp_path,
                              timeout=120)
        assert done.returncode == 2, done.stderr
        lines = done.stderr.splitlines()
        assert len(lines) == 1 and lines[0].startswith("swarmpc: error: ") and needle in lines[0], done.stderr
        assert "Traceback" not in done.stderr
        assert not (tmp_path / "results").exists() and not (tmp_path.parent / "x").exists()
        assert time.perf_counter() - started < 60

    def test_a_fifo_through_the_command_line(self, tmp_path):
        fifo = tmp_path / "pipe.yaml"
        os.mkfifo(fifo)
        done = subprocess.run([str(SWARMPC), "run", str(fifo)], capture_output=True, text=True, cwd=tmp_path,
                              timeout=60)  # a blocked open would time out here
        assert done.returncode == 2
        assert done.stderr == f"swarmpc: error: {fifo}: cannot read scenario file (a FIFO, not a regular file)\n"
        assert not (tmp_path / "results").exists()
