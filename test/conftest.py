"""Fixtures for the whole-chain tests: the bundled bag, and one live demo run shared by tests."""

from __future__ import annotations

import json
import os
import subprocess
from pathlib import Path

import pytest

from wheelgrid_common.testing import wheelgrid_command

ROOT = Path(__file__).resolve().parents[1]
BAG_DIR = ROOT / "bags" / "paper_room"


def run_wheelgrid(args: list[str], timeout: float, **kw) -> subprocess.CompletedProcess:
    """Run ``wheelgrid ARGS`` with this interpreter (the venv) in its own process group."""
    return subprocess.run(
        wheelgrid_command(*args),
        cwd=ROOT,
        capture_output=True,
        text=True,
        timeout=timeout,
        start_new_session=True,
        **kw,
    )


@pytest.fixture(scope="session")
def run_wg():
    """The ``wheelgrid`` command as a function: run_wg(args, timeout) -> CompletedProcess."""
    return run_wheelgrid


@pytest.fixture(scope="session")
def repo_root() -> Path:
    return ROOT


@pytest.fixture(scope="session")
def bag_dir() -> Path:
    if not (BAG_DIR / "scan" / "metadata.yaml").exists():
        pytest.skip("bundled bag bags/paper_room is missing")
    return BAG_DIR


@pytest.fixture(scope="session")
def live_demo(tmp_path_factory, bag_dir) -> dict:
    """One `wheelgrid demo` run over real DDS on loopback; its out/ folder and exit code."""
    out = tmp_path_factory.mktemp("demo") / "out"
    env = dict(os.environ)
    proc = run_wheelgrid(["demo", "--bag", str(bag_dir), "--out", str(out)], timeout=400, env=env)
    summary = (
        json.loads((out / "summary.json").read_text()) if (out / "summary.json").exists() else {}
    )
    return {
        "out": out,
        "code": proc.returncode,
        "stdout": proc.stdout,
        "stderr": proc.stderr,
        "summary": summary,
    }
