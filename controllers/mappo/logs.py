"""Metrics of a run as JSON lines and CSV side by side (``<name>.jsonl`` and ``<name>.csv``).

Rows are flat dicts of numbers (None where undefined, e.g. no episode ended in an iteration);
every row of a log has the same keys. On resume the log is cut back to the rows the
checkpoint covers, so an interrupted and resumed run leaves the same curve as an
uninterrupted one.
"""

from __future__ import annotations

import csv
import io
import json
import math
from pathlib import Path
from typing import Any

from sim.files import atomic_write_text


def _clean(value: Any) -> Any:
    if isinstance(value, float) and not math.isfinite(value):
        return None
    return value


class LogFileError(ValueError):
    """A damaged line in a JSON-lines log (not its last one); the message names the file and line."""


def read_jsonl(path: str | Path) -> list[dict[str, Any]]:
    """The rows of the JSON-lines log ``path`` (each line one JSON object; blank lines skipped).

    A last line that does not parse is what a crash in the middle of an append leaves (the
    expected crash artifact): it is skipped. A line before it that is not a JSON object raises
    :class:`LogFileError` naming the file and the line."""
    path = Path(path)
    lines = [(k, line) for k, line in enumerate(path.read_text(errors="replace").splitlines(), 1)
             if line.strip()]
    rows = []
    for k, line in lines:
        try:
            row = json.loads(line)
        except ValueError as exc:
            if k == lines[-1][0]:
                break                       # torn by a crash while it was appended
            raise LogFileError(f"{path}, line {k}: not valid JSON ({exc}); the log is damaged: "
                               "remove that line, or the file to start the run over") from None
        if not isinstance(row, dict):
            raise LogFileError(f"{path}, line {k}: expected a JSON object, got {type(row).__name__}; "
                               "the log is damaged: remove that line, or the file to start the run over")
        rows.append(row)
    return rows


class MetricsLog:
    """Append-only ``<run_dir>/<name>.jsonl`` + ``.csv`` with a fixed column set."""

    def __init__(self, run_dir: str | Path, name: str):
        self.jsonl = Path(run_dir) / f"{name}.jsonl"
        self.csv = Path(run_dir) / f"{name}.csv"
        self.columns: list[str] | None = None
        rows = self.read()
        if rows:
            self.columns = list(rows[0])

    def read(self) -> list[dict[str, Any]]:
        if not self.jsonl.exists():
            return []
        return read_jsonl(self.jsonl)

    def append(self, row: dict[str, Any]) -> None:
        row = {k: _clean(v) for k, v in row.items()}
        if self.columns is None:        # no rows yet: the files start anew (a torn line goes)
            self.columns = list(row)
            self.jsonl.write_text("")
            with self.csv.open("w", newline="") as f:
                csv.writer(f).writerow(self.columns)
        elif list(row) != self.columns:
            raise ValueError(f"{self.jsonl.name}: row keys {list(row)} differ from the columns {self.columns}")
        with self.jsonl.open("a") as f:
            f.write(json.dumps(row, allow_nan=False) + "\n")
        with self.csv.open("a", newline="") as f:
            csv.writer(f).writerow(["" if row[k] is None else row[k] for k in self.columns])

    def truncate(self, keep: int) -> None:
        """Keep only the first ``keep`` rows of both files (atomic rewrites)."""
        rows = self.read()[:keep]
        if not rows:
            for path in (self.jsonl, self.csv):
                path.unlink(missing_ok=True)
            self.columns = None
            return
        self.columns = list(rows[0])
        atomic_write_text(self.jsonl, "".join(json.dumps(r, allow_nan=False) + "\n" for r in rows))
        buffer = io.StringIO()
        writer = csv.writer(buffer)
        writer.writerow(self.columns)
        for r in rows:
            writer.writerow(["" if r[k] is None else r[k] for k in self.columns])
        atomic_write_text(self.csv, buffer.getvalue())


class TensorBoardLog:
    """The numeric fields of train and eval rows as TensorBoard scalars (``tag = "<group>/<key>"``,
    step = training episodes), in ``<run_dir>/tensorboard``; closed by :meth:`close`."""

    def __init__(self, run_dir: str | Path):
        try:
            from torch.utils.tensorboard import SummaryWriter
        except ImportError as exc:      # torch imports tensorboard lazily
            raise RuntimeError("tensorboard=True needs the tensorboard package: "
                               "`pip install tensorboard`") from exc
        self.writer = SummaryWriter(log_dir=str(Path(run_dir) / "tensorboard"))

    def add(self, group: str, row: dict[str, Any]) -> None:
        step = int(row["episodes"])
        for key, value in row.items():
            if isinstance(value, bool) or not isinstance(value, int | float) or not math.isfinite(value):
                continue
            self.writer.add_scalar(f"{group}/{key}", value, step)

    def close(self) -> None:
        self.writer.flush()
        self.writer.close()

