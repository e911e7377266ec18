"""import-stray that fails mid-way (a full disk, Ctrl-C) leaves no bag behind: the part written
had a metadata.yaml and opened as if complete, and a full disk on sqlite3 was a traceback."""

from __future__ import annotations

import sqlite3
from pathlib import Path

import pytest

from wheelgrid_common import bagio
from wheelgrid_mapping.cli_stray import import_main


@pytest.mark.parametrize(
    ("error", "code"),
    [
        (sqlite3.OperationalError("database or disk is full"), 1),
        (OSError(28, "No space left on device"), 1),
        (KeyboardInterrupt(), 130),
    ],
)
def test_an_import_that_fails_mid_way_leaves_no_bag(
    tmp_path: Path, stray_capture: Path, monkeypatch, capsys, error: BaseException, code: int
) -> None:
    real = bagio.BagWriter.write
    written = []

    def write(self: bagio.BagWriter, *args: object) -> None:
        if len(written) == 7:  # a frame and a bit: the disk fills up
            raise error
        written.append(args)
        real(self, *args)  # type: ignore[arg-type]

    monkeypatch.setattr(bagio.BagWriter, "write", write)
    out = tmp_path / "bag"
    assert import_main([str(stray_capture), "--out", str(out), "--frames", "3"]) == code
    err = capsys.readouterr().err
    assert "Traceback" not in err and "no bag was made" in err, err
    assert not out.exists()
