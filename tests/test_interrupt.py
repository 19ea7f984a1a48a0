"""Ctrl-C mid-run leaves either nothing or a complete run folder marked as interrupted."""

from __future__ import annotations

import json
import signal
import subprocess
import sys
import time

import numpy as np
import pytest

from swarmpc.config import scenario_to_yaml
from swarmpc.scenarios import builtin_scenario


def _like_a_terminal() -> None:
    """Ctrl-C's default disposition in the child, as a shell in the foreground gives it: a suite
    started in the background (``cmd &`` in a script) hands its children SIGINT ignored, and
    Python then keeps ignoring it."""
    signal.signal(signal.SIGINT, signal.SIG_DFL)


def _wait_for_staging(folder, process: subprocess.Popen, timeout_s: float = 120.0) -> None:
    """Wait until the run has reserved its staging folder in ``folder`` (a loaded machine may
    take many seconds to import the numerical stack; a signal before the loop has begun ends the
    run with no step to write)."""
    deadline = time.monotonic() + timeout_s
    while not any(folder.glob(".run.partial-*")):
        assert process.poll() is None, process.communicate()
        assert time.monotonic() < deadline, "the run reserved no staging folder"
        time.sleep(0.05)


@pytest.mark.parametrize("sig, executor", [
    (signal.SIGINT, "serial"), pytest.param(signal.SIGTERM, "serial", marks=pytest.mark.loop),
    pytest.param(signal.SIGTERM, "process", marks=pytest.mark.loop),
    pytest.param(signal.SIGTERM, "ray", marks=pytest.mark.loop),
])
def test_a_signal_gives_a_complete_interrupted_folder(tmp_path, sig, executor):
    """SIGINT and SIGTERM end the loop after the step; the interrupted run is written whole, no
    staging folder is left, and worker processes end quietly. The run is paper-2d with a goal
    tolerance no agent meets, so it is still running whenever the signal comes (a fast machine
    flies the whole of paper-2d within the start-up wait): the agents are pushed by process noise,
    or the QP local step would bring them to rest exactly on their goals."""
    out = tmp_path / "run"
    endless = tmp_path / "endless.yaml"
    endless.write_text(scenario_to_yaml(builtin_scenario("paper-2d").with_updates(
        **{"stop.goal_tolerance": 1e-9, "disturbance.process_position_std": 1e-3})))
    process = subprocess.Popen(
        [sys.executable, "-m", "swarmpc", "run", str(endless), "--executor", executor,
         "--max-steps", "100000", "--out", str(out), "--quiet"],
        stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, preexec_fn=_like_a_terminal,
    )
    _wait_for_staging(tmp_path, process)  # imports done, the run folder reserved: the loop is next
    time.sleep({"serial": 3.0, "process": 5.0, "ray": 10.0}[executor])  # start-up and some steps
    assert process.poll() is None, process.communicate()
    process.send_signal(sig)
    _stdout, stderr = process.communicate(timeout=120)
    assert process.returncode == 0, stderr
    assert "Traceback" not in stderr
    leftovers = [p.name for p in tmp_path.iterdir() if p.name not in ("run", endless.name)]
    assert leftovers == []  # no half-written staging folder
    summary = json.loads((out / "summary.json").read_text())
    assert summary["interrupted"] is True
    with np.load(out / "trajectory.npz") as data:
        states, inputs = data["states"], data["inputs"]
    assert summary["steps"] == inputs.shape[0] == states.shape[0] - 1 >= 1


# The console script's own wrapper, plus one line that says the command line's import has begun
# (printed by an import hook when ``swarmpc.cli`` is first looked up): a Ctrl-C before that line
# lands in the interpreter's start-up (runpy, site) or between statements before the entry point
# has taken Ctrl-C over, which no program can turn into one line (on a loaded machine a signal
# sent just after a line printed before ``main()`` sometimes landed there).
ENTRY_POINT = """
import sys
from swarmpc._launch import main
class Announce:
    def find_spec(self, name, path=None, target=None):
        if name == "swarmpc.cli":
            print("loaded", flush=True)
        return None
sys.meta_path.insert(0, Announce())
main()
"""


@pytest.mark.parametrize("delay", [0.0, 0.02, 0.1, 0.25])
def test_sigint_while_starting_up_is_one_line_not_a_traceback(tmp_path, delay):
    """Ctrl-C while the command line is still importing its libraries: status 130 and the same
    one line as later on; nothing written. (Python may end such a process by SIGINT itself after
    the line, which a shell reports as the same status 130.)"""
    out = tmp_path / "run"
    process = subprocess.Popen(
        [sys.executable, "-c", ENTRY_POINT, "run", "paper-2d", "--out", str(out), "--quiet"],
        stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, preexec_fn=_like_a_terminal,
    )
    assert process.stdout is not None and process.stdout.readline() == "loaded\n"
    time.sleep(delay)
    process.send_signal(signal.SIGINT)
    _stdout, stderr = process.communicate(timeout=120)
    lines = [line for line in stderr.splitlines() if "leaked" not in line]  # nanobind's exit notes
    assert "Traceback" not in stderr
    assert process.returncode in (130, -signal.SIGINT) and lines == ["swarmpc: interrupted"], stderr
    assert not out.exists()


def test_package_import_is_light():
    """``import swarmpc`` loads none of the numerical stack, so the entry point can take Ctrl-C at once."""
    code = "import sys, swarmpc; print(sorted(m for m in ('numpy', 'casadi', 'pydantic') if m in sys.modules))"
    done = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert done.stdout.strip() == "[]"
    from swarmpc import Scenario, load_scenario  # the names still resolve, on first use
    assert callable(load_scenario) and Scenario.__name__ == "Scenario"


def test_an_import_error_raised_by_a_ctrl_c_counts_as_the_ctrl_c():
    """A Ctrl-C inside a compiled module's initialisation surfaces as that module's import error."""
    from swarmpc._interrupts import caused_by_interrupt

    def failing_import(chain: str) -> BaseException:
        try:
            try:
                raise KeyboardInterrupt
            except KeyboardInterrupt as interrupt:
                if chain == "cause":
                    raise ImportError("initialization failed") from interrupt
                # the implicit chain (__context__ only) is the case under test
                raise ImportError("initialization failed")  # noqa: B904
        except ImportError as error:
            return error

    assert caused_by_interrupt(failing_import("cause"))
    assert caused_by_interrupt(failing_import("context"))
    assert caused_by_interrupt(KeyboardInterrupt())
    assert not caused_by_interrupt(ImportError("no module named casadi"))


def test_a_ctrl_c_the_import_machinery_ignores_still_ends_the_command(monkeypatch, capsys):
    """A Ctrl-C inside a callback of the import machinery is reported as "ignored" and the import
    goes on; the entry point still ends with the one line and status 130, no traceback."""
    import types

    from swarmpc import _launch

    class Unraisable:
        exc_type, exc_value, exc_traceback, err_msg, object = KeyboardInterrupt, KeyboardInterrupt(), None, None, None

    fake_cli = types.ModuleType("swarmpc.cli")

    def main() -> None:
        raise AssertionError("the command ran after Ctrl-C")

    def attribute(name: str):
        sys.unraisablehook(Unraisable())  # what the interpreter does with the ignored interrupt
        return main

    fake_cli.__getattr__ = attribute  # type: ignore[method-assign]
    monkeypatch.setitem(sys.modules, "swarmpc.cli", fake_cli)
    with pytest.raises(SystemExit) as stop:
        _launch.main()
    assert stop.value.code == _launch.INTERRUPTED
    assert capsys.readouterr().err == "swarmpc: interrupted\n"
    assert sys.unraisablehook is sys.__unraisablehook__
