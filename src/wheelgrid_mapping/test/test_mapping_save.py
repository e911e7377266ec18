"""Mapper.save: all three files or none. A save that fails leaves the previous map as it was
(a second `wheelgrid map` into the same --out that hit a full disk used to leave a cut-off
map.ply beside the first run's trajectory and report, the first map gone)."""

from __future__ import annotations

import errno
import json
from pathlib import Path

import numpy as np
import pytest

from wheelgrid_common.fileio import read_ply
from wheelgrid_common.testing import body_frame_room
from wheelgrid_mapping import pipeline
from wheelgrid_mapping.pipeline import Mapper, MapperConfig


def _mapped(frames: int, seed: int) -> Mapper:
    rng = np.random.default_rng(seed)
    m = Mapper(cfg=MapperConfig(level_min_frames=2))
    for i in range(frames):
        assert m.add_frame(body_frame_room(rng, True), i * 0.2, "base_link").status == "used"
    return m


def _contents(folder: Path) -> dict[str, bytes]:
    return {p.name: p.read_bytes() for p in sorted(folder.iterdir())}


@pytest.mark.parametrize("fails", ["write_ply", "write_tum"])
def test_a_save_that_fails_keeps_the_previous_map(fails: str, tmp_path: Path, monkeypatch) -> None:
    _mapped(2, 1).save(tmp_path)
    before = _contents(tmp_path)
    assert set(before) == {"map.ply", "trajectory.tum", "report.json"}

    real = getattr(pipeline, fails)

    def disk_full(path: Path, *args: object, **kwargs: object) -> None:
        real(path, *args, **kwargs)  # part of it written, then the disk is full
        with open(path, "r+b") as fh:
            fh.truncate(max(fh.seek(0, 2) // 2, 1))
        raise OSError(errno.ENOSPC, "No space left on device")

    monkeypatch.setattr(pipeline, fails, disk_full)
    with pytest.raises(OSError, match="No space"):
        _mapped(3, 2).save(tmp_path)
    assert _contents(tmp_path) == before  # nothing replaced, no partial file left behind
    assert read_ply(tmp_path / "map.ply").shape[0] > 0


def test_a_save_that_succeeds_replaces_all_three(tmp_path: Path) -> None:
    _mapped(2, 1).save(tmp_path)
    rep = _mapped(3, 2).save(tmp_path)
    assert sorted(p.name for p in tmp_path.iterdir()) == [
        "map.ply",
        "report.json",
        "trajectory.tum",
    ]
    assert json.loads((tmp_path / "report.json").read_text())["frames"]["used"] == 3
    assert rep["frames"]["used"] == 3
    assert len((tmp_path / "trajectory.tum").read_text().splitlines()) == 3
