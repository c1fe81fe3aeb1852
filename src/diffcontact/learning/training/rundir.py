"""The run directory of ``train()``: what may be written, ``run.json`` and the CSV log.

A run directory is written only when it is new or empty, or holds a run of
ours: its ``run.json`` (written first, before anything else) carries our
schema (``format_version``, ``model``, ``versions.diffcontact``). A folder
with other files, or a run directory holding a symbolic link, is refused
with a one-line :class:`TrainingInputError`; every file is written by
renaming a temporary file of the same folder over it (``diffcontact.io``), so
a link planted later is replaced, never written through. The CSV log
(``logs/metrics.csv``) is appended to without following links and rewritten
atomically when a column is added.
"""

from __future__ import annotations

import csv
import io
import logging
import os
from pathlib import Path
from typing import Any

import yaml
from lightning.pytorch.loggers import CSVLogger
from lightning.pytorch.loggers.csv_logs import ExperimentWriter

from diffcontact.io import (
    atomic_write_bytes,
    atomic_write_json,
    find_symlinks,
    jsonable,
    read_json_object,
    remove_orphan_temporaries,
)
from diffcontact.learning.training.options import TrainingInputError

__all__ = [
    "RUN_FILE",
    "check_run_dir",
    "clear_for_restart",
    "is_run_file",
    "loggers",
    "remove_temporaries",
    "truncate_log",
    "write_run_file",
]

log = logging.getLogger(__name__)

RUN_FILE = "run.json"
LOG_DIR = "logs"
METRICS = "metrics.csv"
# run.json keys that must match to resume a run
_RUN_IDENTITY = (
    "model_format", "model", "options", "data_dir", "seed",
    "batch_size", "lr", "weight_decay", "physics_lr", "schedule", "dtype", "steps_per_epoch",
)  # fmt: skip
# what a run that stopped before its first checkpoint may have left (removed on a restart)
_PARTIAL = ("learned.json", f"{LOG_DIR}/{METRICS}", f"{LOG_DIR}/hparams.yaml")


def is_run_file(data: Any) -> bool:
    """Whether ``data`` (a parsed ``run.json``) is the run file of a diffcontact run."""
    return (
        isinstance(data, dict)
        and data.get("format_version") == 1
        and isinstance(data.get("model"), str)
        and isinstance(data.get("versions"), dict)
        and "diffcontact" in data["versions"]
    )


def _differences(old: dict[str, Any], new: dict[str, Any]) -> list[str]:
    """What differs between two runs' identities. The data are compared by their checksum
    where the old run recorded one (moved data are the same data; data replaced at the
    same path are not), else by their path."""
    keys = list(_RUN_IDENTITY)
    if old.get("data_checksum") is not None:
        keys[keys.index("data_dir")] = "data_checksum"
    return [f"{k}: {old.get(k)!r} -> {new.get(k)!r}" for k in keys if old.get(k) != new.get(k)]


def _names(folder: Path) -> str:
    entries = sorted(p.name for p in folder.iterdir())
    return ", ".join(entries[:5]) + (" ..." if len(entries) > 5 else "")


def check_run_dir(out: Path, run_info: dict[str, Any], resume: bool) -> dict[str, Any] | None:
    """Check ``out`` against the new run; return the ``run.json`` to write.

    Returns ``None`` when ``out`` holds no run yet (``run_info`` is written).

    Raises:
        TrainingInputError: ``out`` is a file; it holds a symbolic link; it is
            not empty and holds no run of ours (no ``run.json``, or one not
            ours); it holds a run and ``resume`` is false; it holds a run with
            other options.
    """
    if out.exists() and not out.is_dir():
        raise TrainingInputError(f"--out {out} exists and is not a directory")
    if not out.is_dir():
        return None
    links = find_symlinks(out)
    if links:
        raise TrainingInputError(
            f"{links[0]} is a symbolic link (to {os.readlink(links[0])}): diffcontact does not "
            f"write through links in a run directory; remove it or choose another --out"
        )
    run_file = out / RUN_FILE
    if not run_file.exists():
        if any(out.iterdir()):
            raise TrainingInputError(
                f"--out {out} is not empty and holds no diffcontact run (no {RUN_FILE}; found "
                f"{_names(out)}): choose an empty or new folder"
            )
        return None
    old = read_json_object(run_file, "run file", TrainingInputError)
    if not is_run_file(old):
        raise TrainingInputError(
            f"{run_file} is not the run file of a diffcontact run: {out} is left alone; "
            "choose another --out"
        )
    if not resume:
        started = any((out / "checkpoints").glob("*.ckpt"))
        hint = (
            "pass --resume to continue it"
            if started
            else "it has no checkpoint yet (stopped before its first epoch ended?); pass "
            "--resume to start it again"
        )
        raise TrainingInputError(f"{out} already holds a run; {hint} or choose another --out")
    diff = _differences(old, run_info)
    if diff:
        hint = "use another --out"
        if any(d.startswith("data_checksum") for d in diff):
            hint = (
                f"the dataset at {run_info['data_dir']} is not the one this run trained on "
                f"(its metadata checksum differs); resume with that dataset, or {hint}"
            )
        raise TrainingInputError(f"{out} holds a different run ({'; '.join(diff)}); {hint}")
    info = dict(old)
    if old.get("data_dir") != run_info["data_dir"]:  # the same data, moved
        log.warning(
            "the run's dataset moved: %s -> %s (the same checksum); run.json names the new one",
            old.get("data_dir"), run_info["data_dir"],
        )  # fmt: skip
        info["data_dir"] = run_info["data_dir"]
    info.setdefault("data_checksum", run_info["data_checksum"])
    info["epochs"] = run_info["epochs"]
    info["resumed"] = [*info.get("resumed", []), run_info["created"]]
    return info


def write_run_file(out: Path, info: dict[str, Any]) -> None:
    try:
        out.mkdir(parents=True, exist_ok=True)
        atomic_write_json(out / RUN_FILE, info)
    except OSError as err:
        raise TrainingInputError(f"cannot write to {out}: {err}") from None


class RunLock:
    """An exclusive lock on a run directory, held by the process that trains in it: a
    second ``train`` there (a resume started while the run goes on) is refused instead of
    interleaving its log rows with the first's or clearing the files of a live run.

    It locks the folder itself (``flock`` on its descriptor: no file is written, and the
    lock ends with the process, however it ends); without ``fcntl`` (Windows) it does
    nothing."""

    def __init__(self, out: Path) -> None:
        self.out = out
        self.fd: int | None = None

    def acquire(self) -> None:
        """Take the lock if the folder exists (again: no-op).

        Raises:
            TrainingInputError: another process holds it."""
        if self.fd is not None or not self.out.is_dir():
            return
        try:
            import fcntl
        except ImportError:  # (Windows)
            return
        try:
            fd = os.open(self.out, os.O_RDONLY)
        except OSError:  # (an unreadable folder: the run directory's checks name it)
            return
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except OSError:
            os.close(fd)
            raise TrainingInputError(
                f"another process is training in {self.out} (it holds the folder's lock): "
                "wait for it to end, or stop it (Ctrl-C writes a checkpoint), then --resume"
            ) from None
        self.fd = fd

    def release(self) -> None:
        if self.fd is not None:
            os.close(self.fd)  # (closing the descriptor releases the lock)
            self.fd = None


def remove_temporaries(out: Path) -> None:
    """Remove the temporary files a killed writer left in the run directory's folders."""
    for folder in (out, out / "checkpoints", out / LOG_DIR):
        remove_orphan_temporaries(folder)


def clear_for_restart(out: Path) -> None:
    """Remove what a run that stopped before its first checkpoint left (log rows, learned.json)."""
    for name in _PARTIAL:
        (out / name).unlink(missing_ok=True)


# ------------------------------------------------------------------------ the CSV log


def _read_rows(path: Path) -> tuple[list[str], list[dict[str, Any]]]:
    with open(path, newline="") as fh:
        reader = csv.DictReader(fh)
        rows = list(reader)
        return list(reader.fieldnames or []), rows


def _write_rows(path: Path, fields: list[str], rows: list[dict[str, Any]]) -> None:
    buf = io.StringIO()
    writer = csv.DictWriter(buf, fieldnames=fields, lineterminator="\n", extrasaction="ignore")
    writer.writeheader()
    writer.writerows(rows)
    atomic_write_bytes(path, buf.getvalue().encode())


class _RunCSVWriter(ExperimentWriter):
    """Lightning's CSV writer: an existing ``metrics.csv`` is continued, links are never followed.

    Rows are appended (the file opened with ``O_NOFOLLOW``); a new column, or
    a link at the file's name, makes it rewritten by an atomic rename.
    ``hparams.yaml`` is written atomically too.
    """

    def _check_log_dir_exists(self) -> None:
        path = Path(self.metrics_file_path)
        if path.is_file() and not path.is_symlink():
            self.metrics_keys = _read_rows(path)[0]

    def save(self) -> None:
        if not self.metrics:
            return
        new_keys = self._record_new_keys()
        path = Path(self.metrics_file_path)
        if path.is_symlink():
            path.unlink()  # replaced by a file of ours, never written through
        if new_keys or not path.is_file():
            rows = _read_rows(path)[1] if path.is_file() else []
            _write_rows(path, self.metrics_keys, rows + self.metrics)
        else:
            fd = os.open(path, os.O_WRONLY | os.O_APPEND | getattr(os, "O_NOFOLLOW", 0))
            with os.fdopen(fd, "a", newline="") as fh:
                writer = csv.DictWriter(
                    fh, fieldnames=self.metrics_keys, lineterminator="\n", extrasaction="ignore"
                )
                writer.writerows(self.metrics)
        self.metrics = []

    def log_hparams(self, params: dict[str, Any]) -> None:
        self.hparams.update(params)
        text = yaml.safe_dump(jsonable(self.hparams), sort_keys=False)
        atomic_write_bytes(Path(self.log_dir) / self.NAME_HPARAMS_FILE, text.encode())


class _RunCSVLogger(CSVLogger):
    """``CSVLogger`` writing ``RUN_DIR/logs/metrics.csv``; a resumed run appends to it."""

    @property
    def experiment(self):  # type: ignore[override]
        if self._experiment is None:
            self._fs.makedirs(self.root_dir, exist_ok=True)
            self._experiment = _RunCSVWriter(log_dir=self.log_dir)
        return self._experiment


def _number(text: Any) -> float | None:
    try:
        return float(text)
    except (TypeError, ValueError):
        return None


def truncate_log(out: Path, epoch: int, step: int) -> None:
    """Keep only the rows of ``metrics.csv`` logged before ``(epoch, step)`` (a resume point).

    Rows are ordered by ``(epoch, step)``; rows that cannot be read (a line
    cut by a kill) are dropped.
    """
    path = out / LOG_DIR / METRICS
    if not path.is_file():
        return
    fields, rows = _read_rows(path)
    kept = []
    for row in rows:
        e, s = _number(row.get("epoch")), _number(row.get("step"))
        if e is not None and s is not None and (e, s) < (epoch, step):
            kept.append(row)
    _write_rows(path, fields, kept)


def loggers(out: Path) -> list[Any]:
    """The run's loggers: CSV (``logs/metrics.csv``) and, when installed, TensorBoard."""
    found: list[Any] = [_RunCSVLogger(save_dir=out, name=LOG_DIR, version="")]
    try:
        import tensorboard  # noqa: F401
    except ImportError:
        pass
    else:
        from lightning.pytorch.loggers import TensorBoardLogger

        found.append(TensorBoardLogger(save_dir=out / LOG_DIR, name="tensorboard", version=""))
    return found
