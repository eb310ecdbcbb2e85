"""Sum up a test run's compile report: where the suite's time goes, per file and per test.

    JSHADOW_COMPILE_REPORT=/tmp/report bash scripts/test.sh
    python scripts/compile_report.py /tmp/report [--top 30]

Every test process writes ``compile_<worker>.json`` (``tests/conftest.py``, ``_CompileReport``):
per test its wall time and the seconds of jax's tracing, lowering to StableHLO and XLA compilation
(which includes reads of the persistent compilation cache; ``saved`` is what those reads saved).
Tracing is what jax's trace events report (a jitted function traced inside another one recorded
no event of its own in a check, so it counts once, within its caller). Time in child processes
(tests that start Python) is wall time only.
"""

from __future__ import annotations

import argparse
import json
import pathlib
from collections import defaultdict

FIELDS = ("wall", "compile", "lower", "trace", "saved")
OUTSIDE = "(outside tests)"  # compilation while collecting (module-level arrays), not in a test


def load(folder: pathlib.Path) -> dict[str, dict[str, float]]:
    rows: dict[str, dict[str, float]] = {}
    files = sorted(folder.glob("compile_*.json"))
    if not files:
        raise SystemExit(f"no compile_*.json in {folder}: run the tests with JSHADOW_COMPILE_REPORT={folder}")
    for path in files:
        for test, r in json.loads(path.read_text()).items():
            into = rows.setdefault(test, dict.fromkeys(FIELDS, 0.0))  # "(outside tests)": every process's
            for f in FIELDS:
                into[f] += r.get(f, 0.0)
    return rows


def table(rows, key, top):
    groups: dict[str, dict[str, float]] = defaultdict(lambda: dict.fromkeys(FIELDS, 0.0))
    for test, r in rows.items():
        g = groups[key(test)]
        for f in FIELDS:
            g[f] += r.get(f, 0.0)
    out = [
        "| | wall s | compile s | lower s | trace s | compile share | cache saved s |",
        "|---|---:|---:|---:|---:|---:|---:|",
    ]
    for name, g in sorted(groups.items(), key=lambda kv: -kv[1]["wall"])[:top]:
        share = g["compile"] / g["wall"] if g["wall"] > 0 else 0.0
        out.append(
            f"| {name} | {g['wall']:.1f} | {g['compile']:.1f} | {g['lower']:.1f} | {g['trace']:.1f} "
            f"| {share:.0%} | {g['saved']:.1f} |"
        )
    return "\n".join(out)


def main(argv=None) -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("folder", type=pathlib.Path)
    p.add_argument("--top", type=int, default=25, help="rows per table (default 25)")
    a = p.parse_args(argv)
    rows = load(a.folder)
    total = {f: sum(r.get(f, 0.0) for r in rows.values()) for f in FIELDS}
    print(
        f"{sum(t != OUTSIDE for t in rows)} tests; summed over the test processes: wall "
        f"{total['wall']:.0f} s, XLA compilation "
        f"{total['compile']:.0f} s ({total['compile'] / max(total['wall'], 1e-9):.0%}), lowering "
        f"{total['lower']:.0f} s, tracing {total['trace']:.0f} s; "
        f"the persistent cache saved {total['saved']:.0f} s\n"
    )
    print("By file:\n" + table(rows, lambda t: t.split("::")[0], a.top) + "\n")
    print("By test:\n" + table(rows, lambda t: t, a.top))


if __name__ == "__main__":
    main()
