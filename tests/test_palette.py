"""One colour per agent across every picture: the figures' and the viewer's come from one palette."""

from __future__ import annotations

import re

import pytest
from matplotlib.colors import to_hex

from swarmpc import palette, plots


@pytest.mark.parametrize("m", [1, 4, 10, 11, 16, 64])
def test_colours_are_valid_distinct_and_shared(m):
    colors = palette.agent_colors(m)
    assert len(colors) == m and len(set(colors)) == m
    assert all(re.fullmatch(r"#[0-9a-f]{6}", c) for c in colors)
    assert [to_hex(c) for c in plots.agent_colors(m)] == colors


def test_the_viewer_draws_each_agent_in_its_palette_colour(tmp_path):
    from swarmpc.scenarios import builtin_scenario
    from swarmpc.simulation.loop import simulate
    from swarmpc.simulation.results import write_run
    from swarmpc.viewer import load_run, run_figure_dict

    folder = write_run(simulate(builtin_scenario("paper-2d").with_updates(**{"stop.max_steps": 2})), tmp_path / "r")
    figure = run_figure_dict(load_run(folder))
    used = {str(trace.get("line", {}).get("color", "")).lower() for trace in figure["data"]}
    assert set(palette.agent_colors(4)) <= used
