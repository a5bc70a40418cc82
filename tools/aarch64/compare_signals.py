"""Compare the signals.csv of two sets of runs made by jiwy_variants.py, bit for bit.

    python3 tools/aarch64/compare_signals.py DIR_A DIR_B

For each variant folder present in both, prints `same <variant>: <rows> rows x <columns>
columns, identical bytes` or `DIFFER <variant>: ...` with the first row and column that
differ, the number of differing values and the largest difference. Exit status 1 if any
variant differs or is missing. Standard library only (runs with the host's python3).
"""

from __future__ import annotations

import csv
import json
import sys
from pathlib import Path


def _rows(path: Path) -> tuple[list[str], list[list[str]]]:
    with path.open(newline="") as file:
        reader = csv.reader(file)
        header = next(reader)
        return header, list(reader)


def _hot_paths(a: Path, b: Path, name: str) -> str:
    """Which per-cycle path each run took (summary.json's hot_path: "c" or "python")."""
    kinds = []
    for folder in (a, b):
        try:
            kinds.append(json.loads((folder / name / "summary.json").read_text()).get("hot_path") or "?")
        except (OSError, ValueError):
            kinds.append("?")
    return f"hot path {kinds[0]} / {kinds[1]}"


def compare(a: Path, b: Path, name: str) -> bool:
    file_a, file_b = a / name / "signals.csv", b / name / "signals.csv"
    for path in (file_a, file_b):
        if not path.is_file():
            print(f"DIFFER {name}: {path} is missing")
            return False
    header_a, rows_a = _rows(file_a)
    header_b, rows_b = _rows(file_b)
    shape = f"{len(rows_a)} rows x {len(header_a)} columns"
    if file_a.read_bytes() == file_b.read_bytes():
        print(f"same {name}: {shape}, identical bytes ({_hot_paths(a, b, name)})")
        return True
    if header_a != header_b or len(rows_a) != len(rows_b):
        print(f"DIFFER {name}: columns {header_a} vs {header_b}, rows {len(rows_a)} vs {len(rows_b)}")
        return False
    first = None
    count = 0
    largest = 0.0
    for row_index, (row_a, row_b) in enumerate(zip(rows_a, rows_b, strict=True)):
        for column, (text_a, text_b) in enumerate(zip(row_a, row_b, strict=True)):
            if text_a == text_b:
                continue
            count += 1
            largest = max(largest, abs(float(text_a) - float(text_b)))
            if first is None:
                first = (row_index, column, text_a, text_b)
    assert first is not None  # the bytes differ, so some value does
    row_index, column, text_a, text_b = first
    print(
        f"DIFFER {name}: {shape}; {count} values differ, the first at t_s={rows_a[row_index][0]} "
        f"in {header_a[column]} ({text_a} vs {text_b}); largest difference {largest:.3g}"
    )
    return False


def main() -> int:
    if len(sys.argv) != 3:
        print(__doc__.strip().splitlines()[2].strip(), file=sys.stderr)
        return 2
    a, b = Path(sys.argv[1]), Path(sys.argv[2])
    names = sorted({p.name for p in a.iterdir() if p.is_dir()} | {p.name for p in b.iterdir() if p.is_dir()})
    if not names:
        print(f"DIFFER: no runs in {a} or {b}")
        return 1
    print(f"comparing {a} with {b}")
    results = [compare(a, b, name) for name in names]
    return 0 if all(results) else 1


if __name__ == "__main__":
    sys.exit(main())
