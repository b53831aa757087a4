"""Captures and compares the deterministic results the docs print (architecture issue).

A restructuring must not change one printed digit of what the simulator decides. This script runs
the deterministic commands of docs/closed-loop.md and docs/benchmarks.md (accuracy), keeps their
JSON reports, and compares two captures field by field, ignoring what depends on the machine
(latencies, tick times, wall-clock durations, paths).

    python benchmarks/deterministic.py capture OUT_DIR      # at the commit where the work starts
    python benchmarks/deterministic.py capture OUT_DIR2     # at the end
    python benchmarks/deterministic.py compare OUT_DIR OUT_DIR2

``capture`` runs the installed ``hapticloud`` of the interpreter that runs this script.
"""

from __future__ import annotations

import json
import math
import re
import subprocess
import sys
from pathlib import Path

COMMANDS: dict[str, list[str]] = {
    "wall": ["run", "wall", "--quiet", "--report", "{out}"],
    "impacts": ["run", "impacts", "--quiet", "--report", "{out}"],
    "sliding": ["run", "sliding", "--quiet", "--report", "{out}"],
    "demo": ["run", "demo", "--quiet", "--report", "{out}"],
    "moving": [
        "run",
        "moving-surface",
        "--quiet",
        "--sweep",
        "surface.speed_mps=0.5,1.0,1.5,2.0",
        "--compare-paper",
        "--report",
        "{out}",
    ],
    "perception": ["bench", "perception", "--frames", "60", "--json", "{out}"],
    "safety": ["bench", "safety", "--json", "{out}"],
}

# Fields measured on the clock of the machine that ran them, or naming where it ran.
MACHINE_DEPENDENT = re.compile(
    r"(_ms\b|_ms\.|_us\b|_us\.|latency|wall|elapsed|tick|speedup|ratio|path|duration_wall|"
    r"perception_ms|seconds|timing|machine|host|cpu|worker|misses|slowdown)",
    re.IGNORECASE,
)


def _hapticloud() -> str:
    return str(Path(sys.executable).with_name("hapticloud"))


def capture(out_dir: Path, only: list[str]) -> None:
    out_dir.mkdir(parents=True, exist_ok=True)
    for name, args in COMMANDS.items():
        if only and name not in only:
            continue
        report = out_dir / f"{name}.json"
        cmd = [_hapticloud(), *(a.replace("{out}", str(report)) for a in args)]
        done = subprocess.run(cmd, capture_output=True, text=True, check=False)
        (out_dir / f"{name}.txt").write_text(done.stdout + done.stderr)
        print(f"{name}: exit {done.returncode}", flush=True)


def _flatten(value: object, prefix: str = "") -> dict[str, object]:
    if isinstance(value, dict):
        flat: dict[str, object] = {}
        for key, item in value.items():
            flat.update(_flatten(item, f"{prefix}.{key}" if prefix else str(key)))
        return flat
    if isinstance(value, list):
        flat = {}
        for index, item in enumerate(value):
            flat.update(_flatten(item, f"{prefix}[{index}]"))
        return flat
    return {prefix: value}


def _same(a: object, b: object) -> bool:
    if isinstance(a, float) and isinstance(b, float):
        return (math.isnan(a) and math.isnan(b)) or a == b
    return a == b


def compare(before: Path, after: Path) -> int:
    differences = 0
    for report in sorted(before.glob("*.json")):
        other = after / report.name
        if not other.exists():
            print(f"{report.name}: missing in {after}")
            differences += 1
            continue
        a = _flatten(json.loads(report.read_text()))
        b = _flatten(json.loads(other.read_text()))
        # Every field the earlier capture printed must print the same; fields added since are new.
        keys = sorted(k for k in a if not MACHINE_DEPENDENT.search(k))
        changed = [k for k in keys if not _same(a.get(k), b.get(k))]
        print(f"{report.name}: {len(keys)} deterministic fields, {len(changed)} differ")
        for key in changed[:20]:
            print(f"  {key}: {a.get(key)!r} -> {b.get(key)!r}")
        differences += len(changed)
    return 1 if differences else 0


def main(argv: list[str]) -> int:
    if len(argv) >= 2 and argv[0] == "capture":
        capture(Path(argv[1]), argv[2:])
        return 0
    if len(argv) == 3 and argv[0] == "compare":
        return compare(Path(argv[1]), Path(argv[2]))
    print(__doc__)
    return 2


if __name__ == "__main__":
    raise SystemExit(main(sys.argv[1:]))
