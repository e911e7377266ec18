"""Fast DDS shared-memory segments left behind by processes that died.

A participant maps a segment file in /dev/shm and holds an exclusive ``flock`` on its ``_el``
lock file while it lives; a clean exit removes both. A process killed outright (SIGKILL, the
OOM killer, a crash) leaves them, and /dev/shm is RAM: with wheelgrid's profile each
participant's segment is 16 MB, so every node killed cost about 17 MB until the next reboot
(a node that crashes and is restarted over and over fills the machine), and a day of this
project's test runs had left 57 such segments, about 400 MB. Fast DDS does not remove them itself;
``fastdds shm clean`` (not in the pip wheels) does, by the same rule as here: a lock file that
nobody holds is a dead participant's.
"""

from __future__ import annotations

import fcntl
import os
import re
from dataclasses import dataclass
from pathlib import Path

SHM_DIR = Path("/dev/shm")
# A segment's lock file: "fastrtps_" (Fast DDS 2, Jazzy) or "fastdds_" (Fast DDS 3) and 16
# characters of id. Port files (fastrtps_port7411 ...) are shared by every participant of a
# domain and reused by number; they are small and left to Fast DDS.
_SEGMENT_LOCK = re.compile(r"^(fastrtps|fastdds)_[0-9a-z]{16}_el$")


@dataclass(frozen=True)
class ShmCleanup:
    """What :func:`clean_dead_segments` found: segments removed, their bytes, segments in use."""

    removed: int
    bytes: int
    in_use: int


def _held(lock_file: Path) -> bool:
    """True while a live process holds the lock (or the file cannot be opened: not ours)."""
    try:
        fd = os.open(lock_file, os.O_RDONLY | os.O_NOFOLLOW)
    except OSError:
        return True
    try:
        fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
    except OSError:
        return True
    finally:
        os.close(fd)  # closing drops the lock again, if it was taken
    return False


def clean_dead_segments(shm_dir: Path = SHM_DIR) -> ShmCleanup:
    """Remove the Fast DDS segments whose owner is dead; never one a live process holds.

    Safe to call at any time: a live participant holds its lock from before its segment
    exists until after it is removed. Files of other users are skipped (no permission)."""
    removed = freed = in_use = 0
    try:
        names = os.listdir(shm_dir)
    except OSError:
        return ShmCleanup(0, 0, 0)
    for name in names:
        if not _SEGMENT_LOCK.match(name):
            continue
        lock = shm_dir / name
        if _held(lock):
            in_use += 1
            continue
        segment = shm_dir / name[: -len("_el")]
        try:
            size = segment.stat().st_size
            segment.unlink()
        except OSError:
            size = 0  # already gone (the lock outlived it) or not ours to remove
        try:
            lock.unlink()
        except OSError:
            continue
        removed += 1
        freed += size
    return ShmCleanup(removed, freed, in_use)
