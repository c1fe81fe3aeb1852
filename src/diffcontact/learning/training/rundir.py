"""The run directory of ``train()``: what may be written, ``run.json`` and the CSV log.

A run directory is written only when it is new or empty, or holds a run of
ours: its ``run.json`` (written first, before anything else) carries our
schema (``format_version``, ``model``, ``versions.diffcontact``). A folder
with other files, or a run directory holding a symbolic link, is refused
with a one-line :class:`TrainingInputError`; every file is written by
renaming a temporary file of the same folder over it (``diffcontact.io``), so
a link planted later is replaced, never written through. The CSV log
(``logs/metrics.csv``) is appended to without following links and rewritten
atomically when a column is added; an append that fails (a full disk) leaves
no half-written line and names the file. A resume keeps the log's complete
rows before the checkpoint and says which lines it dropped as incomplete.
"""

from __future__ import annotations

import contextlib
import csv
import io
import logging
import os
import re
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
# the files and folders a run writes: a folder (or other non-file) at a file's name, or a
# file at a folder's, made the write fail when it came (last.ckpt: at the end of the first
# epoch, after its time was spent), so a resume refuses it up front
_FILES = (
    "learned.json", "model.pt", "refit.json", "model_adam.pt", "checkpoints/last.ckpt",
    f"{LOG_DIR}/{METRICS}", f"{LOG_DIR}/hparams.yaml",
)  # fmt: skip
_FOLDERS = ("checkpoints", LOG_DIR)
_EPOCH_CHECKPOINT = re.compile(r"^epoch\d+\.ckpt$")


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


def _wrong_kind(out: Path) -> str | None:
    """What stands where the run writes a file or makes a folder, of the other kind."""
    for name in _FOLDERS:
        path = out / name
        if path.exists() and not path.is_dir():
            return f"{path} is a file where the run keeps a folder"
    paths = [out / name for name in _FILES]
    folder = out / "checkpoints"
    if folder.is_dir():
        paths += sorted(p for p in folder.iterdir() if _EPOCH_CHECKPOINT.match(p.name))
    for path in paths:
        if path.exists() and not path.is_file():
            kind = "a directory" if path.is_dir() else "not a regular file"
            return f"{path} is {kind}, and the run writes a file there"
    return None


def check_run_dir(out: Path, run_info: dict[str, Any], resume: bool) -> dict[str, Any] | None:
    """Check ``out`` against the new run; return the ``run.json`` to write.

    Returns ``None`` when ``out`` holds no run yet (``run_info`` is written).

    Raises:
        TrainingInputError: ``out`` is a file; it holds a symbolic link; it is
            not empty and holds no run of ours (no ``run.json``, or one not
            ours); it holds a run and ``resume`` is false; it holds a run with
            other options; a folder stands at the name of a file the run writes
            (``checkpoints/last.ckpt``, ...), or a file at a folder's.
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
    wrong = _wrong_kind(out)
    if wrong:
        raise TrainingInputError(
            f"cannot resume: {wrong} (the run would fail there only when it writes it, "
            "after the time spent training); move it away, then --resume"
        )
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


def _named(err: OSError, path: Path) -> OSError:
    """``err`` naming ``path`` (a full disk says "No space left on device", naming nothing)."""
    if err.filename is not None:
        return err
    return type(err)(err.errno, err.strerror or str(err), str(path))


def _append_rows(path: Path, fields: list[str], rows: list[dict[str, Any]]) -> None:
    """Append ``rows`` to the CSV file ``path`` (not following a link there).

    A failed write (a full disk) is undone: the file is cut back to its size
    before, so no half-written line stays; the error names the file.
    """
    buf = io.StringIO()
    writer = csv.DictWriter(buf, fieldnames=fields, lineterminator="\n", extrasaction="ignore")
    writer.writerows(rows)
    data = memoryview(buf.getvalue().encode())
    try:
        fd = os.open(path, os.O_WRONLY | os.O_APPEND | getattr(os, "O_NOFOLLOW", 0))
    except OSError as err:
        raise _named(err, path) from err
    try:
        size = os.fstat(fd).st_size
        try:
            while data:
                data = data[os.write(fd, data) :]
        except OSError as err:
            with contextlib.suppress(OSError):
                os.ftruncate(fd, size)
            raise _named(err, path) from err
    finally:
        os.close(fd)


class _RunCSVWriter(ExperimentWriter):
    """Lightning's CSV writer: an existing ``metrics.csv`` is continued, links are never followed.

    Rows are appended (the file opened with ``O_NOFOLLOW``; a failed append is
    cut back and names the file); a new column, or a link at the file's name,
    makes it rewritten by an atomic rename. ``hparams.yaml`` is written
    atomically too.
    """

    def _check_log_dir_exists(self) -> None:
        path = Path(self.metrics_file_path)
        if path.is_file() and not path.is_symlink():
            self.metrics_keys = _read_rows(path)[0]

    def save(self) -> None:
        if not self.metrics:
            return
        keys = list(self.metrics_keys)
        new_keys = self._record_new_keys()
        path = Path(self.metrics_file_path)
        try:
            if path.is_symlink():
                path.unlink()  # replaced by a file of ours, never written through
            if new_keys or not path.is_file():
                rows = _read_rows(path)[1] if path.is_file() else []
                _write_rows(path, self.metrics_keys, rows + self.metrics)
            else:
                _append_rows(path, self.metrics_keys, self.metrics)
        except BaseException:
            # nothing was written: a later save (Lightning's at the end) writes these rows,
            # and a new column, again
            self.metrics_keys = keys
            raise
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


def _read_log(path: Path) -> tuple[list[str], list[tuple[int, dict[str, str]]], list[int]]:
    """A CSV log's header, its complete rows (each with its line number in the file) and
    the numbers of its incomplete lines.

    A line is incomplete when it does not hold as many cells as the header, holds NUL
    or undecodable bytes, or is the file's last and does not end with a newline: a line
    cut mid-way (a crash or a full disk while it was appended; rows appended after the
    cut continue that line, which then holds too many cells). Blank lines are skipped.
    """
    with open(path, newline="", encoding="utf-8", errors="replace") as fh:
        text = fh.read()
    reader = csv.reader(io.StringIO(text))
    header = next(reader, [])
    rows: list[tuple[int, dict[str, str]]] = []
    bad: list[int] = []
    line = reader.line_num + 1  # the first line of the next record
    for cells in reader:
        first, line = line, reader.line_num + 1
        if not cells:
            continue
        if len(cells) != len(header) or any("\x00" in c or "\ufffd" in c for c in cells):
            bad.append(first)
        else:
            rows.append((first, dict(zip(header, cells, strict=True))))
    if rows and not text.endswith(("\n", "\r")) and rows[-1][0] > max(bad, default=0):
        bad.append(rows.pop()[0])  # the last line, cut where its cells were complete
    return header, rows, bad


def _dropped_lines(path: Path, bad: list[int], kept: list[int]) -> str:
    """The warning on the incomplete lines ``bad`` of ``path`` (``kept``: the line numbers
    of the rows kept)."""
    first = bad[0]
    before = sum(n < first for n in kept)
    after = len(kept) - before
    which = f"line {first} is" if len(bad) == 1 else f"lines {', '.join(map(str, bad))} are"
    return (
        f"{path}: {which} incomplete (cut mid-line, as a crash or a full disk while the log "
        f"was written leaves it); dropped {'it' if len(bad) == 1 else 'them'}, kept the "
        f"{before} rows before {'it' if len(bad) == 1 else 'the first'}"
        + (f" and the {after} complete rows after it" if after else "")
    )


def truncate_log(out: Path, epoch: int, step: int) -> None:
    """Keep only the rows of ``metrics.csv`` logged before ``(epoch, step)`` (a resume point).

    Rows are ordered by ``(epoch, step)``. Incomplete lines (cut by a crash or a
    full disk, :func:`_read_log`) are dropped with a warning that names them and
    the rows kept; complete rows before the resume point are all kept.
    """
    path = out / LOG_DIR / METRICS
    if not path.is_file():
        return
    fields, rows, bad = _read_log(path)
    kept = []
    for line, row in rows:
        e, s = _number(row.get("epoch")), _number(row.get("step"))
        if e is not None and s is not None and (e, s) < (epoch, step):
            kept.append((line, row))
    _write_rows(path, fields, [row for _, row in kept])
    if bad:
        log.warning("%s", _dropped_lines(path, bad, [line for line, _ in kept]))


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
