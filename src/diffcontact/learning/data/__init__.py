"""Datasets: simulated or recorded trajectories, chunked for training (``docs/data.md``).

- :mod:`.format`: the folder format, :func:`load_dataset` (its one reader,
  checksums verified), :class:`Dataset`, :class:`DataSplit`;
- :mod:`.generate`: :func:`generate_dataset` simulates a task's train/val/test
  trajectories;
- :mod:`.arrays`: :func:`dataset_from_arrays` writes the same format from
  trajectories recorded elsewhere;
- :mod:`.convert`: converters from positions only (finite differences) and from
  generalised coordinates; :mod:`.mujoco`: from MuJoCo ``qpos``/``qvel``
  (``docs/own-data.md``); :mod:`.convert_cli`: ``diffcontact convert``;
- :mod:`.chunks`: :func:`contact_states`, :func:`contact_flags` (recorded data:
  gaps, velocity jumps of impacts between samples, given flags and event times),
  :func:`select_chunks` (one chunk per trajectory, starting out of contact),
  :func:`window_chunks` (every window); :mod:`.noise`: :func:`add_chunk_noise`;
- :mod:`.write`: folder checks and atomic writing; :mod:`.checks`: argument checks;
- :mod:`.cli`: ``diffcontact generate`` (no torch at import).

Names are imported lazily, so ``diffcontact.learning.data.cli`` loads no torch.
"""

from __future__ import annotations

from diffcontact.learning._lazy import lazy_exports

_FORMAT = "diffcontact.learning.data.format"
_EXPORTS: dict[str, str] = {
    "ARRAYS": _FORMAT,
    "FORMAT_VERSION": _FORMAT,
    "METADATA": _FORMAT,
    "SPLITS": _FORMAT,
    "DataSplit": _FORMAT,
    "Dataset": _FORMAT,
    "DatasetError": _FORMAT,
    "load_dataset": _FORMAT,
    "split_seeds": _FORMAT,
    "add_chunk_noise": "diffcontact.learning.data.noise",
    "contact_flags": "diffcontact.learning.data.chunks",
    "contact_states": "diffcontact.learning.data.chunks",
    "impact_intervals": "diffcontact.learning.data.chunks",
    "window_chunks": "diffcontact.learning.data.chunks",
    "select_chunks": "diffcontact.learning.data.chunks",
    "dataset_from_arrays": "diffcontact.learning.data.arrays",
    "finite_difference_velocities": "diffcontact.learning.data.convert",
    "trajectories_from_coordinates": "diffcontact.learning.data.convert",
    "trajectories_from_mujoco": "diffcontact.learning.data.mujoco",
    "trajectories_from_positions": "diffcontact.learning.data.convert",
    "trajectory_checks": "diffcontact.learning.data.convert",
    "velocity_jumps": "diffcontact.learning.data.convert",
    "generate_dataset": "diffcontact.learning.data.generate",
    "register_cli": "diffcontact.learning.data.cli",
    "run_generate_cli": "diffcontact.learning.data.cli",
}

__all__ = sorted(_EXPORTS)

__getattr__, __dir__ = lazy_exports(__name__, _EXPORTS)
