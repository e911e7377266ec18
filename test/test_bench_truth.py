"""The benchmark's truth metrics, checked against distances worked out by hand."""

from __future__ import annotations

import importlib.util
import json
import sys
from pathlib import Path
from types import ModuleType

import numpy as np

from wheelgrid_sim import paper_scene

BENCH = Path(__file__).resolve().parents[1] / "bench"


def bench_module(name: str) -> ModuleType:
    """A bench/ script as a module (bench/ is no package): its functions, not its main()."""
    spec = importlib.util.spec_from_file_location(name, BENCH / f"{name}.py")
    assert spec is not None and spec.loader is not None
    module = importlib.util.module_from_spec(spec)
    sys.modules[name] = module  # its dataclasses look their module up there
    spec.loader.exec_module(module)
    return module


def test_near_surface_share_ignores_the_far_faces_of_walls_floor_and_ceiling() -> None:
    """ "Map points within 5 cm of a true surface" measured each point to every face of every
    scene box, the 20 cm thick shell boxes' far faces included: a wall mapped 15-25 cm behind
    the true one, or a floor 15-25 cm too low, counted as on the truth."""
    near_surface_pct = bench_module("bench_mapping").near_surface_pct
    scene = json.loads(paper_scene().dumps())
    behind = np.array(
        [
            [-0.18, 5.0, 1.0],  # 18 cm behind the west wall
            [9.8, 2.0, 1.0],  # 20 cm behind the east wall
            [5.0, 7.0, -0.19],  # 19 cm under the floor
            [5.0, 7.0, 2.88],  # 18 cm above the ceiling
        ]
    )
    assert near_surface_pct(behind, scene) == 0.0
    on = np.array([[-0.02, 5.0, 1.0], [5.0, 7.0, 0.01], [1.1, 5.4, 0.74]])
    assert near_surface_pct(on, scene) == 100.0


def test_transport_lines_give_the_baseline_with_its_unit_and_no_empty_one() -> None:
    """`python bench/bench_transport.py` printed "0 packets (baseline ) must be 0" for the
    leak count, which has no baseline, and the delivered share's baseline without its %."""
    row_line = bench_module("bench_transport").row_line
    leak = dict(
        figure="RTPS packets leaving", value=0, unit="packets", baseline="", note="must be 0"
    )
    assert row_line(leak) == "RTPS packets leaving: 0 packets; must be 0"
    share = dict(figure="delivered at 10 Hz", value=100.0, unit="%", baseline=36.0, note="n=100")
    assert row_line(share) == "delivered at 10 Hz: 100.0 % (baseline 36.0 %); n=100"


def test_the_bench_does_not_score_a_box_that_wheelgrid_measure_refuses(capsys) -> None:
    """A ghost copy of table B's face 3 cm nearer table A (as a loop might leave): `wheelgrid
    measure` refuses the box (a second surface nearer the other box), while the bench read
    9(a) off it, 0 % deviation, and counted the target met (a review)."""
    bench = bench_module("bench_mapping")
    scene = paper_scene()
    pts = scene.interior_surface_points(0.02)
    x_face = 1.1 + 1.2012  # table B's west face
    face = pts[
        (np.abs(pts[:, 0] - x_face) < 1e-9)
        & (pts[:, 1] >= 4.95)
        & (pts[:, 1] <= 5.85)
        & (pts[:, 2] >= 0.1)
        & (pts[:, 2] <= 0.745)
    ]
    ghost = face[face[:, 2] < 0.45].copy()
    ghost[:, 0] -= 0.03
    bench.truth_rows("ghost", np.vstack([pts, ghost]), json.loads(scene.dumps()))
    out = capsys.readouterr().out
    assert "ghost: 9(a)" in out and "not measurable (a second surface nearer" in out, out
    assert "ghost: Table I 9(a) table A to table B deviation" not in out, out
