"""Fuzzed scenario data: every rejection is a ScenarioError with one line naming a field."""

from __future__ import annotations

import math

import yaml
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from conftest import run_cli
from swarmpc.config import ScenarioError, scenario_from_dict

numbers = st.one_of(st.floats(allow_nan=True, allow_infinity=True), st.integers(-5, 5))
vectors = st.lists(numbers, min_size=0, max_size=4)
leaf = st.one_of(numbers, vectors, st.text(max_size=5), st.none(), st.booleans())
keys = st.sampled_from(["name", "dim", "dt", "horizon", "delta", "collision", "d_min", "kappa", "weights",
                        "workspace", "limits", "obstacles", "agents", "solver", "stop", "bogus"])
agents = st.lists(st.fixed_dictionaries({"start": vectors, "goal": vectors}), max_size=4)
scenarios = st.dictionaries(keys, st.one_of(leaf, agents, st.dictionaries(st.text(max_size=4), leaf, max_size=3)),
                            max_size=8)


@settings(max_examples=300, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(scenarios)
def test_random_mappings_validate_or_fail_with_one_line(data):
    try:
        scn = scenario_from_dict(data)
    except ScenarioError as err:
        message = str(err)
        assert message and "\n" not in message
        assert ":" in message or "is required" in message
    else:
        assert scn.num_agents >= 1 and math.isfinite(scn.dt) and scn.dt > 0


@settings(max_examples=8, deadline=None, suppress_health_check=[HealthCheck.too_slow, HealthCheck.function_scoped_fixture])
@given(scenarios)
def test_cli_never_shows_a_traceback(tmp_path, data):
    path = tmp_path / "fuzz.yaml"
    path.write_text(yaml.safe_dump(data, allow_unicode=True))
    done = run_cli("run", str(path), "--out", str(tmp_path / "out"), "--quiet", "--max-steps", "1")
    assert "Traceback" not in done.stderr
    if done.returncode != 0:
        assert done.returncode == 2 and len(done.stderr.strip().splitlines()) == 1
