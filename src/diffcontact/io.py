"""Atomic file writing: a reader never sees a half-written file.

Every helper writes to a temporary file in the destination's folder, flushes
and fsyncs it, then renames it over the destination with :func:`os.replace`
(atomic on POSIX and Windows when both are on the same file system). On any
error the temporary file is removed and the destination is left untouched.
"""

from __future__ import annotations

import contextlib
import os
import tempfile
import zipfile
from collections.abc import Iterator
from pathlib import Path

import numpy as np

__all__ = ["atomic_path", "atomic_save_npz", "atomic_write_bytes", "check_writable"]

# Fixed zip entry timestamp so the same arrays always give the same bytes.
_ZIP_EPOCH = (1980, 1, 1, 0, 0, 0)


def _umask() -> int:
    mask = os.umask(0)
    os.umask(mask)
    return mask


def _fsync_dir(folder: Path) -> None:
    """Make a rename durable (best effort; not possible on every platform)."""
    try:
        fd = os.open(folder, os.O_RDONLY)
    except OSError:
        return
    try:
        os.fsync(fd)
    except OSError:
        pass
    finally:
        os.close(fd)


def check_writable(path: str | os.PathLike[str]) -> Path:
    """Return ``path`` as a ``Path`` if a file can be written there, else raise ``OSError``.

    Checks that the parent folder exists and is writable and that ``path`` is
    not a folder. Call it before expensive work whose result goes to ``path``.
    """
    p = Path(path)
    parent = p.parent if str(p.parent) else Path(".")
    if p.is_dir():
        raise IsADirectoryError(f"{p} is a directory")
    if not parent.is_dir():
        raise FileNotFoundError(f"folder {parent} does not exist")
    if not os.access(parent, os.W_OK | os.X_OK):
        raise PermissionError(f"folder {parent} is not writable")
    if p.exists() and not os.access(p, os.W_OK):
        raise PermissionError(f"{p} is not writable")
    return p


@contextlib.contextmanager
def atomic_path(path: str | os.PathLike[str]) -> Iterator[Path]:
    """Yield a temporary path next to ``path``; on success move it onto ``path``.

    The temporary name keeps ``path``'s suffix, so writers that infer the
    format from the extension (Pillow, matplotlib) still work::

        with atomic_path("anim.gif") as tmp:
            writer.save(tmp)
    """
    target = Path(path)
    folder = target.parent if str(target.parent) else Path(".")
    fd, tmp_name = tempfile.mkstemp(dir=folder, prefix=f".{target.stem}.tmp-", suffix=target.suffix)
    os.close(fd)
    tmp = Path(tmp_name)
    try:
        yield tmp
        with open(tmp, "rb+") as fh:
            os.fsync(fh.fileno())
        os.chmod(tmp, 0o666 & ~_umask())
        os.replace(tmp, target)
    except BaseException:
        with contextlib.suppress(OSError):
            tmp.unlink()
        raise
    _fsync_dir(folder)


def atomic_write_bytes(path: str | os.PathLike[str], data: bytes) -> Path:
    """Write ``data`` to ``path`` atomically; return the path."""
    with atomic_path(path) as tmp, open(tmp, "wb") as fh:
        fh.write(data)
    return Path(path)


def atomic_save_npz(
    path: str | os.PathLike[str], *, compress: bool = False, **arrays: object
) -> Path:
    """Save named arrays as an ``.npz`` file atomically; return the path.

    Readable with ``np.load(path)`` (no pickle: object arrays are refused;
    strings are stored as numpy unicode arrays). The output is byte-for-byte
    reproducible: entries keep the argument order and carry a fixed timestamp.
    The name is used as given (no ``.npz`` is appended).
    """
    prepared = {}
    for name, value in arrays.items():
        if hasattr(value, "detach"):  # torch tensor, without importing torch
            value = value.detach().cpu().numpy()
        arr = np.asanyarray(value)
        if arr.dtype == object:
            raise TypeError(f"atomic_save_npz: array {name!r} has dtype object; not saved")
        prepared[name] = arr
    method = zipfile.ZIP_DEFLATED if compress else zipfile.ZIP_STORED
    with (
        atomic_path(path) as tmp,
        zipfile.ZipFile(tmp, mode="w", compression=method, allowZip64=True) as zf,
    ):
        for name, arr in prepared.items():
            info = zipfile.ZipInfo(f"{name}.npy", date_time=_ZIP_EPOCH)
            info.compress_type = method
            info.external_attr = 0o644 << 16
            with zf.open(info, mode="w", force_zip64=True) as fh:
                np.lib.format.write_array(fh, arr, allow_pickle=False)
    return Path(path)
