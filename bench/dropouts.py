"""What a dropout costs the map, and what a pose prior that re-anchors across one does to it.

    python bench/dropouts.py [--set dev|held|fresh|all] [--ambiguity M] [--workers N]

The bundled bag (`bags/paper_room`, 210 clouds at 5 Hz, `--prior arkit`, no loop closure) with
three clouds lost (0.6 s; the odometry goes on) and, from the odometry message after them,
the odometry's world moved by a shift in x, y (ARKit re-anchoring while the stream was down).
Each run is `wheelgrid map` on the edited bag; its trajectory is compared with the bag's true
poses (`poses_map.tum`). Per run: the frames that failed, the frames mapped after the gap, and
the largest position error of any mapped frame. A run with the prior right must resume; one
whose prior moved must either end the map at the gap or stay within the online drift (8-9 cm
on the untouched bag): this prints how many ran on more than 12 cm off, and how far.

The sets, in the order they were made (docs/mapping.md tells which rule each one shaped):
``dev`` the gaps at clouds 6, 20, 40, 100 with shifts of 15 and 30 cm along x or y; ``held``
the gaps at 50, 75, 130, 150 with four mixed shifts; ``fresh`` the gaps at 30, 60, 90, 115,
140, 170 with three. Each has a run with the prior right per gap. ``--ambiguity 0`` turns the
ambiguity test after a gap off (``registration.relocalise_ambiguity``), for a side-by-side
reading. Fidelity, not speed: nothing here is timed, and it is no stage of `make bench`. The
three sets take about 4 minutes on 2 cores.
"""

from __future__ import annotations

import argparse
import contextlib
import io
import json
import shutil
import sys
import tempfile
from multiprocessing import Pool
from pathlib import Path
from typing import Any

import numpy as np

from wheelgrid_common.testing import dropout_bag, poses_by_stamp
from wheelgrid_mapping import cli_map

ROOM = Path(__file__).resolve().parents[1] / "bags" / "paper_room"
LOST = 3  # clouds lost in a row: 0.6 s at the bag's 5 Hz
OFF = 0.12  # m: more than the online drift (8-9 cm on the untouched bag)

SETS: dict[str, tuple[list[int], list[tuple[float, float]]]] = {
    "dev": ([6, 20, 40, 100], [(0.0, 0.0), (0.15, 0.0), (0.3, 0.0), (0.0, 0.15), (0.0, 0.3)]),
    "held": (
        [50, 75, 130, 150],
        [(0.0, 0.0), (0.1, 0.0), (-0.2, 0.1), (0.05, -0.2), (0.2, 0.2)],
    ),
    "fresh": ([30, 60, 90, 115, 140, 170], [(0.0, 0.0), (0.25, 0.0), (0.0, -0.25), (-0.15, -0.15)]),
}


def run(job: tuple[int, tuple[float, float], str, str]) -> dict[str, Any]:
    """One edited bag mapped: what failed, what was mapped after the gap, how far off."""
    first, (dx, dy), root, config = job
    last = first + LOST - 1
    out = Path(root) / f"gap{first}_{dx:+.2f}_{dy:+.2f}"
    shutil.rmtree(out, ignore_errors=True)
    out.mkdir(parents=True)
    bag = dropout_bag(ROOM / "scan", out / "bag", first, last, (dx, dy))
    argv = [str(bag), "--out", str(out / "map"), "--prior", "arkit", "--no-loop-closure"]
    if config:
        argv += ["--config", config]
    with contextlib.redirect_stderr(io.StringIO()), contextlib.redirect_stdout(io.StringIO()):
        rc = cli_map.main(argv)
    row: dict[str, Any] = {"first": first, "shift": (dx, dy), "rc": rc}
    if rc != 0:
        return row
    report = json.loads((out / "map" / "report.json").read_text())
    est, truth = (
        poses_by_stamp(out / "map" / "trajectory.tum"),
        poses_by_stamp(ROOM / "poses_map.tum"),
    )
    gap_end = sorted(truth)[last]
    row["failed"] = report["frames"]["failed"]
    row["mapped_after"] = sum(t > gap_end for t in est)
    row["worst"] = max(float(np.linalg.norm(est[t][:3, 3] - truth[t][:3, 3])) for t in est)
    shutil.rmtree(out)  # a bag and a map a run: 64 of them would fill a small disk
    return row


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--set", choices=[*SETS, "all"], default="all")
    ap.add_argument("--ambiguity", type=float, default=None, help="relocalise_ambiguity (m)")
    ap.add_argument("--workers", type=int, default=2)
    args = ap.parse_args(argv)
    if not (ROOM / "scan" / "metadata.yaml").exists():
        print(f"dropouts: {ROOM / 'scan'} is missing", file=sys.stderr)
        return 2
    names = list(SETS) if args.set == "all" else [args.set]
    with tempfile.TemporaryDirectory(prefix="wheelgrid-dropouts-") as tmp:
        config = ""
        if args.ambiguity is not None:
            config = str(Path(tmp) / "config.yaml")
            Path(config).write_text(f"registration: {{relocalise_ambiguity: {args.ambiguity}}}\n")
        jobs = [
            (first, shift, tmp, config)
            for name in names
            for first in SETS[name][0]
            for shift in SETS[name][1]
        ]
        print(f"{'gap':>9} {'shift (m)':>13} {'failed':>6} {'after':>5} {'worst (cm)':>10}")
        rows = []
        with Pool(args.workers) as pool:
            for row in pool.imap(run, jobs):
                rows.append(row)
                gap = f"{row['first']}-{row['first'] + LOST - 1}"
                shift = "{:+.2f},{:+.2f}".format(*row["shift"])
                if row["rc"] != 0:
                    print(f"{gap:>9} {shift:>13}   wheelgrid map exited {row['rc']}")
                    continue
                print(
                    f"{gap:>9} {shift:>13} {row['failed']:>6} {row['mapped_after']:>5} "
                    f"{100 * row['worst']:>10.1f}",
                    flush=True,
                )
    right = [r for r in rows if r["shift"] == (0.0, 0.0) and r["rc"] == 0]
    moved = [r for r in rows if r["shift"] != (0.0, 0.0) and r["rc"] == 0]
    ran_off = [r for r in moved if r["mapped_after"] and r["worst"] > OFF]
    ended = sum(not r["mapped_after"] for r in moved)
    print(
        f"prior right: {len(right)} runs, {sum(r['failed'] for r in right)} frames failed, "
        f"{sum(r['mapped_after'] == 0 for r in right)} never resumed, worst "
        f"{100 * max((r['worst'] for r in right), default=0.0):.1f} cm"
    )
    worst = max((r["worst"] for r in ran_off), default=0.0)
    print(
        f"prior re-anchored: {len(moved)} runs, {ended} ended the map at the gap, "
        f"{len(ran_off)} ran on more than {100 * OFF:.0f} cm off (worst {100 * worst:.1f} cm)"
    )
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
