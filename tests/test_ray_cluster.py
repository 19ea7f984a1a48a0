"""A stock Ray cluster (``ray start --head`` with Ray's default token authentication) is joined
like any other Ray application, and gives the same plans as the serial executor."""

from __future__ import annotations

import os
import signal
import socket
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

pytest.importorskip("ray")

RAY = str(Path(sys.executable).with_name("ray"))


def _free_port() -> int:
    with socket.socket() as sock:
        sock.bind(("127.0.0.1", 0))
        return int(sock.getsockname()[1])


def _wait_for_port(port: int, timeout_s: float) -> None:
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        try:
            with socket.create_connection(("127.0.0.1", port), timeout=1.0):
                return
        except OSError:
            time.sleep(0.5)
    raise AssertionError(f"the Ray head did not open port {port} within {timeout_s} s")


@pytest.fixture(scope="module")
def head(tmp_path_factory):
    """A head node in a subprocess, with a token made the way Ray's docs say; stopped by its pid."""
    home = tmp_path_factory.mktemp("home")
    env = {**os.environ, "HOME": str(home)}
    env.pop("RAY_AUTH_MODE", None)
    env.pop("RAY_ADDRESS", None)
    subprocess.run([RAY, "get-auth-token", "--generate"], env=env, check=True, capture_output=True)
    assert (home / ".ray" / "auth_token").is_file()
    port = _free_port()
    process = subprocess.Popen(
        [RAY, "start", "--head", "--block", f"--port={port}", "--num-cpus=2", "--include-dashboard=false",
         f"--temp-dir={tmp_path_factory.mktemp('ray')}"],
        env=env, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True,
    )
    try:
        _wait_for_port(port, 90)
        yield env, port
    finally:
        process.send_signal(signal.SIGTERM)
        try:
            process.wait(timeout=60)
        except subprocess.TimeoutExpired:
            process.kill()
            process.wait()


def _run(env: dict, out: Path, *args: str) -> subprocess.CompletedProcess:
    return subprocess.run(
        [sys.executable, "-m", "swarmpc", "run", "paper-2d", "--max-steps", "6", "--out", str(out), "-q", *args],
        env=env, capture_output=True, text=True, timeout=300,
    )


@pytest.mark.loop
def test_a_stock_head_node_is_joined_and_plans_match_serial(head, tmp_path):
    env, port = head
    joined = _run(env, tmp_path / "ray", "--executor", "ray", "--address", f"127.0.0.1:{port}")
    assert joined.returncode == 0, joined.stderr
    serial = _run(env, tmp_path / "serial")
    assert serial.returncode == 0, serial.stderr
    with np.load(tmp_path / "ray" / "trajectory.npz") as a, np.load(tmp_path / "serial" / "trajectory.npz") as b:
        assert a["states"].shape[0] == 7
        assert np.array_equal(a["states"], b["states"])


def test_a_refused_address_is_one_line_within_30_s(tmp_path):
    started = time.monotonic()
    done = _run(dict(os.environ), tmp_path / "out", "--executor", "ray", "--address", f"127.0.0.1:{_free_port()}")
    assert time.monotonic() - started < 30
    assert done.returncode == 2 and done.stderr.strip().count("\n") == 0, done.stderr
    assert done.stderr.startswith("swarmpc: error: --address:")
    assert not (tmp_path / "out").exists()
