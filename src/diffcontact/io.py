"""Files and values at the boundary: atomic writes, JSON, device names.

Every writer writes to a temporary file in the destination's folder, flushes
and fsyncs it, then renames it over the destination with :func:`os.replace`
(atomic on POSIX and Windows when both are on the same file system). On any
error the temporary file is removed and the destination is left untouched.

:func:`jsonable` turns results (numpy and torch values, paths, non-finite
floats) into plain JSON data; :func:`read_json_object` reads a JSON file with
one-line errors; :func:`read_npz` reads ``.npz``/``.npy`` arrays after checking
that each array's header agrees with the bytes stored (a crafted header cannot
make it allocate terabytes); :func:`parse_device` checks a device name. torch is imported
only inside the functions that take tensors or devices.

Output folders are written only through these renames, so a symbolic link
planted at a file's name is replaced, never written through;
:func:`find_symlinks` lists the links in a folder (a run directory refuses
them), and :func:`remove_orphan_temporaries` removes the temporary files a
killed writer left behind (``.NAME.tmp-XXXXXXXX.SUFFIX``).
"""

from __future__ import annotations

import contextlib
import json
import math
import os
import re
import tempfile
import zipfile
import zlib
from collections.abc import Iterable, Iterator, Mapping
from pathlib import Path
from typing import IO, Any

import numpy as np

__all__ = [
    "atomic_path",
    "atomic_save_npz",
    "atomic_write_bytes",
    "atomic_write_json",
    "check_writable",
    "find_symlinks",
    "json_bytes",
    "jsonable",
    "parse_device",
    "read_json_object",
    "read_npz",
    "remove_orphan_temporaries",
    "replace_marked_section",
]

# Fixed zip entry timestamp so the same arrays always give the same bytes.
_ZIP_EPOCH = (1980, 1, 1, 0, 0, 0)
# the names atomic_path gives its temporary files (mkstemp adds 8 characters)
_TEMPORARY = re.compile(r"^\..+\.tmp-[A-Za-z0-9_]{8}[^/]*$")


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
    Writability is tried with a file created and removed in the folder:
    permission bits say nothing for root or on read-only or virtual file systems
    (``/sys``, ``/proc``).
    """
    p = Path(path)
    parent = p.parent if str(p.parent) else Path(".")
    if p.is_dir():
        raise IsADirectoryError(f"{p} is a directory")
    if parent.exists() and not parent.is_dir():
        raise NotADirectoryError(f"{parent} is not a folder")
    if not parent.is_dir():
        raise FileNotFoundError(f"folder {parent} does not exist")
    if not os.access(parent, os.W_OK | os.X_OK):
        raise PermissionError(f"folder {parent} is not writable")
    try:  # what the writer will do: create a file there (root passes os.access anywhere)
        fd, probe = tempfile.mkstemp(dir=parent, prefix=".diffcontact-probe-")
    except OSError as e:
        raise PermissionError(f"folder {parent} is not writable ({e.strerror})") from None
    os.close(fd)
    os.unlink(probe)
    if p.exists() and not os.access(p, os.W_OK):
        raise PermissionError(f"{p} is not writable")
    return p


def check_writable_folder(path: str | os.PathLike[str]) -> Path:
    """Return ``path`` as a ``Path`` if it is a folder, or can be made one, where files can be
    written; else raise ``OSError``.

    ``path`` must not be a file (nor lie under one), and its nearest existing ancestor
    must be a writable folder. Call it before expensive work whose results go there.
    """
    p = Path(path)
    existing = p
    while not existing.exists() and existing != existing.parent:
        existing = existing.parent
    if not existing.is_dir():
        if existing == p:
            raise NotADirectoryError(f"{p} exists and is not a folder")
        raise NotADirectoryError(f"{p} cannot be made: {existing} is not a folder")
    if not os.access(existing, os.W_OK | os.X_OK):
        raise PermissionError(f"folder {existing} is not writable")
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
    try:
        fd, tmp_name = tempfile.mkstemp(
            dir=folder, prefix=f".{target.stem}.tmp-", suffix=target.suffix
        )
    except OSError as err:  # (a missing folder named the hidden temporary file)
        raise type(err)(err.errno, err.strerror or str(err), str(target)) from None
    os.close(fd)
    tmp = Path(tmp_name)
    try:
        yield tmp
        with open(tmp, "rb+") as fh:
            os.fsync(fh.fileno())
        os.chmod(tmp, 0o666 & ~_umask())
        os.replace(tmp, target)
    except OSError as err:
        with contextlib.suppress(OSError):
            tmp.unlink()
        if err.filename not in (None, str(tmp), tmp):
            raise
        # a full disk said "No space left on device" without a name, or named the
        # temporary file: name the file that was being written
        raise type(err)(err.errno, err.strerror or str(err), str(target)) from err
    except BaseException:
        with contextlib.suppress(OSError):
            tmp.unlink()
        raise
    _fsync_dir(folder)


def find_symlinks(folder: str | os.PathLike[str]) -> list[Path]:
    """The symbolic links in ``folder`` and below (links to folders are not followed).

    ``folder`` itself may be a link (the caller named it); an absent folder has none.
    """
    found: list[Path] = []
    for root, dirs, files in os.walk(folder):
        for name in [*dirs, *files]:
            path = Path(root, name)
            if path.is_symlink():
                found.append(path)
    return sorted(found)


def remove_orphan_temporaries(folder: str | os.PathLike[str]) -> list[Path]:
    """Remove the temporary files of :func:`atomic_path` left in ``folder`` by a killed writer.

    Only ``folder``'s own entries named like ours (``.NAME.tmp-XXXXXXXX.SUFFIX``)
    are removed; returns them.
    """
    removed = []
    with contextlib.suppress(FileNotFoundError, NotADirectoryError):
        for entry in os.scandir(folder):
            if _TEMPORARY.match(entry.name) and not entry.is_dir(follow_symlinks=False):
                with contextlib.suppress(FileNotFoundError):
                    os.unlink(entry.path)
                    removed.append(Path(entry.path))
    return sorted(removed)


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


def jsonable(value: Any) -> Any:
    """``value`` as plain JSON data, for writing and for comparing with what was read back.

    Mappings become dicts with ``str`` keys; lists, tuples, numpy arrays and
    torch tensors become lists; numpy scalars become Python numbers and bools;
    paths become strings; non-finite floats (NaN, inf) become ``None``, since
    JSON has no such numbers. Anything else is returned unchanged.
    """
    if isinstance(value, Mapping):
        return {str(k): jsonable(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [jsonable(v) for v in value]
    if hasattr(value, "detach"):  # torch tensor, without importing torch
        value = value.detach().cpu().numpy()
    if isinstance(value, np.ndarray):
        return jsonable(value.tolist())
    if isinstance(value, os.PathLike):
        return os.fspath(value)
    if isinstance(value, np.bool_):
        return bool(value)
    if isinstance(value, np.integer):
        return int(value)
    if isinstance(value, (float, np.floating)):
        number = float(value)
        return number if math.isfinite(number) else None
    return value


def json_bytes(data: Any) -> bytes:
    """``jsonable(data)`` as indented JSON text with a final newline, UTF-8 encoded."""
    return (json.dumps(jsonable(data), indent=2, allow_nan=False) + "\n").encode()


def atomic_write_json(path: str | os.PathLike[str], data: Any) -> Path:
    """Write ``data`` (through :func:`jsonable`) as indented JSON atomically; return the path."""
    return atomic_write_bytes(path, json_bytes(data))


def _section_span(text: str, begin: str, end: str, where: str) -> tuple[int, int] | None:
    """``(start, stop)`` of the block ``begin ... end`` in ``text``, ``None`` where neither
    marker is there; a ``ValueError`` for a marker without its partner, or twice."""
    n_begin, n_end = text.count(begin), text.count(end)
    if n_begin == n_end == 0:
        return None
    start = text.find(begin)
    stop = text.find(end, start + len(begin)) if start >= 0 else -1
    if n_begin != 1 or n_end != 1 or stop < 0:
        raise ValueError(
            f"{where} holds the markers of this section {n_begin} and {n_end} times or in "
            f"the wrong order ({begin!r} ... {end!r}); mend the file by hand (nothing was "
            "written): replacing from a stray marker would delete the text after it"
        )
    return start, stop + len(end)


def replace_marked_section(
    path: str | os.PathLike[str], begin: str, end: str, block: str, *, check_only: bool = False
) -> None:
    """Put ``block`` (which starts with ``begin`` and ends with ``end``) into the Markdown
    file ``path`` in place of its marked section, or append it where the file has none
    (a new file holds the block alone); the rest of the file is kept. Written atomically.

    Raises:
        ValueError: ``path`` is a directory, or holds one marker without the other, one of
            them twice, or in the wrong order (nothing is written). ``check_only``: only
            these checks (before a long computation).
    """
    target = Path(path)
    if target.is_dir():
        raise ValueError(f"{target} is a directory; give a Markdown file")
    text = target.read_text() if target.is_file() else ""
    span = _section_span(text, begin, end, str(target))
    if check_only:
        if not target.is_file():
            check_writable(target)
        return
    if span is None:
        text = text.rstrip("\n") + ("\n\n" if text.strip() else "") + block.rstrip("\n") + "\n"
    else:
        text = text[: span[0]] + block.rstrip("\n") + text[span[1] :]
    atomic_write_bytes(target, text.encode())


def _physical_memory() -> int | None:
    """Bytes of physical memory, or ``None`` where the platform does not say."""
    try:
        return int(os.sysconf("SC_PHYS_PAGES")) * int(os.sysconf("SC_PAGE_SIZE"))
    except (AttributeError, ValueError, OSError):
        return None


def _gib(n: int) -> str:
    """A byte count for people: ``"14.6 TiB"``, ``"96 bytes"``."""
    for unit, size in (("PiB", 2**50), ("TiB", 2**40), ("GiB", 2**30), ("MiB", 2**20)):
        if n >= size:
            return f"{n / size:.3g} {unit}"
    return f"{n:,} bytes"


def _checked_header(fh: IO[bytes], stored: int, name: str) -> None:
    """Read an ``.npy`` header from ``fh`` and check it against ``stored`` bytes in all.

    Raises:
        ValueError: not an ``.npy`` header, an object dtype, or a shape whose
            data would not be the bytes stored (or would not fit in memory).
    """
    fmt = np.lib.format
    version = fmt.read_magic(fh)
    if version == (1, 0):
        shape, _, dtype = fmt.read_array_header_1_0(fh)
    elif version in ((2, 0), (3, 0)):
        shape, _, dtype = fmt.read_array_header_2_0(fh)
    else:  # pragma: no cover - read_magic accepts only these
        raise ValueError(f"{name}: unsupported .npy format version {version}")
    if dtype.hasobject:
        raise ValueError(f"{name}: holds Python objects (dtype {dtype}); only numbers are read")
    data = stored - fh.tell()
    claimed = math.prod(shape) * dtype.itemsize
    memory = _physical_memory()
    if claimed != data or (memory is not None and claimed > memory):
        shown = "x".join(map(str, shape)) or "scalar"
        why = (
            f"more than this machine's memory ({_gib(memory)})"
            if memory is not None and claimed > memory and claimed == data
            else f"but {_gib(max(data, 0))} of data are stored (truncated or forged header)"
        )
        raise ValueError(
            f"{name}: its header claims a {shown} array of {dtype} ({_gib(claimed)}), {why}; "
            "not read"
        )


def read_npz(
    source: str | os.PathLike[str] | IO[bytes], names: Iterable[str] | None = None
) -> tuple[dict[str, np.ndarray], list[str]]:
    """Arrays of an ``.npz`` file (or one ``.npy`` array, named ``""``), read safely.

    Before an array is read, its ``.npy`` header (shape, dtype) is checked
    against the size the file (or zip member) actually has, so a forged header
    that claims a huge shape is refused instead of allocating it; object arrays
    (pickles) are refused.

    Args:
        source: a path or a binary file object (e.g. ``io.BytesIO``).
        names: the arrays to read (absent ones are skipped); ``None``: all.

    Returns:
        ``(arrays, members)``: the arrays read by name, and the names of all
        arrays in the file.

    Raises:
        ValueError: (one line) the file is not a readable ``.npz``/``.npy``
            (truncated, corrupted, forged header, object array); the message
            names the array.
        OSError: the file cannot be opened.
    """
    wanted = None if names is None else set(names)
    fh: IO[bytes]
    close = False
    if isinstance(source, (str, os.PathLike)):
        fh, close = open(source, "rb"), True  # closed below
    else:
        fh = source
    try:
        start = fh.tell()
        magic = fh.read(6)
        fh.seek(start)
        is_zip = magic[:4] == b"PK\x03\x04"
        if not is_zip and magic != b"\x93NUMPY":  # (a CSV file said "the magic string is
            # not correct; expected b'\x93NUMPY'")
            raise ValueError(
                f"not an .npz or .npy file (it starts with {magic!r}): save arrays with numpy.savez"
            )
        if not is_zip:
            size = fh.seek(0, os.SEEK_END) - start
            fh.seek(start)
            _checked_header(fh, size, "the .npy array")
            fh.seek(start)
            arr = np.lib.format.read_array(fh, allow_pickle=False)
            return {"": arr}, [""]
        arrays: dict[str, np.ndarray] = {}
        with zipfile.ZipFile(fh) as zf:
            infos = [i for i in zf.infolist() if i.filename.endswith(".npy")]
            members = [i.filename[: -len(".npy")] for i in infos]
            for info, name in zip(infos, members, strict=True):
                if wanted is not None and name not in wanted:
                    continue
                with zf.open(info) as member:
                    _checked_header(member, info.file_size, f"array {name!r}")
                with zf.open(info) as member:
                    arrays[name] = np.lib.format.read_array(member, allow_pickle=False)
        return arrays, members
    except (EOFError, KeyError, zipfile.BadZipFile, zlib.error, RuntimeError) as err:
        raise ValueError(f"{type(err).__name__}: {err}") from None
    finally:
        if close:
            fh.close()


def read_json_object(
    path: str | os.PathLike[str], what: str, error: type[Exception] = ValueError
) -> dict[str, Any]:
    """The JSON object stored in ``path``.

    Raises:
        error: (a one-line message naming ``what`` and the path) the file
            cannot be read, is not JSON or holds something other than an object.
    """
    try:
        data = json.loads(Path(path).read_text())
    except OSError as err:
        raise error(f"cannot read {what} {path}: {err.strerror or err}") from None
    except (UnicodeDecodeError, json.JSONDecodeError) as err:
        raise error(f"{what} {path} is not valid JSON: {err}") from None
    except RecursionError:
        raise error(f"{what} {path} is nested too deeply to be read") from None
    if not isinstance(data, dict):
        raise error(f"{what} {path} does not hold a JSON object")
    return data


def parse_device(device: Any, *, allow_index: bool = True) -> Any:
    """``device`` (``"cpu"``, ``"cuda"``, ``"cuda:N"`` or a ``torch.device``) as a ``torch.device``.

    Args:
        device: the device asked for.
        allow_index: whether ``"cuda:N"`` is accepted (a Lightning run picks
            its GPUs with ``devices`` instead).

    Raises:
        ValueError: not a CPU or CUDA device, or CUDA asked for but not available.
    """
    import torch

    try:
        dev = torch.device(device)
    except (RuntimeError, TypeError):
        dev = None
    if (
        dev is None
        or dev.type not in ("cpu", "cuda")
        or (dev.index is not None and not allow_index)
    ):
        raise ValueError(f"device must be 'cpu' or 'cuda', got {device!r}")
    if dev.type == "cuda" and not torch.cuda.is_available():
        raise ValueError(f"device {device!r} requested but CUDA is not available (use 'cpu')")
    return dev
