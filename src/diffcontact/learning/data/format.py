"""The dataset format and its one reader (``docs/data.md``).

A dataset is a folder (``docs/conventions.md``, "Learning")::

    metadata.json   arguments, config, seeds, counts, sha256 of every file
    train.npz       traj (N, T, 2, P, d) float64, chunks (M, L, 2, P, d) float64,
    val.npz         chunk_start (M,) int64, chunk_has_contact (M,) bool,
    test.npz        contact (N, T) bool; with windows (metadata ``stride``):
                    chunk_traj (M,) int64, else M = N (one chunk per trajectory)

``metadata.json`` is written last, so a folder without it is unfinished (an
interrupted run leaves the marker file :data:`MARKER`). It carries its own
checksum (``metadata_sha256``, :func:`metadata_checksum`), which covers every
other key, the data files' checksums in ``files`` included, so an edited
``metadata.json`` (e.g. its ``config.dt``) is refused like a changed data
file; metadata written before the checksum existed is read with a warning
(once per folder). :func:`load_dataset` reads a folder, checks the metadata
and every file against their checksums and returns a :class:`Dataset`, whose
``split(name)`` reads one split as tensors; training and evaluation read
datasets through it. A file that cannot be read (truncated, not an ``.npz``,
not JSON) is a :class:`DatasetError` naming it.
"""

from __future__ import annotations

import hashlib
import io
import json
import logging
import math
import os
import re
import time
import zipfile
import zlib
from dataclasses import dataclass, fields
from functools import cached_property
from pathlib import Path
from typing import IO, Any

import numpy as np
import torch
from torch import Tensor

from diffcontact.cli_args import one_line
from diffcontact.io import jsonable, read_json_object, read_npz
from diffcontact.systems import System, load_config, load_system
from diffcontact.systems.config import stored_config

__all__ = [
    "ARRAYS",
    "FORMAT_VERSION",
    "MARKER",
    "METADATA",
    "METADATA_CHECKSUM",
    "SPLITS",
    "WINDOW_ARRAYS",
    "DataSplit",
    "Dataset",
    "DatasetError",
    "load_dataset",
    "metadata_checksum",
    "read_metadata",
    "sha256_file",
    "split_seeds",
    "structure_mismatch",
    "verify_files",
]

log = logging.getLogger(__name__)

FORMAT_VERSION = 1
SPLITS = ("train", "val", "test")
METADATA = "metadata.json"
METADATA_CHECKSUM = "metadata_sha256"  # the key of metadata.json's own checksum
ARRAYS = ("traj", "chunks", "chunk_start", "chunk_has_contact", "contact")
# written when the chunks are windows (metadata "stride" set): the trajectory of each chunk
WINDOW_ARRAYS = ("chunk_traj",)
MARKER = ".generating.json"  # arguments of a run in progress; removed after metadata.json
TMP_NAME = re.compile(r"^\.(train|val|test|metadata|\.generating)\.tmp-")
# numpy SeedSequence streams derived from one split seed (see split_seeds)
STREAM_CHUNKS, STREAM_NOISE, STREAM_SPLIT = 1, 2, 3
# metadata keys every dataset has
_REQUIRED = (
    "format_version", "config", "task", "seed", "seeds", "dt", "n_train", "n_val", "n_test",
    "n_states", "noise_std", "chunk_length", "files", "arguments",
)  # fmt: skip
# a file whose timestamps were this close to its verification may change unnoticed within
# the file system's timestamp granularity; it is hashed again when a split is read
_RECENT_NS = 2_000_000_000
# folders whose metadata.json (written by an earlier version) has no checksum: warned once
_UNCHECKED: set[str] = set()
# what reading a damaged .npz raises (numpy, zipfile, zlib)
_NPZ_ERRORS = (OSError, EOFError, ValueError, KeyError, zipfile.BadZipFile, zlib.error)


class DatasetError(ValueError):
    """A dataset folder is missing, incomplete, corrupted or of an unknown format."""


def split_seeds(seed: int) -> dict[str, int]:
    """Seeds of the splits: ``seed * 1000 + 0, 1, 2`` for train, val, test.

    Each split seed seeds the initial conditions
    (``System.sample_initial_conditions``); the chunk choice and the noise of
    that split use ``numpy.random.default_rng([split_seed, 1])`` and
    ``default_rng([split_seed, 2])``.
    """
    return {name: seed * 1000 + k for k, name in enumerate(SPLITS)}


# ------------------------------------------------------------------- checksums


def _sha256(fh: IO[bytes]) -> str:
    h = hashlib.sha256()
    for block in iter(lambda: fh.read(1 << 20), b""):
        h.update(block)
    return h.hexdigest()


def sha256_file(path: Path) -> str:
    """The sha256 hex digest of a file, read in blocks."""
    with open(path, "rb") as fh:
        return _sha256(fh)


def _signature(st: os.stat_result) -> tuple[int, int, int, int]:
    """What changes when a file is written: inode, size and timestamps."""
    return (st.st_ino, st.st_size, st.st_mtime_ns, st.st_ctime_ns)


def _checksum_error(path: Path, folder: Path) -> DatasetError:
    return DatasetError(
        f"{path} does not match its sha256 checksum in metadata.json (the file was "
        f"changed or is corrupted); delete {folder} and generate it again"
    )


def verify_files(folder: Path, meta: dict[str, Any]) -> dict[str, tuple[int, int, int, int]]:
    """Check every split file of ``folder`` against the checksums in ``meta["files"]``.

    Returns:
        ``{file name: signature}`` of the verified files that had not been
        written within the last seconds: while such a file's signature (inode,
        size, timestamps) stays the same, its bytes are those verified.

    Raises:
        DatasetError: ``files`` is malformed, a file is missing or fails its checksum.
    """
    files = meta.get("files")
    expected = {f"{s}.npz" for s in SPLITS}
    if not isinstance(files, dict) or set(files) != expected:
        raise DatasetError(
            f"{folder / METADATA}: 'files' must map {sorted(expected)} to sha256 checksums, "
            f"got {files!r}"
        )
    verified = {}
    for name in sorted(files):
        path = folder / name
        if not path.is_file():
            raise DatasetError(
                f"{path} is missing (metadata.json lists it): the dataset is incomplete; "
                f"delete {folder} and generate it again"
            )
        now = time.time_ns()
        with open(path, "rb") as fh:
            st = os.fstat(fh.fileno())
            if _sha256(fh) != files[name]:
                raise _checksum_error(path, folder)
        if max(st.st_mtime_ns, st.st_ctime_ns) < now - _RECENT_NS:
            verified[name] = _signature(st)
    return verified


def metadata_checksum(meta: dict[str, Any]) -> str:
    """The sha256 of ``meta`` without its checksum key, as canonical JSON.

    Canonical: keys sorted, no spaces, ASCII (``json.dumps(..., sort_keys=True,
    separators=(",", ":"))``), so what was written and what is read back give
    the same digest.
    """
    body = {k: v for k, v in meta.items() if k != METADATA_CHECKSUM}
    text = json.dumps(jsonable(body), sort_keys=True, separators=(",", ":"), allow_nan=False)
    return hashlib.sha256(text.encode()).hexdigest()


def read_metadata(folder: Path) -> dict[str, Any]:
    """``folder/metadata.json`` as a dict, checked against its own checksum.

    Metadata without a checksum (written by an earlier diffcontact) is read
    with a warning, once per folder.

    Raises:
        DatasetError: the file cannot be read, is not a JSON object, or does
            not match its checksum (it was edited or corrupted).
    """
    path = folder / METADATA
    meta = read_json_object(path, "dataset metadata", DatasetError)
    stored = meta.get(METADATA_CHECKSUM)
    if stored is None:
        key = str(path.resolve())
        if key not in _UNCHECKED:
            _UNCHECKED.add(key)
            log.warning(
                "%s has no checksum (written by an earlier diffcontact): its contents are "
                "not verified; generate the dataset again to add one", path,
            )  # fmt: skip
    elif stored != metadata_checksum(meta):
        raise DatasetError(
            f"{path} does not match its checksum ({METADATA_CHECKSUM}): the file was edited "
            f"or is corrupted; delete {folder} and generate it again"
        )
    return meta


# -------------------------------------------------------------------------- load


@dataclass(frozen=True)
class DataSplit:
    """One split of a dataset as tensors: ``N`` trajectories of ``T`` states, ``M`` chunks of ``L``.

    Attributes:
        name: ``"train"``, ``"val"`` or ``"test"``.
        traj: ``(N, T, 2, P, d)`` clean full trajectories.
        chunks: ``(M, L, 2, P, d)`` training chunks (noisy when the dataset's
            ``noise_std > 0``); ``M = N`` (one per trajectory) unless the
            dataset holds windows (metadata ``stride``).
        chunk_start: ``(M,)`` int64, index of each chunk's first state in its trajectory.
        chunk_has_contact: ``(M,)`` bool, the chunk contains a flagged state.
        contact: ``(N, T)`` bool, states flagged in contact (simulated data: a
            contact was resolved there; recorded data: ``docs/data.md``, "Contact flags").
        chunk_traj: ``(M,)`` int64, the trajectory of each chunk (``arange(N)``
            for one chunk per trajectory).
    """

    name: str
    traj: Tensor
    chunks: Tensor
    chunk_start: Tensor
    chunk_has_contact: Tensor
    contact: Tensor
    chunk_traj: Tensor

    def __len__(self) -> int:
        return int(self.traj.shape[0])

    def to(
        self, device: torch.device | str | None = None, dtype: torch.dtype | None = None
    ) -> DataSplit:
        """A copy with the tensors on ``device`` and the float ones (traj, chunks) in ``dtype``."""
        out = {}
        for f in fields(self):
            value = getattr(self, f.name)
            if isinstance(value, Tensor):
                value = value.to(device=device, dtype=dtype if value.is_floating_point() else None)
            out[f.name] = value
        return DataSplit(**out)


class Dataset:
    """A dataset folder read by :func:`load_dataset`.

    Attributes:
        path: the folder.
        metadata: ``metadata.json`` as a dict.
        config: the validated system config.
        system: a :class:`~diffcontact.systems.System` built from the config
            (created on first use).
        task, dt, chunk_length, noise_std, n_states, counts: from the metadata.

    ``split(name)`` (or ``.train``, ``.val``, ``.test``) reads a split as a
    :class:`DataSplit`. Its bytes are checked against their checksum unless
    :func:`load_dataset` verified the file and it is unchanged since
    (``verified``: file name -> signature, from :func:`verify_files`), so a
    dataset is hashed once on the way from the folder to the tensors.
    """

    def __init__(
        self,
        path: Path,
        metadata: dict[str, Any],
        config: Any,
        verified: dict[str, tuple[int, int, int, int]] | None = None,
    ) -> None:
        self.path = path
        self.metadata = metadata
        self.config = config
        self._verified = dict(verified or {})

    @cached_property
    def system(self) -> System:
        return load_system(stored_config(self.metadata["config"]))

    @property
    def task(self) -> str:
        return str(self.metadata["task"])

    @property
    def dt(self) -> float:
        return float(self.metadata["dt"])

    @property
    def chunk_length(self) -> int:
        return int(self.metadata["chunk_length"])

    @property
    def contact_model(self) -> str | None:
        """The contact model that simulated the data (``None`` for recorded data).

        Datasets written before this was recorded were simulated with CM.
        """
        if self.metadata.get("source") != "simulated":
            return self.metadata.get("contact_model")
        return self.metadata.get("contact_model", "CM")

    @property
    def stride(self) -> int | None:
        """States between the starts of windows (the chunks); ``None``: one chunk per trajectory."""
        value = self.metadata.get("stride")
        return None if value is None else int(value)

    @property
    def parameters_known(self) -> bool:
        """Whether the config's physical parameters are the data's true ones.

        True for simulated data; for recorded data only when declared
        (``dataset_from_arrays(..., true_parameters=True)``).
        """
        if self.metadata.get("source") == "simulated":
            return True
        return bool(self.metadata.get("parameters_known", False))

    @property
    def noise_std(self) -> float:
        return float(self.metadata["noise_std"])

    @property
    def n_states(self) -> int:
        return int(self.metadata["n_states"])

    @property
    def counts(self) -> dict[str, int]:
        return {s: int(self.metadata[f"n_{s}"]) for s in SPLITS}

    def mismatch(self, model: Any, states: Tensor | None = None) -> str | None:
        """Why ``model`` cannot be scored on or refit to these data, or ``None``.

        What a model does not learn must match: the state shape, the time step, the
        contact geometry (every candidate's gap at the data's first states, under the
        model's ``config`` and the data's: walls, radii, limits) and the equality
        constraints (their values at those states: link lengths, pivots). Masses,
        friction, restitution and the potential may differ; those are what is learned.
        ``states``: ``(n, P, dim)`` positions of the data to compare at, where the caller
        has read some (default: the first states of the first non-empty split).
        """
        system = self.system
        shape = getattr(model, "state_shape", None)
        if shape is not None and tuple(shape) != tuple(system.state_shape):
            return (
                f"its states have shape {tuple(system.state_shape)} ({system.name}), the "
                f"model's {tuple(shape)}"
            )
        dt = getattr(model, "dt", None)
        if dt is not None and abs(float(dt) - system.dt) > 1e-9 * system.dt:
            return (
                f"the model steps at dt = {float(dt):g} s, the data are sampled every "
                f"{system.dt:g} s"
            )
        config = getattr(model, "config", None)
        if config is None:
            return None
        try:
            theirs = load_system(config)
        except (ValueError, TypeError):
            return None  # a model whose config is not a system's: nothing to compare
        x = None if states is None else states[:64].to(torch.float64)
        for name in SPLITS if x is None else ():
            if self.counts[name] > 0:
                x = self.split(name, dtype=torch.float64).traj[:64, 0, 0]  # (n, P, dim)
                break
        if x is None or x.shape[0] == 0:
            return None
        return structure_mismatch(system, theirs, x, "the data's system", "the model's")

    def __repr__(self) -> str:
        c = self.counts
        return (
            f"Dataset({str(self.path)!r}, task={self.task!r}, train={c['train']}, "
            f"val={c['val']}, test={c['test']}, states={self.n_states}, "
            f"chunk_length={self.chunk_length}, noise_std={self.noise_std:g})"
        )

    def _read_verified(self, path: Path) -> bytes:
        """The bytes of a split file, checked against their checksum (once)."""
        try:
            with open(path, "rb") as fh:
                before = _signature(os.fstat(fh.fileno()))
                data = fh.read()
                after = _signature(os.fstat(fh.fileno()))
        except OSError as err:
            raise DatasetError(f"cannot read {path}: {err}") from None
        known = self._verified.get(path.name)
        unchanged = known is not None and before == after == known
        if not unchanged and hashlib.sha256(data).hexdigest() != self.metadata["files"][path.name]:
            raise _checksum_error(path, self.path)
        return data

    def split(
        self,
        name: str,
        *,
        dtype: torch.dtype | None = None,
        device: torch.device | str | None = None,
    ) -> DataSplit:
        """Read split ``name`` (``"train"``, ``"val"`` or ``"test"``) as tensors.

        Args:
            name: the split.
            dtype: ``torch.float32`` or ``torch.float64`` (or their names), the dtype of
                ``traj`` and ``chunks`` (stored as float64); ``None``: float64.
            device: where to put the tensors.

        Raises:
            ValueError: an unknown split name or another ``dtype`` (an integer one had
                truncated the chunks, a string had given torch's ``TypeError``).
            DatasetError: the file is missing, fails its checksum or lacks an array.
        """
        if name not in SPLITS:
            raise ValueError(f"split must be one of {SPLITS}, got {name!r}")
        named = {"float32": torch.float32, "float64": torch.float64}
        dtype = named.get(dtype, dtype) if isinstance(dtype, str) else dtype
        if dtype is not None and dtype not in (torch.float32, torch.float64):
            raise ValueError(
                f"dtype must be torch.float32 or torch.float64 (or None: float64), got {dtype!r}"
            )
        path = self.path / f"{name}.npz"
        data = self._read_verified(path)
        try:
            wanted = ARRAYS + (WINDOW_ARRAYS if self.stride is not None else ())
            arrays, _ = read_npz(io.BytesIO(data), wanted)
        except _NPZ_ERRORS as err:
            raise DatasetError(
                f"{path} is not a readable .npz file (truncated or corrupted?): {one_line(err)}"
            ) from None
        missing = [key for key in wanted if key not in arrays]
        if missing:
            raise DatasetError(f"{path} lacks the arrays {missing}")
        N, T, L = self.counts[name], self.n_states, self.chunk_length
        shape = arrays["traj"].shape
        if "chunk_traj" not in arrays:
            arrays["chunk_traj"] = np.arange(N, dtype=np.int64)
        owner = arrays["chunk_traj"]
        M = owner.shape[0] if owner.ndim == 1 else -1
        chunk_shape = (M, L, *shape[2:])
        if (
            len(shape) != 5
            or shape[:3] != (N, T, 2)
            or arrays["chunks"].shape != chunk_shape
            or arrays["chunk_start"].shape != (M,)
            or arrays["chunk_has_contact"].shape != (M,)
            or (M > 0 and not (0 <= owner.min() and owner.max() < N))
        ):
            raise DatasetError(
                f"{path}: traj {shape} / chunks {arrays['chunks'].shape} / chunk_traj "
                f"{owner.shape} do not match the metadata (N={N}, T={T}, chunk_length={L})"
            )
        out = {key: torch.from_numpy(arrays[key]) for key in (*ARRAYS, "chunk_traj")}
        return DataSplit(name=name, **out).to(device=device, dtype=dtype)

    @property
    def train(self) -> DataSplit:
        return self.split("train")

    @property
    def val(self) -> DataSplit:
        return self.split("val")

    @property
    def test(self) -> DataSplit:
        return self.split("test")


def _not_a_folder(path: Path) -> str:
    """Why the file ``path`` is no dataset, and what to pass instead (one line)."""
    start = f"{path} is a file, not a dataset folder"
    if path.name == METADATA:
        return f"{start}: pass the folder that holds it, {path.parent}"
    if path.suffix in (".npz", ".npy"):
        return (
            f"{start}: a recording (trajectories 'traj', e.g. from `diffcontact simulate` or "
            f"`diffcontact convert`) becomes a dataset with `diffcontact generate "
            f"--from-arrays {path} --out DATASET_DIR` (docs/own-data.md)"
        )
    return f"{start} (one that `diffcontact generate` writes)"


def load_dataset(data_dir: str | os.PathLike[str]) -> Dataset:
    """Read a dataset folder written by ``generate_dataset`` or ``dataset_from_arrays``.

    Every file's sha256 is checked against ``metadata.json``.

    Raises:
        DatasetError (a ``ValueError``): the folder or a file is missing, ``data_dir``
            is a file (a recording's ``.npz`` names ``generate --from-arrays``), a
            checksum does not match, or the metadata is unreadable or of
            another format version.
    """
    folder = Path(data_dir)
    if folder.exists() and not folder.is_dir():
        raise DatasetError(_not_a_folder(folder))
    if not folder.is_dir():
        raise DatasetError(f"dataset folder {folder} does not exist")
    meta_path = folder / METADATA
    if not meta_path.is_file():
        unfinished = " (an interrupted run left it unfinished)" * (folder / MARKER).exists()
        raise DatasetError(
            f"{folder} has no {METADATA}: not a finished dataset{unfinished}; create one "
            "with `diffcontact generate`"
        )
    meta = read_metadata(folder)
    missing = [key for key in _REQUIRED if key not in meta]
    if missing:
        raise DatasetError(f"{meta_path} lacks the keys {missing}")
    if meta["format_version"] != FORMAT_VERSION:
        raise DatasetError(
            f"{meta_path}: format_version {meta['format_version']!r} is not supported "
            f"(this diffcontact reads version {FORMAT_VERSION})"
        )
    verified = verify_files(folder, meta)
    try:
        config = load_config(stored_config(meta["config"]))
    except ValueError as err:
        raise DatasetError(f"{meta_path}: invalid config: {err}") from None
    dt = meta["dt"]
    # (a hand-edited file, re-signed, had loaded: Dataset.dt and the system disagreed)
    if not _number(dt) or abs(float(dt) - config.dt) > 1e-12 * config.dt:
        raise DatasetError(
            f"{meta_path}: 'dt' is {dt!r}, but its config steps at dt = {config.dt:g} s: "
            "the two must agree (the file was edited); delete the folder and generate it again"
        )
    return Dataset(folder, meta, config, verified)


def _number(x: Any) -> bool:
    """A finite number (not a bool)."""
    return isinstance(x, int | float) and not isinstance(x, bool) and math.isfinite(x)


def structure_mismatch(
    ours: Any, theirs: Any, x: Tensor, name: str = "the first", other: str = "the second"
) -> str | None:
    """How two systems' known structure differs at positions ``x: (n, P, dim)``, or
    ``None``: the contact geometry (every candidate's gap: walls, radii, limits) and the
    equality constraints (their values: link lengths, pivots, rigid bodies). ``name`` and
    ``other`` name the two in the message."""
    with torch.no_grad():
        gaps, their_gaps = ours.gaps(x), theirs.gaps(x)
    if gaps.shape != their_gaps.shape:
        return f"{name} has {gaps.shape[-1]} candidate contacts, {other} {their_gaps.shape[-1]}"
    diff = float((gaps - their_gaps).abs().max()) if gaps.numel() else 0.0
    if diff > 1e-9 * (1.0 + float(gaps.abs().max())):
        return (
            f"the contact geometry differs (walls, radii or limits): the gaps of the states "
            f"differ by up to {diff:.3g} under {other} config"
        )
    both = (ours.constraints, theirs.constraints)
    cons = [c if c is None or c.num_equations else None for c in both]
    if (cons[0] is None) != (cons[1] is None):
        return "one of the two systems has equality constraints, the other none"
    if cons[0] is not None:
        with torch.no_grad():
            phi, their_phi = cons[0].phi(x), cons[1].phi(x)
        far = phi.shape != their_phi.shape or float((phi - their_phi).abs().max()) > 1e-9 * (
            1.0 + float(x.abs().max())
        )
        if far:
            return (
                "the equality constraints differ (link lengths, pivots or body shapes): the "
                f"data's states do not satisfy {other}"
            )
    return None
