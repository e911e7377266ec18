"""A dependency-free progress bar for long offline work (map building, bag writing).

Redraws in place on a terminal; on a pipe or in CI it prints a line every 10 %, so logs stay
short but still show that work is moving.
"""

from __future__ import annotations

import sys
import time
from typing import TextIO


class Progress:
    def __init__(
        self, total: int, desc: str, unit: str = "frames", stream: TextIO | None = None
    ) -> None:
        self.total = max(int(total), 0)
        self.desc = desc
        self.unit = unit
        self.stream = stream if stream is not None else sys.stderr
        self.tty = bool(getattr(self.stream, "isatty", lambda: False)())
        self.count = 0
        self.start = time.monotonic()
        self._last_draw = 0.0
        self._last_decile = -1
        self._drawn = 0  # the length of the line last drawn over with "\r"
        self.postfix = ""

    def update(self, n: int = 1, postfix: str | None = None) -> None:
        self.count += n
        if postfix is not None:
            self.postfix = postfix
        now = time.monotonic()
        if self.tty:
            if now - self._last_draw >= 0.1 or self.count >= self.total:
                self._draw(now, end="\r")
                self._last_draw = now
        elif self.total:
            decile = min(10, int(10 * self.count / self.total))
            if decile != self._last_decile:
                self._last_decile = decile
                self._draw(now, end="\n")

    def _draw(self, now: float, end: str) -> None:
        elapsed = now - self.start
        rate = self.count / elapsed if elapsed > 0 else 0.0
        if self.total:
            frac = min(1.0, self.count / self.total)
            bar = "#" * int(24 * frac) + "-" * (24 - int(24 * frac))
            text = f"{self.desc} [{bar}] {self.count}/{self.total} {self.unit}"
        else:
            text = f"{self.desc} {self.count} {self.unit}"
        text += f" {rate:.1f} {self.unit}/s {elapsed:.1f} s"
        if self.postfix:
            text += f" {self.postfix}"
        if self.tty:
            # "\r" goes back, but writes over only as far as the new line reaches: a shorter
            # one ("9.9 frames/s" after "10.1") left the old tail on screen ("used 194")
            text, self._drawn = text.ljust(self._drawn), len(text) if end == "\r" else 0
        self.stream.write(text + end)
        self.stream.flush()

    def finish(self, postfix: str) -> None:
        """The last word on the bar, once work that ends after the last update is done (the
        mapper registers its last frame after the bar reached it: "942/942 ... used 941")."""
        changed = postfix != self.postfix
        self.postfix = postfix
        if not self.tty and changed:
            self._draw(time.monotonic(), end="\n")

    def close(self) -> None:
        if self.tty:
            self._draw(time.monotonic(), end="\n")

    def __enter__(self) -> Progress:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()
