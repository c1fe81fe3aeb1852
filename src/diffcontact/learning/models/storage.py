"""Saving and loading any registered model: ``model.pt`` files and training checkpoints.

A model file holds ``format_version``, ``model_name`` (the registry name),
``config`` (the system config as JSON data), ``options`` (the model's
``options()``) and ``state_dict``; :func:`load_model` rebuilds the model with
the registry's factory and loads the weights. The physical CM/CMr models read
older formats through :meth:`LearnedModel.from_checkpoint`.

Loading never runs code: model files and checkpoints hold only tensors and
plain data (dicts, lists, strings, numbers) and are read by
:func:`load_torch_file` with ``torch.load(..., weights_only=True)``; a file
that needs anything else (a pickled object, a function) is refused with
:class:`UnsafeFileError`.
"""

from __future__ import annotations

import io
import os
import pickle
import re
import zipfile
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import torch

from diffcontact.cli_args import one_line
from diffcontact.io import atomic_write_bytes
from diffcontact.learning.models.registry import create_model, is_physical_model
from diffcontact.systems.config import stored_config

__all__ = [
    "UnsafeFileError",
    "load_model",
    "load_torch_file",
    "model_bytes",
    "model_checkpoint",
    "model_from_checkpoint",
    "model_spec",
    "save_model",
]

FORMAT_VERSION = 3  # the physical models' format history is in physical.py


class UnsafeFileError(ValueError):
    """A torch file that holds more than tensors and plain data: loading it could run code."""


def load_torch_file(path: str | os.PathLike[str], what: str, map_location: Any = "cpu") -> Any:
    """``torch.load(path, weights_only=True)``, with one-line errors naming ``what`` and the file.

    Raises:
        UnsafeFileError: the file needs more than tensors and plain data
            (unpickling it could execute code); it is not loaded.
        ValueError: the file is missing, truncated or not a torch file, or
            ``map_location`` (or the device the tensors were saved on) names a device
            this machine does not have (e.g. ``"cuda"`` without CUDA).
    """
    if Path(path).is_file() and not _is_empty(path) and not zipfile.is_zipfile(path):
        # torch.save writes zip archives (diffcontact's files all are); anything else went
        # to the legacy unpickler, whose refusal of random bytes read as "unsafe"
        raise ValueError(
            f"{what} {path} cannot be read (truncated or corrupted?): not a torch file"
        )
    try:
        return torch.load(path, map_location=map_location, weights_only=True)
    except pickle.UnpicklingError as err:  # what weights_only refuses: a global it does not allow
        found = re.search(r"WeightsUnpickler error: (.*?)(?: was not an allowed|\n|$)", str(err))
        detail = f" ({found.group(1).strip()})" if found else ""
        raise UnsafeFileError(
            f"{what} {path} holds objects other than tensors and plain data{detail}: loading "
            "it could run code, so it is refused (diffcontact writes only tensors and plain "
            "data; was the file made or changed by something else?)"
        ) from None
    except FileNotFoundError:
        raise ValueError(f"{what} {path} does not exist") from None
    except (RuntimeError, EOFError, OSError, zipfile.BadZipFile, ValueError, KeyError) as err:
        device = _missing_device(err)
        if device is not None:  # a good file, to be read onto a device this machine lacks
            raise ValueError(
                f"{what} {path} cannot be loaded with map_location={map_location!r}: "
                f"{device} (pass map_location='cpu')"
            ) from None
        reason = "it is empty" if _is_empty(path) else one_line(err).split(". ")[0]
        raise ValueError(
            f"{what} {path} cannot be read (truncated or corrupted?): {reason}"
        ) from None


def _missing_device(err: BaseException) -> str | None:
    """What ``torch.load``'s ``err`` says is missing when it failed because the tensors were
    to go to a device this machine lacks (``"CUDA is not available on this machine"``);
    ``None`` for any other error (torch's messages: ``torch.serialization._validate_device``).
    """
    if not isinstance(err, RuntimeError):
        return None
    text = str(err)
    found = re.search(r"deserialize object on an? (\w+) device but torch\.\w+\.is_avail", text)
    if found:
        return f"{found[1]} is not available on this machine"
    found = re.search(
        r"deserialize object on (\w+) device (\d+) but .*?device_count\(\) is (\d+)", text
    )
    if found:
        return f"{found[1]} device {found[2]} does not exist (this machine has {found[3]})"
    found = re.search(r"The (\w+) device module is not registered", text)
    if found:
        return f"{found[1]} is not available in this torch build"
    return None


def _is_empty(path: str | os.PathLike[str]) -> bool:
    try:
        return os.stat(path).st_size == 0
    except OSError:
        return False


def model_spec(model: Any) -> dict[str, Any]:
    """``{"model_name", "config", "options"}``: what rebuilds ``model`` without its weights.

    The one writer of a model's description: ``model.pt`` files and the
    training checkpoints' hyper-parameters both hold this dict, and
    :func:`model_from_checkpoint` is its one reader.
    """
    return {
        "model_name": model.model_name,
        "config": model.config.model_dump(mode="json"),
        "options": model.options(),
    }


def model_checkpoint(model: Any, format_version: int = FORMAT_VERSION) -> dict[str, Any]:
    """Everything :func:`model_from_checkpoint` needs, as plain data and tensors."""
    return {
        "format_version": format_version,
        **model_spec(model),
        "state_dict": {k: v.detach().cpu() for k, v in model.state_dict().items()},
    }


def model_from_checkpoint(data: Mapping[str, Any]) -> Any:
    """Rebuild a model from :func:`model_checkpoint`'s dict (dtype of the stored weights).

    Raises:
        ValueError: not a model file, or a model name that is not registered
            (register it before loading).
    """
    if not isinstance(data, Mapping) or "options" not in data or "config" not in data:
        raise ValueError("not a diffcontact model file: missing config or options")
    data = {**data, "config": stored_config(data["config"])}  # files of earlier versions
    named, option = data.get("model_name"), dict(data["options"]).get("model")
    if named is not None and option is not None and named != option:
        raise ValueError(
            f"its model_name {named!r} and its options' model {option!r} disagree: was it edited?"
        )
    name = named or option
    if name is None:
        raise ValueError("not a diffcontact model file: no model name")
    state = data.get("state_dict")
    if isinstance(state, Mapping):  # a hand-edited or diverged file: not loaded silently
        bad = [
            str(k)
            for k, v in state.items()
            if isinstance(v, torch.Tensor)
            and v.is_floating_point()
            and not bool(v.isfinite().all())
        ]
        if bad:
            raise ValueError(f"weights with NaN or infinite values: {', '.join(bad[:5])}")
    if is_physical_model(name):
        from diffcontact.learning.models.physical import LearnedModel

        return LearnedModel.from_checkpoint(data)
    version = data.get("format_version")
    if version is not None and version != FORMAT_VERSION:  # (None: a training checkpoint's)
        newer = isinstance(version, int) and version > FORMAT_VERSION
        raise ValueError(
            f"model file format {version!r} is not supported (this diffcontact reads format "
            f"{FORMAT_VERSION}{': written by a newer diffcontact' if newer else ''})"
        )
    model = create_model(name, data["config"], **dict(data["options"]))
    state = dict(data["state_dict"])
    floats = [v for v in state.values() if v.is_floating_point()]
    if floats:
        model.to(floats[0].dtype)
    model.load_state_dict(state)
    return model


def model_bytes(model: Any) -> bytes:
    """The bytes of ``model``'s model file (name, config, options, weights), as
    :func:`save_model` writes them (for writers that must know them first, e.g. to record
    their hash)."""
    checkpoint = model.checkpoint() if hasattr(model, "checkpoint") else model_checkpoint(model)
    buf = io.BytesIO()
    torch.save(checkpoint, buf)
    return buf.getvalue()


def save_model(model: Any, path: str | os.PathLike[str]) -> Path:
    """Write ``model`` (name, config, options, weights) to ``path`` atomically."""
    return atomic_write_bytes(path, model_bytes(model))


def load_model(run_dir: str | os.PathLike[str], map_location: Any = "cpu") -> Any:
    """The learned model of a training run, whatever its registered type.

    Args:
        run_dir: a run directory (``diffcontact train --out``): its ``model.pt``
            (written at the end of training) or, when that is missing (training
            still running or interrupted), its ``checkpoints/last.ckpt``; or
            the path of a ``model.pt``/``.ckpt`` file.
        map_location: as in ``torch.load``.

    Both are read with ``torch.load(..., weights_only=True)`` (:func:`load_torch_file`):
    loading never runs code from the file.

    Raises:
        UnsafeFileError: the file holds more than tensors and plain data (refused).
        ValueError: nothing loadable at ``run_dir``, a truncated or corrupted
            file, or an unregistered model.
    """
    path = Path(run_dir)
    if path.is_dir():
        candidates = [path / "model.pt", path / "checkpoints" / "last.ckpt"]
        found = [p for p in candidates if p.is_file()]
        if not found:
            raise ValueError(f"{path} holds neither model.pt nor checkpoints/last.ckpt")
        path = found[0]
    elif not path.is_file():
        raise ValueError(f"{path} does not exist")
    if path.suffix == ".ckpt":
        ckpt = load_torch_file(path, "checkpoint", map_location)
        hp = ckpt.get("hyper_parameters", {}) if isinstance(ckpt, dict) else {}
        if not isinstance(hp, dict) or "config" not in hp or "options" not in hp:
            raise ValueError(f"{path} is not a diffcontact training checkpoint")
        prefix = "model."
        state = {k[len(prefix) :]: v for k, v in ckpt["state_dict"].items() if k.startswith(prefix)}
        return _rebuilt(
            {
                "format_version": ckpt.get("diffcontact", {}).get("model_format"),
                "model_name": hp.get("model_name"),
                "config": hp["config"],
                "options": hp["options"],
                "state_dict": state,
            },
            path,
        )
    data = load_torch_file(path, "model file", map_location)
    return _rebuilt(data, path)


def _rebuilt(data: Any, path: Path) -> Any:
    """:func:`model_from_checkpoint` of ``path``'s contents; every failure a one-line
    ``ValueError`` naming the file (contents that do not fit together: a missing or
    misshapen weight, options of another model)."""
    try:
        return model_from_checkpoint(data)
    except ValueError as err:
        raise ValueError(f"{path}: {one_line(err)}") from None
    except (RuntimeError, TypeError, KeyError, AttributeError, IndexError) as err:
        raise ValueError(
            f"{path}: its contents do not fit together ({type(err).__name__}: "
            f"{one_line(err)[:300]}); was it edited, or written for another model?"
        ) from None
