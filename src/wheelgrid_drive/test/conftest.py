"""Fixtures for the drive tests: simulated controllers on real ptys, always stopped."""

from __future__ import annotations

from collections.abc import Callable, Iterator

import pytest

from wheelgrid_common.services import poll_until
from wheelgrid_drive.link import MotorLink
from wheelgrid_drive.motor_sim import MotorSim, MotorSimConfig


@pytest.fixture
def make_sim() -> Iterator[Callable[..., MotorSim]]:
    """Start MotorSim threads (kinematics 20x faster than real time unless told otherwise)."""
    sims: list[MotorSim] = []

    def make(**kw: object) -> MotorSim:
        kw.setdefault("time_scale", 20.0)
        sim = MotorSim(MotorSimConfig(**kw)).start()  # type: ignore[arg-type]
        sims.append(sim)
        return sim

    yield make
    for sim in sims:
        sim.stop()


@pytest.fixture
def make_link() -> Iterator[Callable[..., MotorLink]]:
    """Open MotorLinks that record their events; closed (with STOP) at the end."""
    links: list[MotorLink] = []

    def make(port: str, heartbeat: bool = True, **kw: object) -> MotorLink:
        events: list[tuple[str, str]] = []
        link = MotorLink(port, on_event=lambda k, m: events.append((k, m)), **kw)  # type: ignore[arg-type]
        link.events = events  # type: ignore[attr-defined]
        link.open()
        if heartbeat:
            link.start_heartbeat()
        links.append(link)
        return link

    yield make
    for link in links:
        link.close()


def wait_for(predicate: Callable[[], bool], timeout: float = 5.0, step: float = 0.01) -> bool:
    """Poll ``predicate`` until true or ``timeout`` s (threads do the work, we just watch)."""
    return poll_until(predicate, timeout, step)


@pytest.fixture
def wait() -> Callable[..., bool]:
    return wait_for
