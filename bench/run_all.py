"""Run every stage benchmark and print the README's table (figure, baseline, ratio, machine).

    python bench/run_all.py [--quick] [--only NAME ...] [--update-readme]

Each ``bench/bench_<stage>.py`` accepts ``--json FILE`` (and ``--quick``) and writes
``{"rows": [{"figure", "value", "unit", "baseline", "ratio", "note"}]}``. This script runs them
one after another (never in parallel: they time themselves on a 2-core machine), collects the
rows, and with ``--update-readme`` rewrites the block between the BENCH markers in README.md, so
the table is regenerated rather than typed.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import subprocess
import sys
import tempfile
import time
from pathlib import Path

HERE = Path(__file__).resolve().parent
ROOT = HERE.parent
BEGIN, END = "<!-- BENCH:BEGIN -->", "<!-- BENCH:END -->"


def machine() -> str:
    cpu = platform.processor() or "unknown CPU"
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                cpu = line.split(":", 1)[1].strip()
                break
    except OSError:
        pass
    mem = ""
    try:
        kb = int(Path("/proc/meminfo").read_text().split()[1])
        mem = f", {kb / 1024**2:.0f} GiB"
    except (OSError, ValueError, IndexError):
        pass
    return f"{os.cpu_count()} cores ({cpu}){mem}, Python {platform.python_version()}"


def fmt(v: object) -> str:
    if isinstance(v, float):
        return f"{v:.3g}" if abs(v) < 1000 else f"{v:,.0f}"
    return "" if v is None else str(v)


def run_one(script: Path, quick: bool) -> tuple[list[dict], float, str]:
    with tempfile.TemporaryDirectory() as tmp:
        out = Path(tmp) / "rows.json"
        cmd = [sys.executable, str(script), "--json", str(out)] + (["--quick"] if quick else [])
        t0 = time.monotonic()
        proc = subprocess.run(cmd, cwd=ROOT, capture_output=True, text=True)
        dt = time.monotonic() - t0
        if proc.returncode != 0 or not out.exists():
            tail = "\n".join((proc.stdout + proc.stderr).splitlines()[-15:])
            return [], dt, f"FAILED (exit {proc.returncode}):\n{tail}"
        return json.loads(out.read_text()).get("rows", []), dt, proc.stdout


def table(results: dict[str, list[dict]], quick: bool) -> str:
    lines = [
        f"Machine: {machine()}. Mode: {'quick' if quick else 'full'}. "
        f"Command: `make bench{' ARGS=--quick' if quick else ''}` (python bench/run_all.py).",
        "",
        "| stage | figure | value | baseline | ratio | note |",
        "|---|---|---|---|---|---|",
    ]
    for stage, rows in results.items():
        for r in rows:
            value = f"{fmt(r.get('value'))} {r.get('unit', '')}".strip()
            base = r.get("baseline")
            base_s = (
                f"{fmt(base)} {r.get('unit', '')}".strip()
                if isinstance(base, int | float)
                else fmt(base)
            )
            ratio = r.get("ratio")
            ratio_s = f"{ratio:.2f}x" if isinstance(ratio, int | float) else fmt(ratio)
            lines.append(
                f"| {stage} | {r.get('figure', '')} | {value} | {base_s} | {ratio_s} "
                f"| {r.get('note', '')} |"
            )
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true", help="CI-sized inputs")
    ap.add_argument("--only", nargs="*", help="stage names (bench_<name>.py)")
    ap.add_argument("--update-readme", action="store_true")
    args = ap.parse_args(argv)
    scripts = sorted(HERE.glob("bench_*.py"))
    if args.only:
        scripts = [s for s in scripts if s.stem.removeprefix("bench_") in args.only]
    results: dict[str, list[dict]] = {}
    failed = []
    for script in scripts:
        stage = script.stem.removeprefix("bench_")
        print(f"== {stage} ...", flush=True)
        rows, dt, log = run_one(script, args.quick)
        print(log.rstrip(), flush=True)
        print(f"== {stage}: {len(rows)} figures in {dt:.0f} s", flush=True)
        if not rows:
            failed.append(stage)
        results[stage] = rows
    text = table(results, args.quick)
    print()
    print(text)
    if args.update_readme:
        readme = ROOT / "README.md"
        body = readme.read_text()
        if BEGIN in body and END in body:
            head, rest = body.split(BEGIN, 1)
            _, tail = rest.split(END, 1)
            readme.write_text(f"{head}{BEGIN}\n{text}\n{END}{tail}")
            print(f"\nREADME.md table updated ({sum(len(r) for r in results.values())} rows)")
    if failed:
        print(f"\nbenchmarks that failed: {', '.join(failed)}", file=sys.stderr)
        return 1
    return 0


if __name__ == "__main__":
    sys.exit(main())
