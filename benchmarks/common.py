"""Pieces shared by the benchmarks: device sync, the machine description and checks of
the command-line arguments (argument types: ``diffcontact.cli_args``)."""

from __future__ import annotations

import argparse
import os
import platform
import statistics
import time
from pathlib import Path

import torch


def check_tasks(ap: argparse.ArgumentParser, option: str, tasks) -> None:
    """``ap.error`` (exit status 2) unless every name in ``tasks`` is a built-in task."""
    from diffcontact.systems import list_tasks

    known = list_tasks()
    if unknown := [t for t in tasks if t not in known]:
        ap.error(f"{option}: unknown task(s) {', '.join(unknown)}; choose from {', '.join(known)}")


def check_device(ap: argparse.ArgumentParser, device: str) -> None:
    """``ap.error`` for ``--device cuda`` without a CUDA device."""
    if device == "cuda" and not torch.cuda.is_available():
        ap.error("--device cuda: no CUDA device available")


def settings(args: argparse.Namespace, default: dict, quick: dict | None = None) -> dict:
    """The suite's settings: ``quick`` (with ``--quick``) or ``default``, where every
    option given on the command line (not ``None`` in ``args``) wins over the preset."""
    chosen = dict(quick if quick is not None and args.quick else default)
    for key in chosen:
        if getattr(args, key, None) is not None:
            chosen[key] = getattr(args, key)
    return chosen


def sync(device: str) -> None:
    if device == "cuda":
        torch.cuda.synchronize()


def median_time(fn, device: str, reps: int) -> float:
    """Median seconds of ``reps`` calls of ``fn()`` (the device synchronised around each)."""
    times = []
    for _ in range(reps):
        sync(device)
        t0 = time.perf_counter()
        fn()
        sync(device)
        times.append(time.perf_counter() - t0)
    return statistics.median(times)


def machine_header(device: str, dtype: torch.dtype) -> list[str]:
    """Python, library versions, CPU (and GPU) and where/in what dtype ours runs."""
    cpu = platform.processor() or platform.machine()
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                cpu = line.split(":", 1)[1].strip()
                break
    except OSError:
        pass
    versions = [f"torch {torch.__version__}"]
    for mod in ("numpy", "cvxpy", "cvxpylayers", "diffcp", "clarabel", "lightning"):
        try:
            versions.append(f"{mod} {__import__(mod).__version__}")
        except Exception:  # a missing package is not an error here
            versions.append(f"{mod} -")
    lines = [
        f"Python {platform.python_version()} ({platform.python_implementation()}), "
        + ", ".join(versions),
        f"CPU: {cpu}; {os.cpu_count()} logical cores; torch threads {torch.get_num_threads()}",
    ]
    if device == "cuda":
        lines.append(f"GPU: {torch.cuda.get_device_name()}")
    lines.append(f"diffcontact on {device} in {str(dtype).replace('torch.', '')}")
    return lines


READ_FREE_HELP = (
    "run the position projection read-free in step-by-step rollouts that pad their "
    "contacts (CUDA; on the CPU, the CUDA path column): all its iterations, padded rows, "
    "no read of the device (diffcontact.systems.rollout._projects_read_free; a captured "
    "step always does)"
)


SPARSE_GRAM_CUDA_HELP = (
    "on CUDA, let the rope's position projection and contact impulse take J J^T from the "
    "rows' entries (diffcontact.geometry.sparse_gram, a Warp kernel) instead of the dense "
    "rows, as they do on the CPU (sparse_gram.DEVICES; not the default on CUDA until "
    "timed there)"
)


CONTACT_ROWS_HELP = (
    "the contact impulse of point masses from the dense J_C or from the rows' sparse "
    "entries (diffcontact.geometry.sparse_contact), wherever the structure allows; auto "
    "(default): the library's rule (systems.system.SPARSE_CONTACT_COLUMNS, "
    "sparse_gram.MIN_DENSE_SIZE)"
)


def choose_contact_rows(mode: str) -> None:
    """For the rest of the process: the contact impulse of point masses from the dense
    ``J_C`` (``"dense"``), from the rows' sparse entries wherever the structure allows
    (``"sparse"``), or by the library's size rule (``"auto"``)."""
    from diffcontact.systems import system

    if mode == "dense":
        system.SPARSE_CONTACT_COLUMNS = 1 << 62
    elif mode == "sparse":
        system.SPARSE_CONTACT_COLUMNS = 0
        system.MIN_DENSE_SIZE = 0


WARP_BLOCK_DIM_HELP = (
    "threads per block of the fused solver's CUDA launches (default: "
    "diffcontact.contact.fused.CUDA_BLOCK_DIM; each value is a module Warp compiles, or "
    "loads from its kernel cache: benchmarks/warp_aot.py)"
)


WARP_SCRATCH_HELP = (
    "layout of the fused solver's scratch memory on CUDA (default: "
    "diffcontact.contact.fused.CUDA_SCRATCH): the thread index fastest, each thread's "
    "arrays in one block, or that for the C x C matrices only"
)


def choose_warp_scratch(value: str | None) -> None:
    """For the rest of the process: the layout of the fused solver's scratch on CUDA."""
    if value is not None:
        from diffcontact.contact import fused

        fused.CUDA_SCRATCH = value


def choose_warp_block_dim(value: int | None) -> None:
    """For the rest of the process: the fused solver's threads per block on CUDA."""
    if value is not None:
        from diffcontact.contact import fused

        fused.CUDA_BLOCK_DIM = value


def choose_sparse_gram_cuda(on: bool) -> None:
    """With ``on``, the position projection uses ``sparse_gram`` on CUDA as well, for the
    rest of the process (``diffcontact.geometry.sparse_gram.DEVICES``)."""
    if on:
        from diffcontact.geometry import sparse_gram

        sparse_gram.DEVICES.add("cuda")


def choose_read_free_projection(on: bool) -> None:
    """With ``on``, step-by-step rollouts that pad their contacts (on CUDA) run the position
    projection read-free for the rest of the process (the choice
    ``diffcontact.systems.rollout._projects_read_free`` makes, off by default)."""
    if on:
        from diffcontact.systems import rollout

        rollout._projects_read_free = lambda device: True
