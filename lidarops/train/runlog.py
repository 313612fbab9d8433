"""What a run reports: ``log.csv`` rows, ``train.log`` messages, TensorBoard scalars, a progress bar.

Only rank 0 writes; on other ranks every method does nothing. On resume, rows of ``log.csv`` past the
checkpoint's step are dropped (those steps are taken again), so the file reads as one uninterrupted run.
"""
from __future__ import annotations

import csv
import math
import sys
import time
from pathlib import Path
from typing import Any

from lidarops._progress import tqdm_class

__all__ = ["RunLog"]


def _fmt(v: Any) -> str:
    if isinstance(v, float):
        return f"{v:.4g}" if math.isfinite(v) and v != 0 else str(v)
    return str(v)


class RunLog:
    def __init__(self, out_dir: Path, enabled: bool, resume_step: int | None, tensorboard: bool,
                 progress: bool) -> None:
        self.enabled = enabled
        self.bar = None
        self._csv_file = None
        self._writer = None
        self._tb = None
        if not enabled:
            return
        self.csv_path = out_dir / "log.csv"
        self.text_path = out_dir / "train.log"
        self._fields: list[str] | None = None
        rows: list[dict[str, str]] = []
        if resume_step is not None and self.csv_path.exists():
            with open(self.csv_path, newline="") as f:
                reader = csv.DictReader(f)
                self._fields = list(reader.fieldnames or []) or None
                rows = [r for r in reader if r.get("step") and int(r["step"]) <= resume_step]
        self._csv_file = open(self.csv_path, "w", newline="")
        if self._fields:
            self._start_csv(self._fields)
            self._writer.writerows(rows)
            self._csv_file.flush()
        # in a pipe or a file: plain lines every log_every steps
        self._tqdm = tqdm_class(bool(progress) and sys.stderr.isatty(), auto=True)
        self._progress = progress
        if tensorboard:
            try:
                from torch.utils.tensorboard import SummaryWriter

                self._tb = SummaryWriter(log_dir=str(out_dir / "tensorboard"))
            except ImportError:  # tensorboard not installed: csv only
                self._tb = None

    def _start_csv(self, fields: list[str]) -> None:
        self._fields = fields
        self._writer = csv.DictWriter(self._csv_file, fieldnames=fields, extrasaction="ignore", restval="")
        if self._csv_file.tell() == 0:
            self._writer.writeheader()

    def say(self, message: str) -> None:
        """Prints a message (above the progress bar) and appends it to ``train.log``."""
        if not self.enabled:
            return
        if self.bar is not None:
            self.bar.write(message)
        else:
            print(message, flush=True)
        with open(self.text_path, "a") as f:
            f.write(f"{time.strftime('%Y-%m-%d %H:%M:%S')} {message}\n")

    def row(self, values: dict[str, Any]) -> None:
        """One row of ``log.csv`` (columns fixed by the first row) and TensorBoard ``train/<name>`` scalars."""
        if not self.enabled:
            return
        if self._writer is None:
            self._start_csv(list(values))
        self._writer.writerow(values)
        self._csv_file.flush()
        if self._tb is not None:
            for k, v in values.items():
                if k not in ("step", "epoch") and isinstance(v, (int, float)):
                    self._tb.add_scalar(f"train/{k}", v, values["step"])

    def scalars(self, prefix: str, values: dict[str, float], step: int) -> None:
        if self.enabled and self._tb is not None:
            for k, v in values.items():
                if isinstance(v, (int, float)):
                    self._tb.add_scalar(f"{prefix}/{k}", v, step)

    def start_epoch(self, epoch: int, epochs: int, steps: int, done: int) -> None:
        if not (self.enabled and self._progress):
            return
        if self._tqdm is not None:
            self.bar = self._tqdm(total=steps, initial=done, desc=f"epoch {epoch + 1}/{epochs}", unit="step",
                                  dynamic_ncols=True, mininterval=1.0 if sys.stderr.isatty() else 30.0,
                                  leave=False)
        self._epoch_desc = f"epoch {epoch + 1}/{epochs}"
        self._steps = steps

    def step(self, done: int, values: dict[str, Any] | None) -> None:
        """Advances the bar one step; ``values`` (at log steps) become its postfix, or a line without tqdm."""
        if not (self.enabled and self._progress):
            return
        if self.bar is not None:
            self.bar.update(1)
            if values:
                self.bar.set_postfix({k: _fmt(v) for k, v in values.items()}, refresh=False)
        elif values:
            shown = " ".join(f"{k} {_fmt(v)}" for k, v in values.items())
            print(f"{self._epoch_desc} step {done}/{self._steps} {shown}", flush=True)

    def end_epoch(self) -> None:
        if self.bar is not None:
            self.bar.close()
            self.bar = None

    def close(self) -> None:
        self.end_epoch()
        if self._csv_file is not None:
            self._csv_file.close()
        if self._tb is not None:
            self._tb.close()
