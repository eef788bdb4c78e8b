"""Benchmarks: ``python tools/bench.py NAME [--quick]`` (contract in shared BENCHMARKS.md).

Each benchmark lives in ``tools/bench_<name>.py`` (dashes become underscores) and defines
``run(quick: bool) -> dict``; this runner adds ``version``, ``peak_rss_mib`` when missing, and
prints the result as ONE JSON object on the last line.
"""

from __future__ import annotations

import argparse
import importlib
import json
import resource
import sys
from pathlib import Path

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE))
sys.path.insert(0, str(HERE.parent))


def available() -> list[str]:
    """Names of the benchmarks present."""
    return sorted(p.stem[len("bench_") :].replace("_", "-") for p in HERE.glob("bench_*.py"))


def peak_rss_mib() -> float:
    """Peak resident set size of this process (MiB)."""
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("name", help="one of: " + ", ".join(available()))
    parser.add_argument("--quick", action="store_true", help="smaller run, under 60 s")
    args = parser.parse_args()
    if args.name not in available():
        print(f"error: unknown benchmark '{args.name}'; available: {', '.join(available())}", file=sys.stderr)
        return 2
    from loopmodel import __version__

    module = importlib.import_module("bench_" + args.name.replace("-", "_"))
    result = module.run(quick=args.quick)
    result.setdefault("version", __version__)
    result.setdefault("peak_rss_mib", round(peak_rss_mib(), 1))
    print(json.dumps(result))
    return 0


if __name__ == "__main__":
    sys.exit(main())
