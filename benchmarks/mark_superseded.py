"""Mark the records made before the shipped defaults last changed.

Each row of ``benchmarks/results/*.json`` (a case, a row, a named record; a file that is one
measurement counts as one row) gets ``"superseded": "made before COMMIT (DATE) changed the
defaults: WHAT"``, naming the first change of :data:`_record.DEFAULTS_CHANGES` made after the
row, when the row was made before the last of them. When a row was made is its ``utc`` field
(records of :mod:`_record`) or else the date of the first commit whose version of the file holds
the row's values (a later commit that only added a field still matches: the values the two
versions share must agree and cover at least 80 % of the row's keys). Nothing else is changed.

Usage: ``.venv/bin/python benchmarks/mark_superseded.py [--check]`` (``--check``: only list the
rows that would change, exit 1 if any).
"""

from __future__ import annotations

import argparse
import datetime as dt
import json
import subprocess
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _record import DEFAULTS_CHANGES, RESULTS, ROOT  # noqa: E402

ROW_LISTS = ("cases", "rows", "runs")  # keys that hold one row per entry (list or dict of rows)


def rows_of(record) -> list[tuple[str, dict]]:
    """The rows of a results file: (label, row) pairs; the file itself when it holds no row list."""
    if isinstance(record, dict) and not any(k in record for k in ROW_LISTS) and record \
            and all(isinstance(v, dict) and ("command" in v or "date_utc" in v) for v in record.values()):
        return list(record.items())  # named records (bench_examples.json)
    found = []
    for key in ROW_LISTS:
        block = record.get(key) if isinstance(record, dict) else None
        if isinstance(block, list):
            found += [(f"{key}[{i}]", r) for i, r in enumerate(block) if isinstance(r, dict)]
        elif isinstance(block, dict):
            found += [(f"{key}.{k}", r) for k, r in block.items() if isinstance(r, dict)]
    return found or [("(file)", record)]


def _same(old: dict, row: dict) -> bool:
    shared = [k for k in row if k in old and k != "superseded"]
    return len(shared) >= 0.8 * len([k for k in row if k != "superseded"]) and all(old[k] == row[k] for k in shared)


def made_dates(path: Path) -> dict[str, dt.datetime]:
    """Label → when the row was made (its ``utc``, else the first commit holding its values)."""
    rel = str(path.relative_to(ROOT))
    log = subprocess.run(["git", "log", "--reverse", "--format=%H %aI", "--", rel], cwd=ROOT,
                         capture_output=True, text=True).stdout.split("\n")
    rows = rows_of(json.loads(path.read_text()))
    found = {label: dt.datetime.fromisoformat(r["utc"]) for label, r in rows if isinstance(r.get("utc"), str)}
    for line in filter(None, log):
        sha, date = line.split()
        try:
            old = json.loads(subprocess.run(["git", "show", f"{sha}:{rel}"], cwd=ROOT, capture_output=True,
                                            text=True).stdout)
        except json.JSONDecodeError:
            continue
        old_rows = [r for _, r in rows_of(old)]
        for label, row in rows:
            if label not in found and any(_same(o, row) for o in old_rows):
                found[label] = dt.datetime.fromisoformat(date)
    return found


def dump_like(text: str, record) -> str:
    """``record`` as JSON in the layout of ``text`` (its indent and final newline), so that a diff
    shows only what changed."""
    indent = 2 if text.startswith("{\n  ") else 1 if text.startswith("{\n ") else None
    return json.dumps(record, indent=indent) + ("\n" if text.endswith("\n") else "")


def marker(made: dt.datetime) -> str | None:
    """The ``superseded`` text for a row made at ``made``, or None when no default changed since."""
    for sha, date, what in DEFAULTS_CHANGES:
        if dt.datetime.fromisoformat(date) > made:
            return f"made before {sha} ({date[:10]}) changed the defaults: {what}"
    return None


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--check", action="store_true", help="list the rows that would change; exit 1 if any")
    args = p.parse_args(argv)
    changed = 0
    for path in sorted(RESULTS.glob("*.json")):
        record = json.loads(path.read_text())
        dates = made_dates(path)
        dirty = False
        for label, row in rows_of(record):
            if label not in dates:
                print(f"{path.name} {label}: not found in git history (not marked)")
                continue
            text = marker(dates[label])
            if text and row.get("superseded") != text:
                print(f"{path.name} {label}: {text}")
                row["superseded"] = text
                dirty = True
                changed += 1
        if dirty and not args.check:
            path.write_text(dump_like(path.read_text(), record))
    return 1 if args.check and changed else 0


if __name__ == "__main__":
    raise SystemExit(main())
