#!/usr/bin/env python3
"""Compares the episode records of two mte run directories field by field, ignoring
timings (`times`): exit 0 when identical, 1 with the differences listed. Standard library
only."""
import json
import pathlib
import sys


def records(run: pathlib.Path) -> dict:
    out = {}
    for cell in sorted((run / "cells").glob("*.jsonl")):
        for line in cell.read_text().splitlines():
            rec = json.loads(line)
            rec.pop("times", None)
            out[(rec.get("cell"), rec.get("arm"), rec.get("seed"), rec.get("kind"))] = rec
    return out


def main() -> int:
    before, after = (records(pathlib.Path(p)) for p in sys.argv[1:3])
    diffs = [k for k in sorted(set(before) | set(after), key=str) if before.get(k) != after.get(k)]
    for k in diffs:
        print(f"differs: {k}\n  before: {before.get(k)}\n  after:  {after.get(k)}")
    print(f"{len(before)} records before, {len(after)} after, {len(diffs)} differ")
    return 1 if diffs or not before else 0


if __name__ == "__main__":
    sys.exit(main())
