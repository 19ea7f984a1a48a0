"""Progress: a bar with an ETA on a terminal, a line every few seconds when stderr is a file."""

from __future__ import annotations

import numpy as np

from swarmpc.cli import RunProgress, _progress_lines
from swarmpc.scenarios import builtin_scenario


def test_progress_counts_agents_at_goal_and_estimates_the_rest():
    scn = builtin_scenario("paper-2d")
    progress = RunProgress(scn)
    starts, goals = scn.start_states(), scn.goal_states()
    assert progress.describe(0, starts) == ("0/4 at goal", "ETA -")
    halfway = (starts + goals) / 2
    halfway[0] = goals[0]
    goals_text, eta = progress.describe(10, halfway)
    assert goals_text == "1/4 at goal" and eta.startswith("ETA ~")
    assert progress.describe(20, goals)[0] == "4/4 at goal"


def test_a_line_per_report_when_not_a_terminal(capsys):
    scn = builtin_scenario("paper-2d")
    report = _progress_lines(scn, every_s=0.0)
    report(3, 600, scn.start_states())
    report(4, 600, scn.goal_states())
    lines = capsys.readouterr().err.splitlines()
    assert len(lines) == 2
    assert lines[0].startswith("swarmpc: paper-2d: step 3/600, 0/4 at goal")
    assert "4/4 at goal" in lines[1]
    quiet = _progress_lines(scn, every_s=3600.0)
    quiet(5, 600, np.asarray(scn.start_states()))
    assert capsys.readouterr().err == ""
