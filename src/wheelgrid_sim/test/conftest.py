"""Shared fixtures: small simulate() runs written once per session (tests only read them)."""

from __future__ import annotations

from pathlib import Path

import pytest

from wheelgrid_sim import simulate


@pytest.fixture(scope="session")
def sim_clean(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A noise-free paper-scene run (sqlite3): points must lie exactly on the boxes."""
    out = tmp_path_factory.mktemp("sim_clean")
    simulate(out, seed=3, frames=12, rate=5.0, scene="paper", stride=4, noise=False)
    return out


@pytest.fixture(scope="session")
def sim_mcap(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A noisy random-scene run stored as mcap."""
    out = tmp_path_factory.mktemp("sim_mcap")
    simulate(out, seed=11, frames=6, rate=2.0, scene="random", stride=4, storage="mcap")
    return out


@pytest.fixture(scope="session")
def bundled_bag() -> Path:
    return Path(__file__).resolve().parents[3] / "bags" / "paper_room"
