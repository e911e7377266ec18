"""Frames prepared one ahead, in a second process, while the mapper registers the frame before.

On two cores a 256x192 keyframe costs about 65 ms of preparation (filters, and registration's
inputs: :func:`~.pipeline.prepare_frame`) and 50 ms of registering and integrating, one after
the other in one process: that is slower than a keyframe every 0.1 s on a busy machine. The
preparation needs nothing from the map, so a second process does it for frame k+1 while this
one registers frame k; the map, the poses and the report are the same numbers as in one
process (it is the same code on the same inputs), only sooner.

A second *process* because both halves hold the GIL most of the time (numpy's small calls,
KISS-ICP's binding), so a thread would not overlap them. It is started with ``spawn`` (a fork
of a process running DDS threads is not safe), imports only numpy and this package, never ROS,
and ends when its pipe closes: with the mapper, however that ends. Where it cannot start or
dies, frames are prepared in this process instead, and nothing is lost: a frame is kept until
its preparation has come back.
"""

from __future__ import annotations

import contextlib
import multiprocessing as mp
import signal
from dataclasses import dataclass
from typing import Any

import numpy as np

from .pipeline import DEFAULT_FRAME_ID, FrameOutcome, Mapper, PreparedFrame, prepare_frame
from .preprocess import PreprocessConfig
from .registration import RegistrationConfig


def _serve(conn: Any) -> None:
    """The second process: prepare each frame sent, until the pipe closes. Ctrl-C in a
    terminal reaches the whole process group: the mapper decides when this one ends."""
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    while True:
        try:
            points, confidence, pre, reg = conn.recv()
        except (EOFError, OSError, KeyboardInterrupt):
            return
        try:
            reply: tuple[str, Any] = ("ok", prepare_frame(points, confidence, pre, reg))
        except Exception as exc:  # the caller prepares it again itself, and sees the error
            reply = ("error", repr(exc))
        try:
            conn.send(reply)
        except OSError:  # the mapper closed the pipe mid-frame (it ended): nothing to answer
            return
        except Exception as exc:  # a result that does not pickle: the caller prepares it
            try:
                conn.send(("error", repr(exc)))
            except OSError:
                return


class _Worker:
    """One spawned process and its pipe; one frame in flight at a time."""

    def __init__(self) -> None:
        ctx = mp.get_context("spawn")
        self.conn, child = ctx.Pipe()
        self.proc = ctx.Process(target=_serve, args=(child,), name="wheelgrid-prepare", daemon=True)
        self.proc.start()
        child.close()

    def send(
        self,
        points: np.ndarray,
        confidence: np.ndarray | None,
        pre: PreprocessConfig,
        reg: RegistrationConfig,
    ) -> None:
        self.conn.send((points, confidence, pre, reg))

    def recv(self) -> tuple[str, Any]:
        result: tuple[str, Any] = self.conn.recv()
        return result

    def close(self) -> None:
        self.conn.close()  # the process sees EOF and returns
        self.proc.join(timeout=2.0)
        if self.proc.is_alive():
            self.proc.kill()
            self.proc.join(timeout=2.0)


@dataclass
class _Pending:
    """A frame admitted and sent, not yet added: its inputs are kept until it is."""

    points: np.ndarray
    confidence: np.ndarray | None
    prior: np.ndarray | None
    stamp: float
    sent: bool  # to the worker (else it is prepared here when its turn comes)
    after_gap: bool | None = None  # Mapper.add_prepared's
    dropped_priors: tuple[float, float] | None = None  # Mapper.add_prepared's
    number: int = -1  # in the input (Mapper.admit's): an error's outcome names it too


class FramePipeline:
    """Feeds a :class:`~.pipeline.Mapper` with each frame prepared one frame ahead.

    :meth:`push` admits a frame (in order: keyframe selection sees every frame as
    :meth:`Mapper.add_frame` would), sends it to the worker, then adds the frame before it,
    whose preparation has come back meanwhile, to the map. So a frame reaches the map one push
    later than with ``add_frame``; :meth:`flush` adds the last one (before a loop closure,
    saving, or the end of a bag). ``ahead=False`` prepares every frame in this process, in
    order, with the same results: what ``add_frame`` does, through the same calls.
    """

    def __init__(self, mapper: Mapper, ahead: bool = True) -> None:
        self.mapper = mapper
        self._worker: _Worker | None = None
        self.note = "off" if not ahead else "second process"
        if ahead:
            try:
                self._worker = _Worker()
            except Exception as exc:  # e.g. no /dev/shm or process limit: one process, slower
                self.note = f"one process ({exc!r})"
        self._pending: _Pending | None = None

    @property
    def ahead(self) -> bool:
        return self._worker is not None

    @property
    def pending(self) -> bool:
        return self._pending is not None

    def push(
        self,
        points: np.ndarray,
        stamp: float,
        frame_id: str = DEFAULT_FRAME_ID,
        confidence: np.ndarray | None = None,
        prior: np.ndarray | None = None,
        received: float | None = None,
        after_gap: bool | None = None,
        dropped_priors: tuple[float, float] | None = None,
        number: int | None = None,
    ) -> list[tuple[float, FrameOutcome]]:
        """Admit this frame and add the one before it: the ``(stamp, outcome)`` of every frame
        finished by this call. A frame skipped between keyframes is finished at once, so its
        outcome can come before that of the frame still in preparation. ``after_gap``,
        ``dropped_priors``: as :meth:`Mapper.add_prepared`'s; ``number``: as
        :meth:`Mapper.admit`'s."""
        skipped = self.mapper.admit(stamp, frame_id, received, number)
        if skipped is not None:
            return [(stamp, skipped)]
        previous = self._pending
        prepared = self._collect(previous) if previous is not None else None
        self._pending = _Pending(
            points,
            confidence,
            prior,
            float(stamp),
            False,
            after_gap,
            dropped_priors,
            self.mapper.newest_admitted,
        )
        if self._worker is not None:
            try:
                self._worker.send(points, confidence, self.mapper.pre, self.mapper.reg_cfg)
                self._pending.sent = True
            except Exception as exc:
                self._give_up(exc)
        done = [] if previous is None or prepared is None else [self._add(previous, prepared)]
        if self._worker is None:  # one process: this frame at once, as add_frame would
            done.extend(self.flush())
        return done

    def flush(self) -> list[tuple[float, FrameOutcome]]:
        """Add the frame still in preparation, if any. It stays :attr:`pending` until added, so
        a reader that sees nothing pending reads every frame's outcome in the counts."""
        previous = self._pending
        if previous is None:
            return []
        try:
            return [self._add(previous, self._collect(previous))]
        finally:
            self._pending = None

    def _add(
        self, frame: _Pending, prepared: PreparedFrame | BaseException
    ) -> tuple[float, FrameOutcome]:
        """The frame added to the map; an exception in its preparation or registration is its
        outcome (``error``), as a bad frame must never stop the frames after it."""
        if not isinstance(prepared, PreparedFrame):
            self.mapper.drop_admitted()
            return frame.stamp, FrameOutcome("error", repr(prepared), number=frame.number)
        try:
            return frame.stamp, self.mapper.add_prepared(
                prepared, frame.prior, frame.after_gap, frame.dropped_priors
            )
        except Exception as exc:
            self.mapper.frames_errored += 1  # read, and neither used, failed nor skipped
            return frame.stamp, FrameOutcome("error", repr(exc), number=frame.number)

    def discard(self) -> None:
        """Forget the frame in preparation (a reset)."""
        if self._pending is not None and self._pending.sent and self._worker is not None:
            try:
                self._worker.recv()  # the answer must not be read as the next frame's
            except Exception as exc:
                self._give_up(exc)
        self._pending = None

    def worker_peak_bytes(self) -> int | None:
        """The second process's peak resident memory so far (Linux's ``VmHWM``), else None.
        Read here because ``getrusage(RUSAGE_CHILDREN)`` is no measure of it: a spawned child
        starts as a fork and keeps the high-water mark of the parent's pages it was forked
        with (a replay that had decoded its frames up front read 495 MiB for a child that
        itself never held 100)."""
        if self._worker is None:
            return None
        try:
            with open(f"/proc/{self._worker.proc.pid}/status") as f:
                for line in f:
                    if line.startswith("VmHWM:"):
                        return int(line.split()[1]) * 1024
        except (OSError, ValueError):
            return None
        return None

    def __enter__(self) -> FramePipeline:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def close(self) -> None:
        """End the second process (a frame still in preparation is not added: :meth:`flush`)."""
        if self._worker is not None:
            self._worker.close()
            self._worker = None

    def _collect(self, frame: _Pending) -> PreparedFrame | BaseException:
        if frame.sent and self._worker is not None:
            try:
                kind, value = self._worker.recv()
            except Exception as exc:
                self._give_up(exc)
            else:
                if kind == "ok":
                    prepared: PreparedFrame = value
                    return prepared
        # Not sent, the worker gone, or its error: here, which gives the error if there is one.
        try:
            return prepare_frame(
                frame.points, frame.confidence, self.mapper.pre, self.mapper.reg_cfg
            )
        except Exception as exc:
            return exc

    def _give_up(self, exc: BaseException) -> None:
        self.note = f"one process (the second one failed: {exc!r})"
        worker, self._worker = self._worker, None
        if worker is not None:
            with contextlib.suppress(Exception):
                worker.close()
