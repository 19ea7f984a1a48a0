"""The command line starts without the heavy libraries only some commands need."""

from __future__ import annotations

import subprocess
import sys


def test_the_command_line_imports_no_scipy_matplotlib_or_ray_until_a_command_needs_them():
    """Every call of ``swarmpc`` pays its imports: a bad argument or ``--help`` should not wait
    for scipy (about 0.4 s), matplotlib or Ray."""
    code = "import sys, swarmpc.cli; print(sorted(m for m in ('scipy', 'matplotlib', 'ray') if m in sys.modules))"
    loaded = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True).stdout
    assert loaded.strip() == "[]"
