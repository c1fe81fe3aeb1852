"""``evaluate()``: a learned model on the test set: metrics, plots and a GIF.

Protocol (paper-facts.md, "Training set-up"): from the first state of every
test trajectory, roll the model out for ``max(horizon, 100 dt)`` (that is
``max(horizon / dt, 100)`` states, ``steps = states - 1``) and compare with the
ground truth. When the stored test trajectories of a simulated dataset are
shorter than that (e.g. the rope, 20 states), the ground truth is simulated
from the same initial states with the true system (``load_system(config)``,
float64).

Recorded data (``generate --from-arrays``) has no ground truth but its
states: the rollout follows the recording (``T - 1`` steps by default, never
more), nothing is simulated, and unless the dataset declares the config's
parameters true (``--true-params``) the true parameters and the true energy
are unknown: ``null`` in ``metrics.json``, with the reason in ``unknown``, and
no true values in the plots.

The metrics are those of :mod:`~diffcontact.learning.evaluation.metrics`
(``docs/evaluation.md``); :func:`evaluate` writes ``metrics.json``,
``rollout.npz``, the plots of :mod:`~diffcontact.learning.evaluation.plots`,
``impacts.png`` (:mod:`~diffcontact.learning.evaluation.impacts`: observed vs
predicted normal velocity ratios of the first impact of each test trajectory)
and a GIF (:data:`OUTPUT_FILES`). It does not replace the files of another
evaluation (of another run or data set) without ``force``.
"""

from __future__ import annotations

import contextlib
import csv
import hashlib
import inspect
import json
import math
import os
import tempfile
import warnings
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import numpy as np
import torch

from diffcontact import __version__
from diffcontact.io import (
    atomic_save_npz,
    atomic_write_json,
    check_writable_folder,
    jsonable,
    parse_device,
    read_json_object,
)
from diffcontact.learning.data.format import load_dataset
from diffcontact.learning.evaluation.impacts import impact_ratios, impact_summary, plot_impacts
from diffcontact.learning.evaluation.log import find_training_log, read_training_log
from diffcontact.learning.evaluation.metrics import (
    as_numpy,
    energy_drifts,
    energy_scale,
    finite_mean,
    mean_ci95,
    relative_error,
    rollout_steps,
    true_energy,
    true_parameters,
)
from diffcontact.learning.evaluation.plots import plot_energy, plot_rel_error, plot_training
from diffcontact.systems.config import rollout_size_error

__all__ = [
    "METRICS_FORMAT_VERSION",
    "OUTPUT_FILES",
    "DivergedRolloutsWarning",
    "EvaluationInputError",
    "evaluate",
]

METRICS_FORMAT_VERSION = 2
"""2 (2026-11-28): ``impacts.n`` became ``n_found`` and ``n_predicted``,
``energy_rel_drift`` gained ``n``, and ``identity`` was added."""
OUTPUT_FILES = (
    "metrics.json", "rollout.npz", "rel_error.png", "energy.png", "training.png", "rollout.gif",
    "impacts.png",
)  # fmt: skip


class EvaluationInputError(ValueError):
    """Bad input to :func:`evaluate` (missing run, checkpoint, test data or config)."""


class DivergedRolloutsWarning(RuntimeWarning):
    """:func:`evaluate` left diverged rollouts out of its means (``n_nonfinite``)."""


# ---------------------------------------------------------------------------
# learned parameters
# ---------------------------------------------------------------------------


def _floats(value: Any) -> list[float] | None:
    if value is None:
        return None
    arr = as_numpy(value).reshape(-1)
    return [float(v) for v in arr]


def _learned(raw: Mapping[str, Any], n_bodies: int) -> dict[str, Any]:
    """Normalise ``model.learned_parameters()``: mass ratios ``m_i/m_1`` for i >= 2."""
    if not isinstance(raw, Mapping):
        raise EvaluationInputError(
            f"model.learned_parameters() must return a dict (mass_ratios, mu, cor, ...), "
            f"got {type(raw).__name__}"
        )

    def numbers(key: str) -> list[float] | None:
        try:
            return _floats(raw.get(key))
        except (TypeError, ValueError) as err:
            raise EvaluationInputError(
                f"model.learned_parameters()[{key!r}] must hold numbers: {err}"
            ) from None

    out: dict[str, Any] = {}
    ratios = numbers("mass_ratios")
    if ratios is None:
        mass = numbers("mass")
        ratios = [m / mass[0] for m in mass] if mass else None
    if ratios is not None and len(ratios) == n_bodies:
        # the model's list includes the first body (ratio 1): drop it
        ratios = [r / ratios[0] for r in ratios[1:]] if ratios[0] != 0 else ratios[1:]
    out["mass_ratios"] = ratios
    out["mu"] = numbers("mu")
    out["cor"] = numbers("cor")
    out["eps"] = numbers("eps")
    if out["eps"] is not None and len(out["eps"]) == 1:
        out["eps"] = out["eps"][0]
    return out


def _compare(
    learned: list[float] | None, true: list[float] | None, relative: bool
) -> dict[str, Any]:
    entry: dict[str, Any] = {"learned": learned, "true": true}
    key = "max_rel_error" if relative else "max_abs_error"
    if true is None:  # no known truth: nothing to compare with
        entry[key] = None
    elif learned is not None and len(learned) == len(true):
        if len(true) == 0:
            entry[key] = 0.0
        else:
            lv, tv = np.asarray(learned), np.asarray(true)
            diff = np.abs(lv - tv)
            if relative:
                diff = diff / np.abs(tv)
            entry[key] = float(diff.max())
    elif learned is not None and len(learned) == 1 and len(true) > 1:
        # one shared learned value against per-contact truth
        entry[key] = float(np.max(np.abs(np.asarray(true) - learned[0])))
    else:
        entry[key] = None
    return entry


# ---------------------------------------------------------------------------
# run directory, dataset and model
# ---------------------------------------------------------------------------


def _has_checkpoint(run_dir: Path) -> bool:
    if (run_dir / "model.pt").is_file():
        return True
    ckpts = run_dir / "checkpoints"
    return ckpts.is_dir() and any(ckpts.glob("*.ckpt"))


def _unfinished_checkpoint(run_path: Path, run: Mapping[str, Any]) -> tuple[Path, str]:
    """The checkpoint an evaluation of a run without ``model.pt`` scores, and the note
    that says so: ``checkpoints/last.ckpt``, else (missing or unreadable) the newest
    readable ``epochNNNN.ckpt``.

    Raises:
        EvaluationInputError: no readable checkpoint; one that would run code to load.
    """
    from diffcontact.learning.training.checkpoints import (
        LAST,
        epochs_done,
        newest_checkpoint,
    )

    folder = run_path / "checkpoints"
    try:
        path, ckpt, notes = newest_checkpoint(folder)
    except ValueError as err:  # (UnsafeFileError)
        raise EvaluationInputError(f"cannot load the model of {run_path}: {err}") from None
    if path is None:
        skipped = f" ({'; '.join(notes)})" if notes else ""
        raise EvaluationInputError(
            f"no trained model in {run_path}: no model.pt and no readable checkpoint in "
            f"{folder}{skipped}"
        )
    done = epochs_done(ckpt)
    total = run.get("epochs") if isinstance(run.get("epochs"), int) else None
    of = "" if total is None else f" of {total}"
    when = "" if done is None else f" after {done}{of} epochs"
    if path.name == LAST:
        what = f"its last checkpoint{when}"
    else:
        gone = "; ".join(notes) if notes else f"no {folder.name}/{LAST}"
        what = f"its newest epoch checkpoint, {folder.name}/{path.name}{when} ({gone})"
    if done is not None and total is not None and done >= total:
        # every epoch ran: model.pt was written, then deleted or moved
        refit = (
            ", before its refit (refit.json): not the refit's model"
            if (run_path / "refit.json").is_file()
            else ""
        )
        note = (
            f"{run_path} has no model.pt although its training finished: the file is missing "
            f"(deleted or moved?); this is {what}, the weights at the end of its training{refit}"
        )
    else:
        note = (
            f"{run_path} has no model.pt (its training did not finish): this is {what}, not a "
            "final model"
        )
    return path, note


def _resolve_data_dir(run_dir: Path | None, run: Mapping[str, Any], data_dir: Any) -> Path:
    if data_dir is not None:
        return Path(data_dir)
    value = run.get("data_dir")
    if not value:
        if run_dir is None:
            raise EvaluationInputError("no test data: give data_dir when there is no run directory")
        raise EvaluationInputError(
            f"no test data: {run_dir / 'run.json'} names no data_dir (pass --data DIR)"
        )
    path = Path(str(value))
    if path.is_absolute() or path.exists() or run_dir is None:
        return path
    near = run_dir / path  # relative to the run directory
    return near if near.exists() else path


def _model_label(model: Any, run: Mapping[str, Any]) -> str:
    for value in (getattr(model, "model_name", None), run.get("model")):
        if isinstance(value, str) and value:
            return value
        if isinstance(value, Mapping):
            name = value.get("model") or value.get("name")
            if isinstance(name, str) and name:
                return name
    return type(model).__name__


def _load_test(data_path: Path) -> tuple[np.ndarray, Any, Any]:
    """The test trajectories ``(N, T, 2, P, dim)``, the system and the dataset
    (its ``contact_model``, ``parameters_known`` and ``metadata["source"]``)."""
    if data_path.is_file():  # (it said "test data not found: DIR/test.npz/test.npz")
        raise EvaluationInputError(
            f"{data_path} is a file: pass the dataset folder that holds it (--data "
            f"{data_path.parent}); evaluate reads its test.npz and metadata.json"
        )
    if not data_path.is_dir():
        raise EvaluationInputError(
            f"test data not found: {data_path / 'test.npz'} (missing data directory; if the "
            "dataset moved, pass its folder with --data)"
        )
    try:
        dataset = load_dataset(data_path)
        traj = dataset.split("test", dtype=torch.float64).traj.numpy()
        system = dataset.system
    except ValueError as err:
        raise EvaluationInputError(f"cannot read the test data: {err}") from None
    if len(traj) == 0:
        raise EvaluationInputError(f"{data_path}: the test split holds no trajectory")
    if not np.isfinite(traj[:, 0]).all():
        raise EvaluationInputError(f"{data_path}/test.npz: the initial states contain NaN or inf")
    if tuple(traj.shape[2:]) != system.state_shape:
        raise EvaluationInputError(
            f"{data_path}/test.npz: states have shape {tuple(traj.shape[2:])}, but the system "
            f"{system.name} has {system.state_shape}"
        )
    return traj, system, dataset


def _same_path(recorded: Any, path: Path | None) -> bool:
    if recorded is None or path is None:
        return recorded is None and path is None
    return Path(str(recorded)).resolve() == path.resolve()


STARTED = ".evaluation-started.json"
"""Written (run and data) before an evaluation's first output file, removed after its
``metrics.json``: an evaluation stopped in between can be run again in its folder."""

_RESUME_FIELDS = ("data_dir", "data_checksum", "epochs", "resumed")
"""The fields of ``run.json`` a resume may rewrite (a moved dataset, more epochs)."""


def _relative(path: Path, out: Path) -> str:
    """``path`` relative to the output folder ``out`` (both resolved: independent of the
    working directory, and unchanged when a folder holding both moves)."""
    try:
        return Path(os.path.relpath(path.resolve(), out.resolve())).as_posix()
    except ValueError:  # (another drive)
        return path.resolve().as_posix()


def _identity(
    out: Path, run_path: Path | None, run: Mapping[str, Any], data_path: Path, dataset: Any
) -> dict[str, Any]:
    """What makes an evaluation in ``out`` the same as another (``metrics.json["identity"]``).

    ``run`` and ``data``: the run and data folders relative to ``out``; ``run_id``: a
    digest of ``run.json`` without the fields a resume rewrites (its ``created`` time
    stamp makes it the run's own; ``None`` for a ``run.json`` without one, or no run);
    ``data_checksum``: the dataset's metadata checksum (``metadata_sha256``, which covers
    its files).
    """
    from diffcontact.learning.data.format import METADATA_CHECKSUM, metadata_checksum

    run_id = None
    if run_path is not None and run.get("created"):
        fixed = {k: v for k, v in run.items() if k not in _RESUME_FIELDS}
        text = json.dumps(fixed, sort_keys=True, default=str)
        run_id = hashlib.sha256(text.encode()).hexdigest()
    meta = dataset.metadata
    return {
        "run": None if run_path is None else _relative(run_path, out),
        "run_id": run_id,
        "data": _relative(data_path, out),
        "data_checksum": meta.get(METADATA_CHECKSUM) or metadata_checksum(dict(meta)),
    }


def _same_evaluation(
    old: Mapping[str, Any], identity: Mapping[str, Any], run_path: Path | None, data_path: Path
) -> bool:
    """Whether ``old`` (a ``metrics.json`` or the marker) is an evaluation of the same run
    and data set: each the same folder (relative to the output folder) or the same run
    (``run_id``) and data (``data_checksum``), wherever they lie now."""
    then = old.get("identity")
    if not isinstance(then, Mapping):  # written before 2026-11-28: the paths as given
        return _same_path(old.get("run_dir"), run_path) and _same_path(
            old.get("data_dir"), data_path
        )

    def same(where: str, which: str) -> bool:
        if then.get(where) == identity[where]:  # (both None: no run directory)
            return True
        return then.get(which) is not None and then.get(which) == identity[which]

    no_run = then.get("run") is None or identity["run"] is None
    if no_run:
        run_ok = then.get("run") is None and identity["run"] is None
    else:
        run_ok = same("run", "run_id")
    return run_ok and same("data", "data_checksum")


def _check_out(
    out: Path,
    identity: Mapping[str, Any],
    run_path: Path | None,
    data_path: Path,
    force: bool,
) -> None:
    """Refuse to replace another evaluation's files in ``out`` (unless ``force``).

    Files of an evaluation of the same run and data set (re-evaluating, from any working
    directory, also after the folders moved: :func:`_same_evaluation`) are replaced; so
    is everything with ``force``.
    """
    present = [n for n in OUTPUT_FILES if (out / n).exists() or (out / n).is_symlink()]
    if not present or force:
        return
    old = None
    # metrics.json is written last; an evaluation stopped before it left its marker
    for name in ("metrics.json", STARTED):
        found = out / name
        if old is None and found.is_file() and not found.is_symlink():
            try:
                old = json.loads(found.read_text())
            except (OSError, UnicodeDecodeError, json.JSONDecodeError):
                old = None
    if isinstance(old, dict) and _same_evaluation(old, identity, run_path, data_path):
        return
    raise EvaluationInputError(
        f"{out} already holds {', '.join(present)} of another evaluation (or files not "
        "written by one): pass --force to replace them, or choose another --out"
    )


def _check_writable(out: Path) -> None:
    """Refuse an output folder where no file can be written, before anything is: tried
    with a file made and removed in ``out`` where it exists (permission bits say nothing
    for root or on read-only file systems), else checked on its nearest existing folder
    (made by :func:`_start`, which undoes it when the first file fails)."""
    try:
        check_writable_folder(out)
    except NotADirectoryError as err:  # "DIR exists and is not a folder", ...
        raise EvaluationInputError(f"output folder {err}") from None
    except OSError as err:
        raise EvaluationInputError(f"cannot write to the output folder {out}: {err}") from None
    try:
        if out.is_dir():
            fd, probe = tempfile.mkstemp(dir=out, prefix=".diffcontact-probe-")
            os.close(fd)
            os.unlink(probe)
    except OSError as err:
        why = err.strerror if isinstance(err.strerror, str) else str(err)
        raise EvaluationInputError(f"cannot write to the output folder {out}: {why}") from None


def _start(out: Path, started: Mapping[str, Any]) -> None:
    """Make ``out`` and write the marker :data:`STARTED`; a failure is bad input and
    leaves no folder behind that this call made."""
    made = []
    folder = out
    while not folder.exists() and folder != folder.parent:
        made.append(folder)
        folder = folder.parent
    try:
        out.mkdir(parents=True, exist_ok=True)
        atomic_write_json(out / STARTED, started)
    except OSError as err:
        for folder in made:  # (innermost first; only while empty)
            with contextlib.suppress(OSError):
                folder.rmdir()
        why = err.strerror if isinstance(err.strerror, str) else str(err)
        raise EvaluationInputError(f"cannot write to the output folder {out}: {why}") from None


def _check_model_fits(
    model: Any,
    dataset: Any,
    traj: np.ndarray,
    data_path: Path,
    run_model: tuple[Path, Mapping[str, Any], Path] | None = None,
) -> None:
    """Refuse a model that cannot be scored on the data (``Dataset.mismatch``).

    ``run_model``: ``(run directory, its run.json, the model file)`` for a model read from
    a run. When ``run.json`` says the run trained on these very data (their checksum),
    the model file is blamed: it is not the run's (copied from another run), rather than
    the run's own data being "data of another system".
    """
    from diffcontact.learning.data.format import METADATA_CHECKSUM, metadata_checksum

    why = dataset.mismatch(model, torch.as_tensor(traj[:64, 0, 0]))  # the test states, read
    if why is None:
        return
    name = getattr(model, "model_name", None) or type(model).__name__
    if run_model is not None:
        run_path, run, model_file = run_model
        meta = dataset.metadata
        checksum = meta.get(METADATA_CHECKSUM) or metadata_checksum(dict(meta))
        if run.get("data_checksum") == checksum:
            raise EvaluationInputError(
                f"{model_file} is not the model of the run {run_path} (copied from another "
                f"run?): run.json says the run trained on {data_path} ({dataset.task}), but "
                f"the model does not fit those data: {why} ({name})"
            )
    raise EvaluationInputError(f"{data_path}: {why} ({name}): data of another system")


# ---------------------------------------------------------------------------
# evaluate
# ---------------------------------------------------------------------------


def simulate_data_states(model: Any, z0: torch.Tensor, steps: int) -> Any:
    """``model.simulate(z0, steps)`` from states of the data, without the overlap check
    where the model's ``simulate`` takes ``check_overlap`` (the protocol's; a model that
    takes only ``(z0, steps)`` is called so): a recording may hold its states slightly
    penetrating (MuJoCo's soft contacts), and the contact model pushes such a state out
    as a step would."""
    try:
        takes = inspect.signature(model.simulate).parameters
    except (TypeError, ValueError):  # no signature to read (a builtin): as the protocol
        takes = {"check_overlap": None}
    known = "check_overlap" in takes or any(p.kind is p.VAR_KEYWORD for p in takes.values())
    if known:
        return model.simulate(z0, steps, check_overlap=False)
    return model.simulate(z0, steps)


def _rollouts(model: Any, z0: torch.Tensor, steps: int) -> tuple[np.ndarray, list[int]]:
    """``model.simulate(z0, steps)`` as numpy; a trajectory whose contact solve fails
    (``ConeQPError`` naming its states) or whose rollout diverges
    (:class:`~diffcontact.systems.NonFiniteRolloutError`) is left out and returned as
    NaN, so that it counts as diverged (``n_nonfinite``) instead of stopping the
    evaluation. Returns the rollouts and the trajectories whose contact solve failed.

    The states ``z0`` are the data's (a test trajectory's first state, a state before an
    impact), not a user's initial conditions: they are not checked for overlaps
    (:func:`simulate_data_states`)."""
    from diffcontact.contact import ConeQPError
    from diffcontact.systems import NonFiniteRolloutError

    keep = torch.arange(z0.shape[0], device=z0.device)
    failed: list[int] = []
    out = None
    while len(keep):
        try:
            out = simulate_data_states(model, z0[keep], steps)
            break
        except (ConeQPError, NonFiniteRolloutError) as err:
            if not err.states or (isinstance(err, ConeQPError) and len(keep) == len(err.states)):
                raise
            drop = torch.as_tensor(err.states, dtype=torch.long, device=z0.device)
            if isinstance(err, ConeQPError):
                failed += keep[drop].tolist()
            mask = torch.ones(len(keep), dtype=torch.bool, device=z0.device)
            mask[drop] = False
            keep = keep[mask]
    pred = np.full((z0.shape[0], steps + 1, *z0.shape[1:]), np.nan)
    if out is not None:
        out = as_numpy(out)
        expected = (len(keep), *pred.shape[1:])
        if out.shape != expected:  # (numpy's broadcast error before)
            raise EvaluationInputError(
                f"model.simulate returned shape {out.shape} for {len(keep)} states and "
                f"{steps} steps, expected {expected} (N, steps + 1, 2, P, dim)"
            )
        pred[keep.cpu().numpy()] = out
    return pred, sorted(failed)


def _uncertainty(model: Any, dataset: Any, wanted: bool) -> dict[str, Any] | None:
    """:func:`parameter_uncertainty` and contact regimes on the training chunks, or ``None``."""
    from diffcontact.learning.evaluation.uncertainty import (
        parameter_uncertainty,
        supports_uncertainty,
    )

    if not (wanted and supports_uncertainty(model)):
        return None
    try:
        chunks = dataset.split("train", dtype=torch.float64).chunks
    except ValueError:
        return None  # no training split: nothing to assess against
    if chunks.shape[0] == 0 or chunks.shape[1] < 2:
        return None
    from diffcontact.contact import ConeQPError

    try:
        return parameter_uncertainty(model, chunks)
    except (ValueError, ConeQPError) as err:  # e.g. a training chunk the model cannot roll out
        return {"error": f"parameter uncertainty not assessed: {err}"}


def _diverged_message(n_bad: int, n: int, n_failed: int = 0) -> str:
    """The warning of :func:`evaluate` on ``n_bad`` of ``n`` diverged rollouts
    (``n_failed`` of them stopped on a failed contact solve), on one line."""
    rollouts = "rollout" if n == 1 else "rollouts"
    solves = f" ({n_failed} on a failed contact solve)" if n_failed else ""
    return (
        f"{n_bad} of {n} test {rollouts} diverged (non-finite){solves}: left out of the "
        "means (n_nonfinite in metrics.json)"
    )


def evaluate(
    run_dir: str | os.PathLike[str] | None,
    out_dir: str | os.PathLike[str] | None = None,
    *,
    model: Any = None,
    data_dir: str | os.PathLike[str] | None = None,
    n_gif: int = 4,
    device: str = "cpu",
    steps: int | None = None,
    n_test: int | None = None,
    gif_frames: int = 40,
    force: bool = False,
    uncertainty: bool = True,
) -> dict[str, Any]:
    """Evaluate a learned model on the test set and write metrics, plots and a GIF.

    Args:
        run_dir: a training run (``run.json`` with ``data_dir``, ``model.pt`` or
            ``checkpoints/``, ``logs/``). May be ``None`` when ``model`` and
            ``data_dir`` (and ``out_dir``) are given.
        out_dir: where to write (default ``RUN_DIR/evaluation``; created).
        model: an object with ``simulate(z0, steps)`` (``(N, 2, P, dim)`` ->
            ``(N, steps + 1, 2, P, dim)``) and ``learned_parameters()`` (dict
            with ``mass_ratios``, ``mu``, ``cor``, optionally ``eps``); default
            the run's ``model.pt``, else (an unfinished run) its
            ``checkpoints/last.ckpt``, else its newest readable ``epochNNNN.ckpt``
            (``model_note`` says which).
        data_dir: the dataset (read with ``load_dataset``: checksums verified); default
            ``run.json``'s ``data_dir`` (as given, else relative to the run).
        n_gif: test trajectories in the GIF (0: no GIF; at most
            :data:`~diffcontact.viz.animation.MAX_PANELS`).
        device: ``"cpu"`` or ``"cuda"`` for the rollouts.
        steps: rollout steps (default ``max(horizon / dt, 100) - 1``; for
            recorded data ``T - 1``, the recorded steps, and at most that).
        n_test: use only the first ``n_test`` test trajectories.
        gif_frames: at most this many GIF frames (evenly subsampled from the rollout's
            states, the first and last included).
        force: replace the files of another evaluation in ``out_dir`` (one of
            another run or data set; those of the same run and data set are
            always replaced).
        uncertainty: assess how well the training data determine the learned
            mass ratios, ``mu`` and ``e_P`` (physical models only;
            :func:`~diffcontact.learning.evaluation.uncertainty.parameter_uncertainty`
            on the training chunks), written under ``uncertainty``.

    Returns:
        The metrics dict written to ``metrics.json`` (see ``docs/evaluation.md``).

    Warns:
        DivergedRolloutsWarning: (a ``RuntimeWarning``) some rollouts diverged
            (non-finite, or stopped on a failed contact solve): how many of how
            many, left out of the means (``n_nonfinite``).

    Raises:
        EvaluationInputError: missing run directory, checkpoint, test data or
            config; a model or data file that cannot be read, fails its
            checksum or would run code to load; ``out_dir`` holding another
            evaluation (without ``force``), or where no file can be written;
            bad arguments (``steps`` beyond the recorded states or beyond
            ``simulate``'s size limits); CUDA requested but unavailable; a model
            of another system than the data's (or, read from the run, not the
            run's own); a ``model`` without ``simulate``, whose rollouts have
            the wrong shape, or whose ``learned_parameters()`` is not a dict of
            numbers. All but the last two are raised before anything is written
            (the output folder is made only after these checks).
    """
    # ---- arguments and files
    from diffcontact.viz.animation import MAX_PANELS

    if not isinstance(n_gif, int) or isinstance(n_gif, bool) or not 0 <= n_gif <= MAX_PANELS:
        raise EvaluationInputError(
            f"n_gif must be an integer in [0, {MAX_PANELS}] (one GIF panel each), got {n_gif!r}"
        )
    if not isinstance(gif_frames, int) or isinstance(gif_frames, bool) or gif_frames < 1:
        raise EvaluationInputError(f"gif_frames must be a positive integer, got {gif_frames!r}")
    for name, value in (("steps", steps), ("n_test", n_test)):
        if value is not None and (
            not isinstance(value, int) or isinstance(value, bool) or value < 1
        ):
            raise EvaluationInputError(f"{name} must be a positive integer, got {value!r}")
    try:
        dev = parse_device(device)
    except ValueError as err:
        raise EvaluationInputError(str(err)) from None
    run_path = None if run_dir is None else Path(run_dir)
    run: dict[str, Any] = {}
    if run_path is not None:
        if run_path.is_file():
            raise EvaluationInputError(
                f"{run_path} is a file: give the run directory that holds it (evaluate reads "
                "its run.json, and model.pt or else its newest checkpoint)"
            )
        if not run_path.is_dir():
            raise EvaluationInputError(f"run directory {run_path} does not exist")
        if (run_path / "run.json").is_file():
            run = read_json_object(run_path / "run.json", "run file", EvaluationInputError)
        elif model is None:
            raise EvaluationInputError(f"{run_path} is not a training run (no run.json)")
        if model is None and not _has_checkpoint(run_path):
            raise EvaluationInputError(
                f"no trained model in {run_path}: expected model.pt or checkpoints/*.ckpt"
            )
    elif model is None:
        raise EvaluationInputError("give a run directory or a model")
    if model is not None:  # (an AttributeError from deep inside, after files were written)
        if not callable(getattr(model, "simulate", None)):
            raise EvaluationInputError(
                f"model must have a method simulate(z0, steps) (docs/evaluation.md); "
                f"{type(model).__name__} has none"
            )
    data_path = _resolve_data_dir(run_path, run, data_dir)
    traj, system, dataset = _load_test(data_path)
    recorded = dataset.metadata.get("source") != "simulated"
    known = dataset.parameters_known
    T_data = traj.shape[1]
    if recorded and steps is not None and steps > T_data - 1:
        raise EvaluationInputError(
            f"steps={steps}: the recorded test trajectories of {data_path} hold {T_data} "
            f"states, so at most {T_data - 1} steps can be compared (recorded data has no "
            "ground truth beyond the recording; nothing is simulated)"
        )
    dt = system.dt
    rollout_note = None
    if steps is None and recorded:
        steps = T_data - 1
        rollout_note = (
            f"the rollout follows the recorded data: {T_data} states per test trajectory, "
            f"{steps} steps ({steps * dt:g} s)"
        )
    steps = rollout_steps(system) if steps is None else steps
    if n_test is not None:
        traj = traj[:n_test]
    N = traj.shape[0]
    too_large = rollout_size_error(N, steps, system.state_shape, names=("steps=", "n_test="))
    if too_large:  # (simulate's limit, which stopped the rollout with exit status 1)
        raise EvaluationInputError(too_large)
    if out_dir is None:
        if run_path is None:
            raise EvaluationInputError("give out_dir when there is no run directory")
        out_dir = run_path / "evaluation"
    out = Path(out_dir)
    identity = _identity(out, run_path, run, data_path, dataset)
    _check_out(out, identity, run_path, data_path, force)
    _check_writable(out)

    # ---- model (read before the output folder is made: a bad one leaves nothing behind)
    model_note, from_run = None, None
    if model is None:
        from diffcontact.learning.models.storage import load_model

        model_file = run_path / "model.pt"
        if not model_file.is_file():  # a run still training, or interrupted
            model_file, model_note = _unfinished_checkpoint(run_path, run)
        try:
            model = load_model(model_file)
        except (FileNotFoundError, ValueError) as err:
            raise EvaluationInputError(f"cannot load the model of {run_path}: {err}") from None
        from_run = (run_path, run, model_file)
    if isinstance(model, torch.nn.Module):
        model = model.to(dev).eval()
    _check_model_fits(model, dataset, traj, data_path, from_run)
    _start(out, {"run_dir": None if run_path is None else str(run_path),
                 "data_dir": str(data_path), "identity": identity})  # fmt: skip

    # ---- rollouts
    z0 = torch.as_tensor(traj[:, 0], dtype=torch.float64, device=dev)
    with torch.no_grad():
        if traj.shape[1] >= steps + 1:
            true = traj[:, : steps + 1]
            source = "recorded test set" if recorded else "test set"
        else:  # simulated data only: its config is the truth
            true = as_numpy(system.simulate(z0, steps, contact_model=dataset.contact_model))
            source = "simulated (test trajectories shorter than the rollout)"
        pred, failed = _rollouts(model, z0, steps)
    if pred.shape != true.shape:
        raise EvaluationInputError(
            f"model.simulate returned shape {pred.shape}, expected {true.shape} "
            "(N, steps + 1, 2, P, dim)"
        )

    # ---- metrics
    err = relative_error(pred, true)  # (N, T)
    finite = np.isfinite(err).all(1)
    n_bad = int((~finite).sum())
    err_ok = err[finite]
    later = slice(1, None) if err.shape[1] > 1 else slice(None)  # step 0 is exact
    if len(err_ok):
        rel_mean, rel_ci = mean_ci95(err_ok[:, later].mean(1))
        curve_mean, curve_ci = mean_ci95(err_ok, axis=0)
    else:
        rel_mean = rel_ci = math.nan
        curve_mean = curve_ci = np.full(err.shape[1], np.nan)
    unknown: dict[str, str] = {}
    if known:
        E_pred, E_true = true_energy(system, pred), true_energy(system, true)
        scale = energy_scale(system, true)
        # the model's and the truth's drift over the same trajectories (those whose
        # rollout stayed finite; the truth's over all of them had been compared before)
        drift_pred, drift_true, rows = energy_drifts(E_pred, E_true, scale)
        gap = np.abs(E_pred - E_true) / scale if scale > 0 else np.full(E_pred.shape, np.nan)
        drift = {
            "pred": finite_mean(drift_pred[rows]),
            "true": finite_mean(drift_true[rows]),
            "n": int(rows.sum()),
        }
        energy_error: float | None = finite_mean(gap[rows])
        truth: dict[str, Any] | None = true_parameters(system)
    else:
        unknown["parameters"] = (
            "recorded data without declared true parameters: the config's masses, mu and "
            "e_P are placeholders, not the recorded system's values (declare them with "
            "`diffcontact generate --from-arrays ... --true-params` if they are known)"
        )
        unknown["energy"] = (
            "the true energy needs the true masses (and potential) of the recorded system, "
            "which are unknown"
        )
        drift = {"pred": None, "true": None, "n": None}
        energy_error, truth = None, None
    impacts = impact_ratios(  # the first impact of each trajectory
        system, model, true, dev, simulate=lambda z, n: _rollouts(model, z, n)[0]
    )
    uncertainty_result = _uncertainty(model, dataset, uncertainty)
    learned_fn = getattr(model, "learned_parameters", None)  # optional in the protocol
    learned = _learned(learned_fn() if callable(learned_fn) else {}, system.n_bodies)
    task = system.name
    label = _model_label(model, run)
    metrics: dict[str, Any] = {
        "format_version": METRICS_FORMAT_VERSION,
        "task": task,
        "model": label,
        "n_test": N,
        "n_nonfinite": n_bad,
        "solver_failures": failed,
        "steps": steps,
        "dt": dt,
        "duration": steps * dt,
        "ground_truth": source,
        "rollout_note": rollout_note,
        "model_note": model_note,
        "parameters_known": known,
        "unknown": unknown,
        "rel_err_mean": rel_mean,
        "rel_err_ci95": rel_ci,
        "rel_err_final": float(np.atleast_1d(curve_mean)[-1]),
        "rel_err_curve": {"mean": curve_mean, "ci95": curve_ci},
        "energy_rel_drift": drift,
        "energy_rel_error": energy_error,
        "mass_ratios": _compare(
            learned["mass_ratios"], truth and truth["mass_ratios"], relative=True
        ),
        "mu": _compare(learned["mu"], truth and truth["mu"], relative=False),
        "cor": _compare(learned["cor"], truth and truth["cor"], relative=False),
        "eps": learned["eps"],
        "uncertainty": uncertainty_result,
        "impacts": impact_summary(impacts),
        "contact_names": list(getattr(system, "contact_names", [])),
        "device": str(device),
        "run_dir": None if run_path is None else str(run_path),
        "data_dir": str(data_path),
        "identity": identity,
        "diffcontact_version": __version__,
    }

    # ---- files
    # from here the folder is rewritten: an earlier evaluation's metrics.json (written
    # last) would describe files it no longer holds if this one stopped half-way
    (out / "metrics.json").unlink(missing_ok=True)
    files = ["metrics.json", "rollout.npz"]
    energies = {"energy_pred": E_pred, "energy_true": E_true} if known else {}
    atomic_save_npz(
        out / "rollout.npz",
        compress=True,
        pred=pred,
        true=true,
        rel_err=err,
        **energies,
        t=np.arange(steps + 1, dtype=np.float64) * dt,
    )
    title = f"{task}: {label}"
    plot_rel_error(err_ok, dt, out / "rel_error.png", title, n_left_out=n_bad)
    files.append("rel_error.png")
    if known:
        plot_energy(E_pred, E_true, scale, dt, out / "energy.png", title)
        files.append("energy.png")
    if impacts["trajectory"].size:
        plot_impacts(impacts, out / "impacts.png", f"{title}: normal velocity ratio of impacts")
        files.append("impacts.png")
    log_path = None if run_path is None else find_training_log(run_path)
    metrics["log_note"] = None
    if log_path is not None:
        try:
            log = read_training_log(log_path)
        except (OSError, UnicodeDecodeError, csv.Error) as err:  # a side plot: not fatal
            log = None
            metrics["log_note"] = (
                f"training.png not drawn: {log_path} cannot be read ({type(err).__name__}: {err})"
            )
        # after a refit the model's parameters are not the log's last epoch: marked
        refit = learned if run_path and (run_path / "refit.json").is_file() else None
        path = out / "training.png"
        if log and plot_training(log, truth, system.n_bodies, path, title, refit=refit):
            files.append("training.png")
        elif log is not None:  # read, but nothing to draw (it was left out without a word)
            what = "no row" if not log else "no loss or learned parameter per epoch"
            metrics["log_note"] = (
                f"training.png not drawn: {log_path} holds {what} (truncated or empty?)"
            )
    if n_gif > 0:
        from diffcontact.viz import animate, scene_from_system

        k = min(n_gif, N)
        what = "recorded" if recorded else "truth"
        animate(
            true[:k],
            scene_from_system(system, title=f"{task}: {what} (filled) vs {label} (dashed)"),
            out / "rollout.gif",
            overlay=pred[:k],
            dt=dt,
            max_trajectories=k,
            max_frames=gif_frames,
            labels=("recorded" if recorded else "ground truth", label),
        )
        files.append("rollout.gif")
    for name in OUTPUT_FILES:  # an earlier evaluation's file that this one does not write
        if name not in files and name != "metrics.json":
            (out / name).unlink(missing_ok=True)
    metrics["files"] = sorted(files)
    metrics = jsonable(metrics)
    atomic_write_json(out / "metrics.json", metrics)
    (out / STARTED).unlink(missing_ok=True)
    if n_bad:  # (after the files: a filter that makes warnings errors leaves them whole)
        warnings.warn(
            _diverged_message(n_bad, N, len(failed)), DivergedRolloutsWarning, stacklevel=2
        )
    return metrics
