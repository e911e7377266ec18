"""What a pose prior that pauses while the clouds go on does to the map.

    python bench/prior_pauses.py [--loops] [--workers N]

The bundled bag (`bags/paper_room`, 210 clouds at 5 Hz, `--prior arkit`) with odometry
messages lost (every cloud kept) and, on some runs, the odometry's world moved from the
message after them (ARKit re-anchoring while its poses were missing). Each run is `wheelgrid
map` on the edited bag (`--no-loop-closure` unless ``--loops``); its trajectory is compared
with the bag's true poses (`poses_map.tum`). Per run: frames used and failed, the pauses judged
as after a dropout (`after_prior_gap`), and the largest and RMS position error of the mapped
frames. The runs are docs/mapping.md's table ("A pose prior that pauses while the clouds go
on"). Fidelity, not speed: nothing here is timed, and it is no stage of `make bench`; about a
minute on 2 cores (three with ``--loops``).
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

from wheelgrid_common.testing import poses_by_stamp, prior_pause_bag
from wheelgrid_mapping import cli_map

ROOM = Path(__file__).resolve().parents[1] / "bags" / "paper_room"

# (first, last odometry message lost, the odometry's world moved after them (m))
RUNS: list[tuple[int, int, tuple[float, float]]] = [
    (100, 100, (0.0, 0.0)),
    (100, 101, (0.0, 0.0)),
    (100, 109, (0.0, 0.0)),
    (130, 139, (0.0, 0.0)),
    (150, 159, (0.0, 0.0)),
    (50, 59, (0.0, 0.0)),
    (30, 44, (0.0, 0.0)),
    (170, 171, (0.0, 0.0)),
    (100, 109, (0.2, 0.2)),
    (100, 109, (0.0, 0.3)),
    (130, 139, (0.2, 0.2)),
    (150, 152, (0.3, 0.0)),
    (60, 62, (0.1, 0.2)),
    (100, 100, (0.2, 0.2)),
]


def run(job: tuple[int, int, tuple[float, float], str, bool]) -> dict[str, Any]:
    """One edited bag mapped: what failed, how far off the mapped frames are."""
    first, last, (dx, dy), root, loops = job
    out = Path(root) / f"pause{first}-{last}_{dx:+.2f}_{dy:+.2f}"
    shutil.rmtree(out, ignore_errors=True)
    out.mkdir(parents=True)
    bag = prior_pause_bag(ROOM / "scan", out / "bag", first, last, (dx, dy))
    argv = [str(bag), "--out", str(out / "map"), "--prior", "arkit"]
    if not loops:
        argv.append("--no-loop-closure")
    with contextlib.redirect_stderr(io.StringIO()), contextlib.redirect_stdout(io.StringIO()):
        rc = cli_map.main(argv)
    row: dict[str, Any] = {"first": first, "last": last, "shift": (dx, dy), "rc": rc}
    if rc != 0:
        return row
    report = json.loads((out / "map" / "report.json").read_text())
    est = poses_by_stamp(out / "map" / "trajectory.tum")
    truth = poses_by_stamp(ROOM / "poses_map.tum")
    errors = np.array([np.linalg.norm(est[t][:3, 3] - truth[t][:3, 3]) for t in est])
    frames = report["frames"]
    row.update(
        used=frames["used"],
        failed=frames["failed"],
        after_prior_gap=frames.get("after_prior_gap", 0),
        worst=float(errors.max()),
        rmse=float(np.sqrt(np.mean(errors**2))),
    )
    shutil.rmtree(out)
    return row


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--loops", action="store_true", help="close the loops as `wheelgrid map` does")
    ap.add_argument("--workers", type=int, default=2)
    args = ap.parse_args(argv)
    if not (ROOM / "scan" / "metadata.yaml").exists():
        print(f"prior_pauses: {ROOM / 'scan'} is missing", file=sys.stderr)
        return 2
    with tempfile.TemporaryDirectory(prefix="wheelgrid-prior-pauses-") as tmp:
        jobs = [(first, last, shift, tmp, args.loops) for first, last, shift in RUNS]
        print(
            f"{'lost':>9} {'shift (m)':>13} {'used':>4} {'failed':>6} {'gap':>3} "
            f"{'worst (cm)':>10} {'RMSE (cm)':>9}"
        )
        with Pool(args.workers) as pool:
            for row in pool.imap(run, jobs):
                lost = f"{row['first']}-{row['last']}"
                shift = "{:+.2f},{:+.2f}".format(*row["shift"])
                if row["rc"] != 0:
                    print(f"{lost:>9} {shift:>13}   wheelgrid map exited {row['rc']}")
                    continue
                print(
                    f"{lost:>9} {shift:>13} {row['used']:>4} {row['failed']:>6} "
                    f"{row['after_prior_gap']:>3} {100 * row['worst']:>10.1f} "
                    f"{100 * row['rmse']:>9.1f}",
                    flush=True,
                )
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
