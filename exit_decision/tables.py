"""CSV files of rows (dicts): the logs and tables every command writes."""
from __future__ import annotations

import csv
from collections.abc import Sequence
from pathlib import Path


def append_row(path: Path, row: dict) -> None:
    """Append one row, writing the header first when the file is new."""
    new = not path.exists()
    with open(path, 'a', newline='') as stream:
        writer = csv.DictWriter(stream, fieldnames=list(row))
        if new:
            writer.writeheader()
        writer.writerow(row)


def write_rows(path: Path, rows: Sequence[dict]) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    with open(path, 'w', newline='') as stream:
        writer = csv.DictWriter(stream, fieldnames=list(rows[0]))
        writer.writeheader()
        writer.writerows(rows)


def read_rows(path: Path) -> list[dict[str, str]]:
    with open(path, newline='') as stream:
        return list(csv.DictReader(stream))
