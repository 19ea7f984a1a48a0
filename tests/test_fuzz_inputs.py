"""Fuzzed scenario data and command lines: every rejection is one line naming a field (or the
option, or the file), exit status 2, no traceback and no output folder."""

from __future__ import annotations

import contextlib
import math
import re
import subprocess
import sys
import tempfile
from pathlib import Path
from typing import Any

import pytest
import typer
import yaml
from hypothesis import HealthCheck, example, given, settings
from hypothesis import strategies as st

from conftest import cli_in_process, run_cli
from swarmpc.cli import app
from swarmpc.config import MAX_MAGNITUDE, MAX_SEED, Scenario, ScenarioError, scenario_from_dict, scenario_to_yaml
from swarmpc.scenarios import BUILTINS, builtin_parameters, builtin_scenario

PREFIX = "swarmpc: error: "
FIELDS = set(Scenario.model_fields)

numbers = st.one_of(st.floats(allow_nan=True, allow_infinity=True), st.integers(-5, 5))
vectors = st.lists(numbers, min_size=0, max_size=4)
leaf = st.one_of(numbers, vectors, st.text(max_size=5), st.none(), st.booleans())
keys = st.sampled_from(["name", "dim", "dt", "horizon", "delta", "collision", "d_min", "kappa", "seed", "weights",
                        "workspace", "limits", "obstacles", "agents", "solver", "stop", "disturbance", "bogus"])
agents = st.lists(st.fixed_dictionaries({"start": vectors, "goal": vectors}), max_size=4)
disturbances = st.dictionaries(
    st.sampled_from(["process_position_std", "process_velocity_std", "measurement_position_std",
                     "measurement_velocity_std", "tightening", "bogus"]),
    numbers, max_size=3)
scenarios = st.dictionaries(
    keys, st.one_of(leaf, agents, disturbances, st.dictionaries(st.text(max_size=4), leaf, max_size=3)), max_size=8)


def names_a_field(message: str, data: Any, source: str | None = None) -> bool:
    """The text before the first ': ' is ``source`` (the file) or a dotted path whose root is a
    scenario field or a key of ``data`` (an unknown key is named as given)."""
    head = message.split(": ", 1)[0]
    if source is not None and head == source:
        return True
    root = re.match(r"[^.\[]*", head).group(0)
    return bool(root) and (root in FIELDS or (isinstance(data, dict) and root in data))


@settings(max_examples=300, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(scenarios)
def test_random_mappings_validate_or_fail_with_one_line(data):
    try:
        scn = scenario_from_dict(data)
    except ScenarioError as err:
        message = str(err)
        assert message and "\n" not in message
        assert names_a_field(message, data), message
    else:
        assert scn.num_agents >= 1 and math.isfinite(scn.dt) and scn.dt > 0 and scn.seed >= 0


@settings(max_examples=8, deadline=None,
          suppress_health_check=[HealthCheck.too_slow, HealthCheck.function_scoped_fixture])
@given(scenarios)
def test_cli_never_shows_a_traceback(tmp_path, data):
    path = tmp_path / "fuzz.yaml"
    path.write_text(yaml.safe_dump(data, allow_unicode=True))
    out = tmp_path / "out"
    done = run_cli("run", str(path), "--out", str(out), "--quiet", "--max-steps", "1")
    assert "Traceback" not in done.stderr
    if done.returncode != 0:
        assert done.returncode == 2 and len(done.stderr.strip().splitlines()) == 1
        line = done.stderr.strip()
        assert line.startswith(PREFIX) and names_a_field(line[len(PREFIX):], data, source=str(path)), line
        assert not out.exists()
    else:
        assert (out / "summary.json").is_file()


# ------------------------------------------------------------------ command-line arguments
RUN = typer.main.get_command(app).commands["run"]
# where the agents run: starting process pools or Ray per example is too slow for a fuzz, and their
# rules (--workers, --address only with some executors) are tested in tests/test_cli_executor.py
EXECUTOR_OPTIONS = {"--executor", "--workers", "--address"}
# every value-taking option of `swarmpc run` but --out and those, with the type its help shows
OPTIONS = {p.opts[0]: p for p in RUN.params
           if p.param_type_name == "option" and not p.is_flag and p.opts[0] != "--out"
           and p.opts[0] not in EXECUTOR_OPTIONS}
# the scenario field(s) a rejection may name for each option (besides the option itself);
# a --delta too large for the scenario is reported at the agent whose start it overlaps
FIELD_OF = {"--seed": ("seed",), "--agents": ("agents",), "--dim": ("dim",), "--delta": ("delta", "agents"),
            "--rho": ("solver.rho",), "--admm-tol": ("solver.tol",), "--admm-max-iter": ("solver.max_iter",),
            "--max-steps": ("stop.max_steps",), "--method": ("solver.method",), "--collision": ("collision",),
            "--initial-guess": ("solver.initial_guess",), "--plane-margin": ("solver.plane_margin",),
            "--deadline": ("solver.deadline",), "--local": ("solver.local",), "--plant": ("plant",)}
# valid ranges, for the options whose range the oracle knows
IN_RANGE = {"--seed": lambda v: 0 <= v <= MAX_SEED, "--agents": lambda v: v >= 1, "--dim": lambda v: v in (2, 3),
            "--admm-max-iter": lambda v: v >= 1, "--max-steps": lambda v: v >= 1,
            "--delta": lambda v: v > 0, "--rho": lambda v: v > 0, "--admm-tol": lambda v: v > 0,
            "--plane-margin": lambda v: v >= 0, "--deadline": lambda v: v > 0}
# added when not fuzzed (and taken by the scenario), so that valid command lines finish in well under a second
FAST = {"--max-steps": "1", "--agents": "2", "--admm-max-iter": "10"}
# options that shape a built-in's generator: an error with a built-in whose generator does not take them
GENERATOR_OPTIONS = {"--agents", "--dim"}


def takes(scenario: str, option: str) -> bool:
    """Whether ``option`` may be given with ``scenario``: the generator options only with the
    built-ins whose generator takes them (``paper-2d --agents 8`` would silently run 4 agents)."""
    return (option not in GENERATOR_OPTIONS or scenario not in BUILTINS
            or option.removeprefix("--") in builtin_parameters(scenario))


CAR_BUILTINS = {"intersection", "mixed", "crossing", "parking"}
CAR_REFUSALS = {("--plant", "mujoco"), ("--executor", "thread"), ("--executor", "process"), ("--executor", "ray")}
"""What a swarm with car agents refuses: the MuJoCo plant does not take cars, and its solvers run
in the calling process."""


def refused(scenario: str, option: str, value: str) -> bool:
    """Whether a valid value is refused with this scenario (the car built-ins' limits)."""
    return scenario in CAR_BUILTINS and (option, value) in CAR_REFUSALS

# text without digits: never a number, except the spellings of nan and inf
letters = st.text(st.characters(categories=["L", "P", "Zs"], exclude_characters="\x00"), max_size=6)
small_ints = st.integers(-3, 4).map(str)  # the run-size options stay small when valid
not_ints = st.sampled_from(["1.5", "-0.5", "nan", "inf", "-inf", "1e3", ""])


def _enum_values(param: Any) -> list[str]:
    return [str(getattr(c, "value", c)) for c in param.type_descriptor.choices]


def values_for(option: str) -> st.SearchStrategy[str]:
    param = OPTIONS[option]
    kind = param.type_descriptor.annotation
    if param.type_descriptor.is_choice:
        return st.one_of(st.sampled_from(_enum_values(param)), letters)
    if kind is int:
        extra = [st.integers(-(2**70), 2**70).map(str)] if option == "--seed" else []
        return st.one_of(small_ints, *extra, not_ints, letters)
    if kind is float:
        return st.one_of(st.floats(allow_nan=True, allow_infinity=True).map(repr), st.integers(-3, 3).map(str),
                         letters)
    return letters


def invalid(option: str, value: str) -> bool:
    """Whether the value is certainly rejected: unparsable, not finite, out of range, not a choice."""
    param = OPTIONS[option]
    kind = param.type_descriptor.annotation
    if param.type_descriptor.is_choice:
        return value not in _enum_values(param)
    try:
        number = int(value) if kind is int else float(value)
    except ValueError:
        return True
    if not math.isfinite(number) or (kind is not int and abs(number) > MAX_MAGNITUDE):
        return True
    return option in IN_RANGE and not IN_RANGE[option](number)


scenario_names = st.one_of(
    st.sampled_from(sorted(BUILTINS)),
    st.text(max_size=8).filter(lambda s: not s.startswith("-") and ": " not in s and "\x00" not in s),
)


@st.composite
def command_lines(draw: st.DrawFn) -> tuple[str, dict[str, str]]:
    chosen = draw(st.lists(st.sampled_from(sorted(OPTIONS)), unique=True, max_size=4))
    return draw(scenario_names), {option: draw(values_for(option)) for option in chosen}


def named_by(message: str) -> str:
    """The option (``Invalid value for '--x'``) or the field path a rejection names."""
    option = re.match(r"Invalid value for '([^']+)'", message)
    return option.group(1) if option else message.split(": ", 1)[0]


def test_the_fuzzed_options_are_the_real_ones():
    expected = {"--seed", "--agents", "--delta", "--rho", "--admm-tol", "--admm-max-iter", "--max-steps",
                "--method", "--collision", "--initial-guess", "--dim"}
    assert expected <= set(OPTIONS), sorted(expected - set(OPTIONS))
    assert set(FAST) <= set(OPTIONS)
    assert OPTIONS["--seed"].type_descriptor.annotation is int
    assert OPTIONS["--delta"].type_descriptor.annotation is float


@settings(max_examples=25, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(command_lines())
@example(("paper-2d", {"--seed": "7", "--delta": "0.25", "--collision": "soft"}))  # valid: runs
@example(("random", {"--seed": "-1"}))  # the generator used to crash on it
@example(("circle", {"--dim": "0"}))
def test_run_arguments_run_or_fail_with_one_line_naming_the_option(command):
    scenario, values = command
    with tempfile.TemporaryDirectory() as tmp, contextlib.chdir(tmp):  # a stray path lands here
        out = Path(tmp) / "out"
        args = [scenario, *(x for item in values.items() for x in item)]
        args += [x for option, value in FAST.items() if option not in values and takes(scenario, option)
                 for x in (option, value)]
        code, stderr = cli_in_process("run", *args, "--out", str(out), "--quiet")
        assert code in (0, 2), (code, stderr)
        assert "Traceback" not in stderr
        bad = [option for option, value in values.items()
               if invalid(option, value) or not takes(scenario, option) or refused(scenario, option, value)]
        if scenario not in BUILTINS:
            bad.append("SCENARIO")
        if bad:
            assert code == 2, (args, stderr)
        elif float(values.get("--delta", "0.3")) <= 0.3:  # valid, and no larger box than the default
            assert code == 0, (args, stderr)
        if code == 0:
            assert (out / "summary.json").is_file()
            return
        lines = stderr.splitlines()
        assert len(lines) == 1 and lines[0].startswith(PREFIX) and len(lines[0]) > len(PREFIX), stderr
        named = named_by(lines[0][len(PREFIX):])
        suspects = bad or ["SCENARIO", *values, *FAST]  # nothing certainly bad: any given value
        allowed = {name for option in suspects
                   for name in ((option, *FIELD_OF.get(option, ())) if option != "SCENARIO"
                                else ("scenario", scenario))}
        assert any(named == name or named.startswith((f"{name}.", f"{name}[")) for name in allowed), (
            f"{lines[0]!r} names {named!r}, expected one of {sorted(allowed)} for {args}")
        assert not out.exists() and list(Path(tmp).iterdir()) == []


@pytest.mark.parametrize("how", ["yaml", "paper-2d", "random"])
def test_a_negative_seed_is_rejected_naming_seed(how, tmp_path):
    out = tmp_path / "out"
    if how == "yaml":
        path = tmp_path / "s.yaml"
        path.write_text(yaml.safe_dump({"seed": -3, "agents": [{"start": [0, 0], "goal": [1, 0]}]}))
        args = [str(path)]
    else:
        args = [how, "--seed", "-1", "--agents", "2"]
    code, stderr = cli_in_process("run", *args, "--max-steps", "1", "--out", str(out), "--quiet")
    assert code == 2 and stderr.startswith(f"{PREFIX}seed: ") and stderr.count("\n") == 1, stderr
    assert not out.exists()


# ------------------------------------------------------------------ Ctrl-C outside the loop
INTERRUPT_AT_OPEN = """\
import os, sys
from swarmpc.cli import main

def interrupt(event, args):
    if event == "open" and isinstance(args[0], (str, os.PathLike)):
        path = os.path.abspath(os.fspath(args[0]))
        if os.path.basename(path) == NAME:
            folder = os.path.dirname(path)
            written = [os.path.isfile(os.path.join(folder, name)) for name in ("summary.json", "trajectory.npz")]
            print(folder, *written, flush=True)
            raise KeyboardInterrupt

sys.addaudithook(interrupt)
main()
"""


def run_interrupted_at_open(name: str, *args: str) -> tuple[int, str, str]:
    """``swarmpc ARGS`` in a fresh interpreter, interrupted the moment it opens a file called
    ``name``: the KeyboardInterrupt Python's SIGINT handler raises, from an audit hook on the
    ``open`` event (at the operating-system boundary, no swarmpc function replaced). Returns
    (exit status, stdout: the file's folder and whether summary.json and trajectory.npz were
    in it, stderr)."""
    script = f"NAME = {name!r}\nimport sys\nsys.argv = ['swarmpc', *{list(args)!r}]\n" + INTERRUPT_AT_OPEN
    done = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True, timeout=600)
    return done.returncode, done.stdout, done.stderr


def test_ctrl_c_during_start_up_is_one_line_and_status_130(tmp_path):
    scenario = tmp_path / "in" / "u-trap.yaml"  # interrupted while the scenario file is read
    scenario.parent.mkdir()
    scenario.write_text(scenario_to_yaml(builtin_scenario("u-trap")))
    work = tmp_path / "work"
    work.mkdir()
    code, stdout, stderr = run_interrupted_at_open(
        "u-trap.yaml", "run", str(scenario), "--max-steps", "1", "--out", str(work / "out"), "--quiet")
    assert (code, stderr) == (130, "swarmpc: interrupted\n")
    assert stdout.split()[0] == str(scenario.parent)  # it was interrupted there
    assert list(work.iterdir()) == []


def test_ctrl_c_while_writing_the_run_folder_leaves_nothing(tmp_path):
    out = tmp_path / "out"  # the figure is written last, into the staging folder
    code, stdout, stderr = run_interrupted_at_open(
        "trajectory.png", "run", "u-trap", "--max-steps", "1", "--out", str(out), "--quiet")
    assert (code, stderr) == (130, "swarmpc: interrupted\n")
    folder, summary, trajectory = stdout.split()
    assert Path(folder).parent == tmp_path and Path(folder) != out  # a staging folder ...
    assert (summary, trajectory) == ("True", "True")  # ... half-written
    assert list(tmp_path.iterdir()) == []  # and the staging folder is gone


@given(points=st.lists(st.tuples(st.integers(0, 12), st.integers(0, 12)), min_size=2, max_size=12, unique=True),
       delta=st.sampled_from([0.25, 0.5, 0.75]))
@settings(max_examples=40, deadline=None)
def test_overlapping_starts_name_the_first_overlapping_pair(points, delta):
    """The start check (one row of pairs at a time) agrees with the plain double loop: an error
    exactly when two starts are within delta on every axis, naming the first such pair."""
    starts = [[0.5 * x, 0.5 * y] for x, y in points]
    agents = [{"start": p, "goal": [20.0 + 2 * k, 20.0]} for k, p in enumerate(starts)]
    first = next(((i, j) for i in range(len(starts)) for j in range(i + 1, len(starts))
                  if all(abs(a - b) < delta for a, b in zip(starts[i], starts[j], strict=True))), None)
    if first is None:
        scenario_from_dict({"dim": 2, "delta": delta, "agents": agents})
        return
    message = f"agents[{first[1]}].start: within delta of agents[{first[0]}].start"
    with pytest.raises(ScenarioError, match=re.escape(message)):
        scenario_from_dict({"dim": 2, "delta": delta, "agents": agents})
