"""A run directory: config, checkpoints, metrics and summary of one training run.

Layout::

    RUN_DIR/
      config.json       the TrainConfig, written once when the run starts
      checkpoint.pt     latest checkpoint (replaced atomically: write temp file, then rename)
      metrics.csv       one row per update
      tensorboard/      TensorBoard events (CleanRL-style tags charts/..., losses/...)
      summary.json      result of the run (written atomically at the end)

Checkpoints hold only tensors and plain Python values and load with ``weights_only=True``,
so opening one never runs arbitrary pickled code.
"""

from __future__ import annotations

import csv
import io
import json
import os
import tempfile
from pathlib import Path
from typing import Any

import torch

from thci.config import TrainConfig
from thci.errors import ThciError

CHECKPOINT_FORMAT = "thci-checkpoint-v1"


def atomic_write_bytes(path: Path, data: bytes) -> None:
    """Write `data` to `path` so a reader sees the old file or the new one, never a torn one."""
    fd, tmp = tempfile.mkstemp(dir=path.parent, prefix=f".{path.name}.", suffix=".tmp")
    try:
        # mkstemp makes the file private (0600); give it the mode a plain open() would
        umask = os.umask(0)
        os.umask(umask)
        os.fchmod(fd, 0o666 & ~umask)
        with os.fdopen(fd, "wb") as f:
            f.write(data)
            f.flush()
            os.fsync(f.fileno())
        os.replace(tmp, path)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise


def atomic_write_json(path: Path, data: Any) -> None:
    """Atomically write `data` as indented JSON."""
    atomic_write_bytes(path, (json.dumps(data, indent=2, sort_keys=False) + "\n").encode())


class RunDirectory:
    """Files of one run. Create with :meth:`create` or :meth:`open_for_resume`."""

    def __init__(self, path: Path) -> None:
        self.path = path
        self.config_path = path / "config.json"
        self.checkpoint_path = path / "checkpoint.pt"
        self.metrics_path = path / "metrics.csv"
        self.summary_path = path / "summary.json"
        self.tensorboard_path = path / "tensorboard"

    @classmethod
    def create(cls, path: Path, config: TrainConfig) -> RunDirectory:
        """A new run directory; ThciError if `path` already holds anything."""
        if path.exists() and (not path.is_dir() or any(path.iterdir())):
            raise ThciError(
                f"run directory {path} already exists: pass --resume to continue it, "
                "or choose another --run-dir"
            )
        path.mkdir(parents=True, exist_ok=True)
        run = cls(path)
        atomic_write_json(run.config_path, config.to_dict())
        return run

    @classmethod
    def open_for_resume(cls, path: Path, config: TrainConfig) -> RunDirectory:
        """An existing run whose config matches `config` (apart from resumable fields)."""
        run = cls(path)
        if not run.config_path.is_file():
            raise ThciError(f"cannot resume: {run.config_path} not found (is {path} a thci run?)")
        saved = run.read_config()
        differing = saved.differences(config)
        if differing:
            detail = ", ".join(
                f"{k}={getattr(saved, k)!r} (now {getattr(config, k)!r})" for k in differing
            )
            raise ThciError(
                f"cannot resume {path}: config differs in {detail}; "
                "resume with the original settings or start a new --run-dir"
            )
        if not run.checkpoint_path.is_file():
            raise ThciError(
                f"cannot resume {path}: no checkpoint yet; delete the directory and start again"
            )
        return run

    def read_config(self) -> TrainConfig:
        """The run's saved TrainConfig."""
        try:
            data = json.loads(self.config_path.read_text())
        except (OSError, json.JSONDecodeError) as exc:
            raise ThciError(
                f"{self.config_path} is unreadable ({exc}); the run is damaged"
            ) from None
        return TrainConfig.from_dict(data)

    def save_checkpoint(self, checkpoint: dict[str, Any]) -> None:
        """Atomically replace the checkpoint."""
        buffer = io.BytesIO()
        torch.save({"format": CHECKPOINT_FORMAT, **checkpoint}, buffer)
        atomic_write_bytes(self.checkpoint_path, buffer.getvalue())

    def load_checkpoint(self) -> dict[str, Any]:
        """The checkpoint, loaded with weights_only=True; ThciError if corrupt or foreign."""
        path = self.checkpoint_path
        if not path.is_file():
            raise ThciError(f"no checkpoint at {path}: the run has not saved one yet")
        try:
            checkpoint = torch.load(path, map_location="cpu", weights_only=True)
        except Exception as exc:
            reason = str(exc).splitlines()[0] if str(exc) else type(exc).__name__
            raise ThciError(
                f"checkpoint {path} is corrupt or truncated ({reason}); "
                "delete the run directory and train again"
            ) from None
        if not isinstance(checkpoint, dict) or checkpoint.get("format") != CHECKPOINT_FORMAT:
            raise ThciError(f"{path} is not a {CHECKPOINT_FORMAT} checkpoint written by thci")
        return checkpoint

    def write_summary(self, summary: dict[str, Any]) -> None:
        """Atomically write summary.json."""
        atomic_write_json(self.summary_path, summary)

    def read_summary(self) -> dict[str, Any] | None:
        """summary.json, or None when the run has not finished."""
        try:
            return json.loads(self.summary_path.read_text())
        except (OSError, json.JSONDecodeError):
            return None


class MetricsLog:
    """Append-only metrics.csv, one row per update, that survives a resume.

    On resume, rows written after the checkpoint (by the killed process) are dropped, so the
    file matches an uninterrupted run.
    """

    def __init__(self, path: Path, keep_until_update: int | None = None) -> None:
        self.path = path
        self.columns: list[str] | None = None
        if keep_until_update is not None and path.is_file():
            with path.open(newline="") as f:
                reader = csv.DictReader(f)
                self.columns = list(reader.fieldnames or [])
                rows = [r for r in reader if int(r["update"]) <= keep_until_update]
            text = io.StringIO()
            writer = csv.DictWriter(text, fieldnames=self.columns)
            writer.writeheader()
            writer.writerows(rows)
            atomic_write_bytes(path, text.getvalue().encode())

    def append(self, row: dict[str, float | int]) -> None:
        """Append one row; the first row fixes the columns."""
        new_file = self.columns is None
        if new_file:
            self.columns = list(row)
        with self.path.open("a" if not new_file else "w", newline="") as f:
            writer = csv.DictWriter(f, fieldnames=self.columns, extrasaction="ignore")
            if new_file:
                writer.writeheader()
            writer.writerow(row)
