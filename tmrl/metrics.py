"""Training metrics: one compact console line per round, the same row in a CSV file, and
optionally TensorBoard and wandb.

Nothing is written until the first row arrives: building a :class:`MetricsLogger` creates no
folder. TensorBoard is used when it is installed (``tensorboard=None``, the default) and wandb
only when asked (``wandb=True``).
"""

from __future__ import annotations

import csv
import io
import logging
import math
import numbers
import os
from collections.abc import Mapping
from pathlib import Path
from typing import Any

from tmrl.errors import UserError

__all__ = ["STANDARD_COLUMNS", "MetricsLogger", "format_row"]

logger = logging.getLogger(__name__)

STANDARD_COLUMNS = (
    "epoch",
    "round",
    "total_updates",
    "total_samples",
    "loss_actor",
    "loss_critic",
    "entropy_coef",
    "return_train",
    "return_test",
    "episode_length_train",
    "episode_length_test",
    "memory_len",
    "updates_per_second",
    "samples_per_second",
    "round_time",
    "idle_time",
)
"""Columns that always come first in the CSV file, in this order (stable names across versions)."""


def _fmt(value: Any) -> str:
    if value is None:
        return "-"
    if isinstance(value, bool):
        return str(value)
    if isinstance(value, int):
        return str(value)
    try:
        f = float(value)
    except (TypeError, ValueError):
        return str(value)
    if math.isnan(f):
        return "-"
    return f"{f:.4g}"


def format_row(row: Mapping[str, Any]) -> str:
    """The compact console line for one round, e.g.
    ``epoch 2 round 7/50 | loss_actor -3.21 loss_critic 0.123 entropy_coef 0.0412 | return train
    -140.5 test -130.2 | samples 12100 memory 12000 | 105.3 upd/s 51.2 smp/s``.

    Args:
        row: the round's metrics (``RoundMetrics.as_row()``).
    """
    rounds = row.get("rounds")
    where = f"epoch {row.get('epoch', '-')} round {row.get('round', '-')}"
    if rounds is not None:
        where += f"/{rounds}"
    losses = " ".join(
        f"{k} {_fmt(row[k])}" for k in ("loss_actor", "loss_critic", "entropy_coef") if k in row
    )
    parts = [where]
    if losses:
        parts.append(losses)
    parts.append(f"return train {_fmt(row.get('return_train'))} test {_fmt(row.get('return_test'))}")
    # the samples received so far: what the workers' summaries add up to (the memory may hold fewer)
    samples = f"samples {_fmt(row['total_samples'])} " if "total_samples" in row else ""
    parts.append(f"{samples}memory {_fmt(row.get('memory_len'))}")
    parts.append(
        f"{_fmt(row.get('updates_per_second'))} upd/s {_fmt(row.get('samples_per_second'))} smp/s"
    )
    # Shown only once something happened: dropped batches or skipped updates deserve attention.
    alarms = " ".join(
        f"{label} {_fmt(row[key])}"
        for key, label in (
            ("rejected_batches", "rejected"),
            ("foreign_batches", "other-run"),
            ("skipped_updates", "non-finite"),
            ("restored_states", "restored"),
            ("memory_errors", "memory-refused"),
        )
        if isinstance(row.get(key), (int, float)) and row[key] > 0
    )
    if row.get("behind") is True:  # the trainer cannot keep the ratio the setting asks for
        done = row.get("updates_per_sample")
        done_text = "-" if done is None else f"{float(done):.2f}"
        behind = f"behind: {done_text} of {_fmt(row.get('updates_per_sample_asked'))} upd/smp"
        alarms = f"{alarms} {behind}" if alarms else behind
    if alarms:
        parts.append(alarms)
    return " | ".join(parts)


def _scalar(value: Any) -> float | None:
    """A float for numeric values (tensors and NumPy scalars included), else ``None``."""
    if isinstance(value, bool):
        return float(value)
    try:
        return float(value)
    except (TypeError, ValueError):
        return None


class MetricsLogger:
    """Receives one row of metrics per training round and reports it.

    Args:
        run_name: name of the run (CSV folder, TensorBoard folder, wandb run name).
        folder: the data folder; the CSV goes to ``<folder>/logs/<run_name>/metrics.csv`` and
            TensorBoard events to ``<folder>/logs/<run_name>/tensorboard``. ``None``: console only.
        tensorboard: ``None`` uses TensorBoard when it is installed, ``True`` requires it,
            ``False`` never uses it. Needs ``folder``.
        wandb: log to wandb (never happens unless ``True``).
        wandb_project: wandb project.
        wandb_entity: wandb entity (user or team).
        wandb_run_id: wandb run id, to resume the same run after a restart.
        wandb_config: hyperparameters recorded with the wandb run.
        console: print each row through ``logging`` (level INFO) as one compact line.

    Raises:
        UserError: ``tensorboard=True`` or ``wandb=True`` and the package is not installed.
    """

    def __init__(
        self,
        run_name: str,
        folder: str | os.PathLike[str] | None = None,
        tensorboard: bool | None = None,
        wandb: bool = False,
        wandb_project: str | None = None,
        wandb_entity: str | None = None,
        wandb_run_id: str | None = None,
        wandb_config: Mapping[str, Any] | None = None,
        console: bool = True,
    ) -> None:
        self.run_name = str(run_name)
        self.folder = Path(folder) if folder is not None else None
        self.console = console
        self._columns: list[str] | None = None
        self._rows = 0
        self._waiting: list[Mapping[str, Any]] = []  # CSV rows not yet written: the file was held
        self._tb_writer: Any = None
        self._tb_cls: Any = None
        if tensorboard is not False and self.folder is not None:
            try:
                from torch.utils.tensorboard import SummaryWriter

                self._tb_cls = SummaryWriter
            except ImportError:
                if tensorboard:
                    raise UserError(
                        "TensorBoard logging was asked for but tensorboard is not installed: "
                        "pip install tensorboard, or set tensorboard=False"
                    ) from None
                logger.debug("tensorboard is not installed: metrics go to the console and CSV only")
        self._wandb: Any = None
        self._wandb_run: Any = None
        self._wandb_kwargs = {
            "project": wandb_project,
            "entity": wandb_entity,
            "id": wandb_run_id,
            "name": self.run_name,
            "config": dict(wandb_config) if wandb_config else None,
            "resume": "allow",
        }
        if wandb:
            try:
                import wandb as wandb_module
            except ImportError:
                raise UserError(
                    'wandb logging was asked for but wandb is not installed: pip install ".[wandb]" in the checkout of this project'
                ) from None
            self._wandb = wandb_module

    @property
    def run_folder(self) -> Path | None:
        """``<folder>/logs/<run_name>`` (``None`` without a folder)."""
        return None if self.folder is None else self.folder / "logs" / self.run_name

    @property
    def csv_path(self) -> Path | None:
        """Where the CSV rows go (``None`` without a folder)."""
        run = self.run_folder
        return None if run is None else run / "metrics.csv"

    def log_round(self, row: Mapping[str, Any]) -> None:
        """Report one round: console line, CSV row, TensorBoard scalars, wandb.

        Args:
            row: metric name to value. Standard names: see :data:`STANDARD_COLUMNS`; ``rounds``
                (rounds per epoch) is shown on the console; ``total_updates`` is the step for
                TensorBoard and wandb.
        """
        self._rows += 1
        if self.console:
            logger.info("%s", format_row(row))
        if self.csv_path is not None:
            self._write_csv(row)
        step = int(row.get("total_updates", self._rows))
        numeric = {k: v for k, v in ((k, _scalar(v)) for k, v in row.items()) if v is not None}
        run_folder = self.run_folder
        if self._tb_cls is not None and run_folder is not None:
            if self._tb_writer is None:
                self._tb_writer = self._tb_cls(log_dir=str(run_folder / "tensorboard"))
            for key, value in numeric.items():
                self._tb_writer.add_scalar(key, value, global_step=step)
            self._tb_writer.flush()
        if self._wandb is not None:
            if self._wandb_run is None:
                kwargs = {k: v for k, v in self._wandb_kwargs.items() if v is not None}
                self._wandb_run = self._wandb.init(**kwargs)
            self._wandb.log(numeric, step=step)

    def _write_csv(self, row: Mapping[str, Any]) -> None:
        """Append ``row`` and any row that waited. While another program holds the file (a
        spreadsheet that has it open, on Windows), the rows wait in memory, said once, and go in
        at the first round it is free again: the trainer never waits for it."""
        self._waiting.append(dict(row))
        try:
            self._append_rows(self._waiting)
        except PermissionError as err:
            if len(self._waiting) == 1:
                logger.warning("%s is held by another program (%s): its rows wait in memory until it is free",
                               self.csv_path, err.strerror or err)
            return
        if len(self._waiting) > 1:
            logger.info("%s is free again: wrote the %d rows that waited", self.csv_path, len(self._waiting))
        self._waiting.clear()

    def _append_rows(self, rows: list[Mapping[str, Any]]) -> None:
        path = self.csv_path
        assert path is not None
        out = io.StringIO()
        writer = csv.writer(out, lineterminator="\n")
        columns = self._columns
        if columns is None:
            path.parent.mkdir(parents=True, exist_ok=True)
            columns = self._existing_columns(path)
            if columns is None:
                standard = [c for c in STANDARD_COLUMNS if c in rows[0]]
                columns = standard + sorted(k for k in rows[0] if k not in standard)
                writer.writerow(columns)  # the header, in the same write as the rows
        # Keys unknown to the header (new metrics mid-run) stay out of the CSV; TensorBoard and
        # wandb still get them.
        for row in rows:
            writer.writerow(["" if row.get(c) is None else _fmt_csv(row.get(c)) for c in columns])
        # One append of whole lines per round: rewriting the file atomically every round would cost
        # I/O quadratic in the run length; a crash can at worst cut the last line.
        with open(path, "a", encoding="utf-8", newline="") as f:
            f.write(out.getvalue())
            f.flush()
        self._columns = columns  # known once written (a held file wrote nothing, header included)

    @staticmethod
    def _existing_columns(path: Path) -> list[str] | None:
        """Columns of a CSV from an earlier run of the same name (resume), or ``None``."""
        if not path.is_file() or path.stat().st_size == 0:
            return None
        with open(path, "r+", encoding="utf-8", newline="") as f:
            first = f.readline()
            f.seek(0, os.SEEK_END)
            if f.tell() > 0:
                f.seek(f.tell() - 1)
                if f.read(1) != "\n":
                    f.write("\n")  # close a line cut by a crash, so new rows start cleanly
        columns = next(csv.reader([first]), None)
        return columns or None

    def close(self) -> None:
        """Write the CSV rows that waited (retried for a moment), flush and close TensorBoard and
        wandb (the CSV is never left open)."""
        if self._waiting and self.csv_path is not None:
            from tmrl.platform import when_free

            try:
                when_free(self._append_rows, self._waiting, what=str(self.csv_path))
                self._waiting.clear()
            except OSError as err:
                logger.warning("%d rows of %s were not written: %s", len(self._waiting), self.csv_path, err)
        if self._tb_writer is not None:
            self._tb_writer.close()
            self._tb_writer = None
        if self._wandb_run is not None:
            self._wandb_run.finish()
            self._wandb_run = None


def _fmt_csv(value: Any) -> str:
    if isinstance(value, numbers.Integral):  # bool, int and NumPy integers
        return str(int(value))
    s = _scalar(value)
    return str(value) if s is None else repr(s)
