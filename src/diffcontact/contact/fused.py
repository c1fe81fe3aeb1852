"""Solver backends of :func:`~diffcontact.contact.solve_cone_qp`: which one runs, and the
fused (NVIDIA Warp) one.

``SolverSettings.backend`` picks the backend:

- ``"torch"``: the reference implementation, batched torch operations
  (:func:`diffcontact.contact.interior_point.interior_point_solve` and
  :func:`diffcontact.contact.cone_qp._polish`); thousands of small operations per call;
- ``"warp"``: the same algorithm fused into Warp kernels, one thread per problem
  (:mod:`diffcontact.contact.warp_kernels`), on the CPU or a CUDA device; needs
  ``pip install diffcontact[warp]`` (``warp-lang``). :class:`FusedConeQP` runs a whole
  ``solve_cone_qp`` call (equilibration, scaling, fast paths, interior point, polish,
  retries, unboundedness certificate, status, input checks) as one kernel launch and its
  backward pass as another: about a dozen torch operations per call (allocations), and
  one host synchronisation (reading the kernel's error flags). Each launch replays one
  recorded for the call's signature with new pointers (:class:`_Recorded`: tens of
  microseconds less per call than packing Warp's arguments anew), and on the CPU a large
  batch is split into ranges of problems launched on several cores at once
  (:func:`_parts`; Warp runs a CPU launch on one core) where splitting has recently
  been faster than one core (measured as calls run, :func:`_run_parts`). Two shortcuts
  of the kernel that the reference does not take (results equal to its tolerance, tests in
  ``tests/contact/test_fused_solver.py``): each problem is solved only up to its last
  active contact (the simulator pads at the end; trailing inactive contacts are
  decoupled, with zero impulse and gradient), and a problem without a fast path (several
  contacts) first tries ``2 polish_steps`` Newton steps from zero, kept where they end
  at a point where the natural map is differentiable with a regular Jacobian, i.e. at
  the unique minimiser (``warp_kernels._at_a_kink``, ``cone_qp``'s docstring); the interior
  point solves the others (on BP5 nearly all multi-contact problems finish without it;
  ``SolverStatus.iterations`` counts the interior point's iterations). Each Newton system
  is solved reduced to the contacts that press, in per-contact bases of the projection's
  range (``warp_kernels._reduced_factor``): separating and padded contacts, and in 2D the
  normal of each sliding contact's ray, drop out of the factorisation, which for d <= 2 is
  a Cholesky one; a factorisation is reused while the projection's derivative is
  unchanged. On the CPU each calling thread keeps its forward workspace between calls
  (:data:`_KEEP_WORKSPACE_BYTES`, :func:`release_workspace`). :func:`solve` and
  :func:`polish` run the interior point and the polish alone on rows that the torch
  code of ``cone_qp._forward`` selected (that function with ``backend="warp"``; tests
  use it to look inside the algorithm);
- ``"auto"`` (default): the environment variable ``DIFFCONTACT_SOLVER`` (``torch``,
  ``warp`` or ``auto``) if it is set, else Warp where it is installed, the device is the
  CPU or CUDA and the solve runs in float32 or float64, else torch. Inside a
  ``torch.func`` transform (``grad``, ``jacrev``, ``vmap``) ``"auto"`` is torch: the
  Warp backend's autograd Functions do not support the transforms, and asking for Warp
  there is a ``ValueError`` that says so.

Warp is imported (and initialised, with its console messages silenced) on the first solve
that uses it, so the torch backend costs no import time. Its kernels are compiled on the
first call for each float type (a few seconds on a CPU) and cached on disk (Warp's kernel
cache, ``~/.cache/warp``).
"""

from __future__ import annotations

import collections
import contextlib
import ctypes
import functools
import importlib.util
import io
import os
import re
import sys
import tempfile
import threading
import time
import warnings
from types import ModuleType
from typing import TYPE_CHECKING

import torch
from torch import Tensor

from diffcontact.contact.first_order import first_order_only

if TYPE_CHECKING:
    from diffcontact.contact.cone_qp import SolverSettings
    from diffcontact.contact.interior_point import InteriorPointResult

BACKENDS = ("auto", "torch", "warp")
ENV_VAR = "DIFFCONTACT_SOLVER"
INSTALL_HINT = "pip install diffcontact[warp]"


@functools.cache
def warp_installed() -> bool:
    """Whether ``warp`` can be found (it is not imported)."""
    return importlib.util.find_spec("warp") is not None


def _env_backend() -> str | None:
    value = os.environ.get(ENV_VAR, "").strip().lower()
    if not value:
        return None
    if value not in BACKENDS:
        raise ValueError(
            f"environment variable {ENV_VAR}={os.environ[ENV_VAR]!r}: expected one of "
            f"{', '.join(BACKENDS)}"
        )
    return value


def _in_func_transform() -> bool:
    """Whether a ``torch.func`` transform (``grad``, ``jacrev``, ``vmap``, ...) is active."""
    active = getattr(torch._C, "_are_functorch_transforms_active", None)
    return bool(active()) if active is not None else False


def resolve_backend(backend: str, dtype: torch.dtype, device: torch.device | None) -> str:
    """The backend that solves: ``"torch"`` or ``"warp"`` (see the module docstring).

    Args:
        backend: ``SolverSettings.backend``.
        dtype: the dtype the solve runs in (``compute_dtype``).
        device: the inputs' device (``None``: not known, taken as supported).

    Raises:
        ValueError: an unknown name, or ``"warp"`` for a dtype or device it cannot run.
        ImportError: ``"warp"`` asked for (by the setting or the environment variable)
            but Warp is not installed.
    """
    if backend not in BACKENDS:
        raise ValueError(f"solver backend must be one of {', '.join(BACKENDS)}, got {backend!r}")
    explicit = backend != "auto"
    if backend == "auto":
        backend = _env_backend() or "auto"
    if backend == "torch":
        return "torch"
    if _in_func_transform():
        if backend == "auto":
            return "torch"
        where = "SolverSettings(backend='warp')" if explicit else f"{ENV_VAR}=warp"
        raise ValueError(
            f"{where}: the Warp solver does not support torch.func transforms (grad, jacrev, "
            "vmap); use backend='torch' or 'auto' there"
        )
    supported_dtype = dtype in (torch.float32, torch.float64)
    kind = "cpu" if device is None else torch.device(device).type
    if backend == "auto":
        usable = warp_installed() and supported_dtype and kind in ("cpu", "cuda")
        if usable and _warp_loads() and (kind == "cpu" or _warp_cuda()):
            return "warp"
        return "torch"
    where = "SolverSettings(backend='warp')" if explicit else f"{ENV_VAR}=warp"
    if not warp_installed():
        raise ImportError(
            f"{where} needs NVIDIA Warp, which is not installed: {INSTALL_HINT} "
            "(or pip install warp-lang), or use backend='torch'"
        )
    if not supported_dtype:
        raise ValueError(f"{where}: the Warp solver runs in float32 or float64, not {dtype}")
    if kind not in ("cpu", "cuda"):
        raise ValueError(f"{where}: the Warp solver runs on the CPU or CUDA, not {device}")
    try:
        _load()
    except Exception as err:
        raise ImportError(f"{where}: NVIDIA Warp is installed but failed to load: {err}") from err
    if kind == "cuda" and not _warp_cuda():
        raise RuntimeError(
            f"{where}: Warp cannot use CUDA on this machine (no driver, or too old a one); "
            "use backend='torch' for CUDA tensors"
        )
    return "warp"


@functools.cache
def _warp_cuda() -> bool:
    """Whether Warp can launch CUDA kernels here."""
    wp, _ = _load()
    return bool(wp.is_cuda_available())


@functools.cache
def _warp_loads() -> bool:
    """Whether Warp imports and initialises (``auto`` falls back to torch, with a warning,
    where it does not)."""
    try:
        _load()
    except Exception as err:  # a broken install must not break the default backend
        warnings.warn(
            f"diffcontact: NVIDIA Warp is installed but failed to load ({err!r}); "
            "solve_cone_qp uses its torch backend",
            RuntimeWarning,
            stacklevel=4,
        )
        return False
    return True


_NO_DRIVER = re.compile(r"cuda[ _]driver|libcuda", re.IGNORECASE)


@contextlib.contextmanager
def _quiet_init():
    """Drop Warp's notices about a missing CUDA driver, printed on machines without a GPU
    driver (where torch has no CUDA device either) by its native library on file
    descriptor 2 and, by older versions, as a warning on ``sys.stdout``; anything else
    printed is kept."""
    out = io.StringIO()
    try:
        fd = sys.stderr.fileno()
    except (AttributeError, OSError, ValueError):
        fd = None
    sys.stderr.flush()
    saved = None if fd is None else os.dup(fd)
    with tempfile.TemporaryFile() as err:
        if saved is not None:
            os.dup2(err.fileno(), fd)
        try:
            with contextlib.redirect_stdout(out):
                yield
        finally:
            sys.stderr.flush()
            if saved is not None:
                os.dup2(saved, fd)
                os.close(saved)
            err.seek(0)
            for text, stream in (
                (err.read().decode(errors="replace"), sys.stderr),
                (out.getvalue(), sys.stdout),
            ):
                if text and not (_NO_DRIVER.search(text) and not torch.cuda.is_available()):
                    stream.write(text)


@functools.cache
def _load() -> tuple[ModuleType, ModuleType]:
    """Import and initialise Warp (quietly) and the kernels' module."""
    import warp as wp

    wp.config.quiet = True  # Warp < 1.10
    if hasattr(wp, "LOG_WARNING"):
        wp.config.log_level = wp.LOG_WARNING  # no "Module ... load" lines
    with _quiet_init():
        wp.init()
    from diffcontact.contact import warp_kernels

    return wp, warp_kernels


# every kernel of warp_kernels that the solver launches
KERNELS = ("fused_solve", "fused_polish", "fused_forward", "fused_backward")


def _kernel(name: str, dtype: torch.dtype):
    """Kernel ``name`` of :mod:`~diffcontact.contact.warp_kernels` instantiated for one
    float type (launching a concrete overload skips Warp's per-launch type inference)."""
    return _overloads(dtype)[name]


@functools.cache
def _overloads(dtype: torch.dtype) -> dict:
    """Every kernel's overload for one float type, registered together.

    Warp compiles a whole module at its first launch on a device, with the overloads
    registered by then; registering one more later changes the module and compiles all of
    it again. Registering the four kernels of a dtype at once makes that one compilation
    per dtype and device (the CUDA compiler takes minutes for this module)."""
    import typing

    wp, kernels = _load()
    scalar = wp.float64 if dtype == torch.float64 else wp.float32
    out = {}
    for name in KERNELS:
        kernel = getattr(kernels, name)
        types = {}
        for arg in kernel.adj.args:
            if wp.types.is_array(arg.type) and arg.type.dtype is typing.Any:
                types[arg.label] = wp.array(dtype=scalar, ndim=arg.type.ndim)
            elif arg.type is typing.Any:
                types[arg.label] = scalar
        out[name] = wp.overload(kernel, types)
    return out


class _Polished:
    """The polish's outputs for n threads, and the scratch memory of the kernels."""

    def __init__(self, n: int, C: int, d: int, dtype: torch.dtype, device: torch.device):
        from diffcontact.contact.warp_kernels import N_SLOTS

        def scratch(*shape: int) -> Tensor:
            # the thread index varies fastest on CUDA (coalesced), slowest on the CPU
            if device.type == "cuda":
                out = torch.empty(*shape[1:], shape[0], dtype=dtype, device=device)
                return out.movedim(-1, 0)
            return torch.empty(*shape, dtype=dtype, device=device)

        self.n, self.C, self.d = n, C, d
        self.vec, self.V, self.LU = scratch(n, N_SLOTS, C), scratch(n, C, C), scratch(n, C, C)
        self.f = torch.empty(n, C, dtype=dtype, device=device)
        self.res = torch.empty(n, dtype=dtype, device=device)
        self.P = torch.empty(n, C, d, dtype=dtype, device=device)
        self.dmu = torch.empty(n, C, dtype=dtype, device=device)
        self.dl = torch.empty(n, C, dtype=dtype, device=device)
        self.piv = torch.empty(n, C, dtype=torch.int32, device=device)

    def scratch_args(self) -> list[Tensor]:
        return [self.vec, self.V]

    def output_args(self) -> list[Tensor]:
        return [self.f, self.res, self.P, self.dmu, self.dl, self.LU, self.piv]

    def result(self) -> tuple[Tensor, ...]:
        """``(f (n, C), residual (n,), P (n, K, d, d), dmu (n, K, d), dl (n, K, d), LU (n,
        C, C), pivots (n, C) int32)``, as :func:`~diffcontact.contact.cone_qp._polish`."""
        n, K, d = self.n, self.C // self.d, self.d
        return (
            self.f,
            self.res,
            self.P.view(n, K, d, d),
            self.dmu.view(n, K, d),
            self.dl.view(n, K, d),
            self.LU,
            self.piv,
        )


# Threads per block of a CUDA launch. A thread solves one problem, and a rollout's batch
# holds a few thousand: Warp's default of 256 would put 4096 problems in 16 blocks, on 16
# of an H100's or H200's 132 multiprocessors, the rest idle (benchmarks/README.md,
# 2026-11-28, eleventh sitting). Each value is a variant of the compiled module (Warp
# compiles it on the first launch with that value).
CUDA_BLOCK_DIM = 32


#: Layout of the forward kernel's scratch memory on CUDA: ``"strided"`` (the thread index
#: varies fastest, so the threads of a warp read adjacent words while they run the same
#: branch), ``"contiguous"`` (each thread's arrays in one block, as on the CPU: a thread
#: left alone in a branch, such as the interior point, reads from few cache lines) or
#: ``"matrices"`` (the C x C arrays contiguous, the vectors strided). All give bitwise the
#: same results. ``python benchmarks/run.py chain --device cuda`` times them; until it has
#: run on a GPU, the default stays the layout of the measurements in benchmarks/README.md.
CUDA_SCRATCH = "strided"
SCRATCH_LAYOUTS = ("strided", "contiguous", "matrices")
_MATRICES = frozenset(("Am", "Aipm", "M", "V"))  # the workspace's C x C arrays


def _scratch_layout(device: torch.device) -> str:
    """The layout of the forward kernel's scratch on ``device`` (``"contiguous"`` on the
    CPU)."""
    if CUDA_SCRATCH not in SCRATCH_LAYOUTS:
        raise ValueError(
            f"fused.CUDA_SCRATCH must be one of {SCRATCH_LAYOUTS}, got {CUDA_SCRATCH!r}"
        )
    return CUDA_SCRATCH if device.type == "cuda" else "contiguous"


def block_dim(device: torch.device) -> int | None:
    """Threads per block of a launch on ``device`` (``None``: Warp's default, the CPU's)."""
    return CUDA_BLOCK_DIM if device.type == "cuda" else None


def _launch(name: str, n: int, arrays_in, scalars, arrays_out, device: torch.device) -> None:
    """Launch kernel ``name`` on n threads, on torch's current stream."""
    wp, _ = _load()
    args = [wp.from_torch(x.contiguous(), return_ctype=True) for x in arrays_in]
    args += scalars
    args += [wp.from_torch(x, return_ctype=True) for x in arrays_out]
    _run(name, n, args, arrays_out[0].dtype, device)


def _scalar(dtype: torch.dtype):
    wp, _ = _load()
    return wp.float64 if dtype == torch.float64 else wp.float32


def solve(
    rows: Tensor,
    ipm_data: tuple[Tensor, ...],
    data: tuple[Tensor, ...],
    d: int,
    gap: float,
    settings: SolverSettings,
) -> tuple[InteriorPointResult, tuple[Tensor, ...]]:
    """Interior point and polish of the problems ``rows`` in one Warp kernel launch.

    The counterpart of the reference's ``interior_point_solve`` followed by ``_polish``
    (:func:`diffcontact.contact.cone_qp._solve`).

    Args:
        rows: (n,) int64 indices of the problems to solve.
        ipm_data: the scaled interior-point problem ``(A (B, C, C), b (B, C), mu, lower,
            apex (B, K), active (B, K) bool)``.
        data: the polish's problem ``(A (B, C, C), b (B, C), mu (B, K), lower (B, K),
            rho (B,), reg (B,), c (B,))``.
        d: contact dimension.
        gap: the interior point's gap target.
        settings: resolved :class:`~diffcontact.contact.SolverSettings`.

    Returns:
        ``(ipm, polished)``: an :class:`~diffcontact.contact.interior_point.
        InteriorPointResult` of the rows (its ``f`` scaled, as the reference's) and what
        :func:`polish` returns.
    """
    from diffcontact.contact.interior_point import InteriorPointResult

    A = data[0]
    dtype, device = A.dtype, A.device
    n, C, K = rows.numel(), A.shape[-1], data[2].shape[-1]
    scalar, finfo = _scalar(dtype), torch.finfo(dtype)
    out = _Polished(n, C, d, dtype, device)
    f_ipm = torch.empty(n, C, dtype=dtype, device=device)
    iterations = torch.empty(n, dtype=torch.int64, device=device)
    solved = torch.empty(n, dtype=torch.bool, device=device)
    unbounded = torch.empty(n, dtype=torch.bool, device=device)
    scalars = [
        d,
        K,
        scalar(gap),
        settings.max_iter,
        scalar(min(settings.polish_tol, settings.tol)),
        settings.polish_steps,
        scalar(1e10),  # the interior point's blow-up bound, as the reference's
        scalar(finfo.eps),
        scalar(finfo.tiny),
        scalar(float("inf")),
    ]
    arrays_in = [rows.to(torch.int32), *ipm_data, *data]
    arrays_out = [*out.scratch_args(), f_ipm, *out.output_args()]
    arrays_out += [iterations, solved, unbounded]
    _launch("fused_solve", n, arrays_in, scalars, arrays_out, device)
    return InteriorPointResult(f_ipm, solved, unbounded, iterations), out.result()


def polish(f: Tensor, rows: Tensor, data: tuple[Tensor, ...], settings: SolverSettings):
    """The natural-map polish of the problems ``rows`` from ``f`` (n, C) in one Warp
    kernel launch: the counterpart of :func:`diffcontact.contact.cone_qp._polish`.

    Args:
        f: (n, C) starting points, one per row.
        rows: (n,) int64 indices of the problems.
        data: the polish's problem for the whole batch, as in :func:`solve`.
        settings: resolved :class:`~diffcontact.contact.SolverSettings`.

    Returns:
        ``(f (n, C), residual (n,), P (n, K, d, d), dmu (n, K, d), dl (n, K, d), LU (n, C,
        C), pivots (n, C) int32)`` at the polished point, as ``_polish`` returns them.
    """
    A = data[0]
    dtype, device = A.dtype, A.device
    n, C, K = rows.numel(), A.shape[-1], data[2].shape[-1]
    d = C // K
    scalar = _scalar(dtype)
    out = _Polished(n, C, d, dtype, device)
    target = scalar(min(settings.polish_tol, settings.tol))
    eps = scalar(torch.finfo(dtype).eps)
    scalars = [d, K, target, settings.polish_steps, eps]
    arrays_in = [rows.to(torch.int32), f, *data]
    _launch("fused_polish", n, arrays_in, scalars, out.scratch_args() + out.output_args(), device)
    return out.result()


# --- the whole call in two kernels ------------------------------------------------------


class _Layout:
    """Arrays carved out of one byte buffer (one torch allocation), as Warp descriptors.

    In the ``"strided"`` layout, arrays of two or more dimensions (the first is the thread
    index) have that index fastest (the threads of a CUDA warp read adjacent words), in
    ``"matrices"`` all but the C x C matrices (:data:`_MATRICES`); else it is slowest
    (:data:`CUDA_SCRATCH`)."""

    def __init__(self, dtype: torch.dtype, device: torch.device, layout: str = "contiguous"):
        self.item = torch.finfo(dtype).bits // 8
        self.layout = layout
        self.device = device
        self.specs: list[tuple[str, tuple[int, ...], int, int]] = []
        self.nbytes = 0

    def add(self, name: str, shape: tuple[int, ...], item: int | None = None) -> None:
        item = item or self.item
        self.nbytes = -(-self.nbytes // 16) * 16
        self.specs.append((name, shape, item, self.nbytes))
        size = item
        for s in shape:
            size *= s
        self.nbytes += size

    def allocate(self) -> Tensor:
        return torch.empty(max(self.nbytes, 16), dtype=torch.uint8, device=self.device)

    def arrays(self, base: int) -> dict:
        """Warp descriptors of the arrays of a buffer starting at address ``base``."""
        from warp._src.types import array_t

        out = {}
        for name, shape, item, offset in self.specs:
            strided = self.layout == "strided" or (
                self.layout == "matrices" and name not in _MATRICES
            )
            if strided and len(shape) > 1:
                rows, rest = shape[0], shape[1:]
                strides = [rows * item] * len(rest)
                for i in range(len(rest) - 2, -1, -1):
                    strides[i] = strides[i + 1] * rest[i + 1]
                strides = (item, *strides)
            else:
                strides = [item] * len(shape)
                for i in range(len(shape) - 2, -1, -1):
                    strides[i] = strides[i + 1] * shape[i + 1]
            out[name] = array_t(base + offset, 0, len(shape), shape, tuple(strides))
        return out


def _ctype(x: Tensor):
    """A tensor as a Warp array descriptor (any strides; no gradient)."""
    from warp._src.types import array_t

    item = x.element_size()
    shape = tuple(x.shape)
    return array_t(x.data_ptr(), 0, len(shape), shape, tuple(s * item for s in x.stride()))


@functools.lru_cache(maxsize=64)
def _saved_layout(n: int, C: int, d: int, dtype: torch.dtype, device: torch.device) -> _Layout:
    from diffcontact.contact.warp_kernels import SV_P

    saved = _Layout(dtype, device)
    saved.add("sv", (n, SV_P + d, C))
    saved.add("LU", (n, C, C))
    saved.add("piv", (n, C), 4)
    saved.add("scratch", (n, 2, C))  # the backward pass's
    return saved


def _run(name: str, n: int, args: list, dtype: torch.dtype, device: torch.device) -> None:
    """Launch kernel ``name`` (its ``dtype`` overload) on n threads with Warp's arguments
    ``args``, on torch's current stream."""
    wp, _ = _load()
    stream = None
    if device.type == "cuda":
        stream = wp.stream_from_torch(torch.cuda.current_stream(device))
    wp.launch(
        _kernel(name, dtype),
        dim=n,
        inputs=args,
        device=wp.device_from_torch(device),
        stream=stream,
        block_dim=block_dim(device),
    )


# ``check_inputs``: A counts as positive semi-definite where, on its active contacts, A plus
# this times max |A_ij| times I has a Cholesky factorisation (both backends; generous
# enough for the rounding of a singular A built in float32)
SEMIDEFINITE_TOL = 3e-4

# what the forward kernel's flags say (entry 5: some problem did not converge; the others
# are ``solve_cone_qp``'s input errors, in the order the reference raises them)
FLAGS = (
    "A contains NaN or infinite values",
    "b contains NaN or infinite values",
    "mu contains NaN or infinite values",
    "lower contains NaN or infinite values",
    "warm_start contains NaN or infinite values",
    None,
    "mu must be >= 0 (friction coefficients)",
    "lower must be >= 0",
    "A must be symmetric",
    "A must be positive semi-definite (a negative eigenvalue: A + "
    f"{SEMIDEFINITE_TOL:g} max|A_ij| I on the active contacts has no Cholesky factorisation)",
)


# the flags in the order the torch backend checks their conditions (warm_start last), so
# that a call with several faults names the same one on both backends
_FLAG_ORDER = (0, 1, 2, 3, 6, 7, 8, 9, 4)


def input_error(flags: list[int]) -> str | None:
    """The message of the first input error the forward kernel flagged (in the torch
    backend's order of checks), or None."""
    for i in _FLAG_ORDER:
        if flags[i]:
            return "solve_cone_qp: " + FLAGS[i]
    return None


class _Recorded:
    """One kernel launch recorded for one call signature and replayed with new data
    pointers: the arrays' strides and trailing shapes and the scalar arguments are those
    of the recording, so a replay costs a pointer store per array and no argument packing
    (tens of microseconds per call on a CPU).

    ``dynamic`` lists ``(argument index, rows per problem)`` of the arrays whose pointer
    changes per call; where rows per problem is not 0 their leading size is that times the
    number of problems n, which a replay may change (with the scalar argument ``n_arg``)
    as long as the strides do not depend on n. The kernel's argument ``first_arg`` is the
    first problem of the launch: a replay may cover a range of the problems."""

    def __init__(self, name: str, n: int, args: list, dynamic, dtype, device, n_arg, first_arg):
        wp, _ = _load()
        self.cmd = wp.launch(
            _kernel(name, dtype),
            dim=n,
            inputs=args,
            device=wp.device_from_torch(device),
            record_cmd=True,
            block_dim=block_dim(device),
        )
        # params[0] is the launch bounds; the array descriptors are patched in place (on
        # CUDA the launch reads them through addresses taken at recording)
        self.slots = [self.cmd.params[i + 1] for i, _ in dynamic]
        self.rows = [rows for _, rows in dynamic]
        self.n, self.dim, self.first = n, n, args[first_arg]
        self.n_arg, self.first_arg = n_arg, first_arg
        self.device = device
        self.args = None
        hooks = getattr(self.cmd, "hooks", None)
        if device.type == "cpu" and self.cmd.block_dim <= 1 and not self.cmd.adjoint and hooks:
            # on the CPU, call the compiled kernel with one argument structure kept here,
            # patched in place, instead of Warp copying every argument into a new one per
            # launch (what Launch.launch does: a third of a small launch's time)
            self.labels = [arg.label for arg in self.cmd.kernel.adj.args]
            values = self.cmd.params[1 : len(self.labels) + 1]
            fields = [(label, type(v)) for label, v in zip(self.labels, values, strict=True)]
            self.args = type("Args", (ctypes.Structure,), {"_fields_": fields})(*values)
            self.slots = [getattr(self.args, self.labels[i]) for i, _ in dynamic]
            self.forward = hooks.forward

    def _set(self, index: int, value: int) -> None:
        self.cmd.set_param_at_index(index, value)
        if self.args is not None:
            setattr(self.args, self.labels[index], value)

    def __call__(self, n: int, pointers: list[int], first: int = 0, count: int | None = None):
        """Run problems ``first, ..., first + count - 1`` (default: all n) of the arrays at
        ``pointers`` (one per dynamic array, in order)."""
        count = n if count is None else count
        if n != self.n:
            if self.n_arg is not None:
                self._set(self.n_arg, n)
            for slot, rows in zip(self.slots, self.rows, strict=True):
                if rows:
                    slot.shape[0] = rows * n
            self.n = n
        if count != self.dim:
            self.cmd.set_dim(count)
            self.dim = count
        if first != self.first:
            self._set(self.first_arg, first)
            self.first = first
        for slot, pointer in zip(self.slots, pointers, strict=True):
            slot.data = pointer
        if self.args is not None:
            self.forward(ctypes.byref(self.cmd.params[0]), ctypes.byref(self.args))
            return
        stream = None
        if self.device.type == "cuda":
            wp, _ = _load()
            stream = wp.stream_from_torch(torch.cuda.current_stream(self.device))
        self.cmd.launch(stream)


# recorded launches of this thread (a replay patches the recording: one per thread), by
# call signature, the most recently used last
_RECORDED = threading.local()
_MAX_RECORDED = 32
_RECORD_LOCK = threading.Lock()
# On the CPU (where launches are synchronous) each calling thread keeps one forward
# workspace, grown as needed up to this size, instead of allocating one per call: a fresh
# allocation of this size comes from the operating system, and every page the kernel then
# touches for the first time costs a page fault (at 30 contacts a large share of the
# solve's time). Only the pages a solve touches take memory; release_workspace()
# frees the buffer.
_KEEP_WORKSPACE_BYTES = 1 << 30
_LOCAL = threading.local()

# a problem without a fast path (several contacts) first tries this many times
# ``polish_steps`` Newton steps from zero, then the interior point (warp_kernels._solve_row)
FIRST_STEPS_FACTOR = 2


def _recorded(key: tuple, record) -> _Recorded:
    """The recorded launch of ``key`` in this thread, made by ``record()`` if missing."""
    cache = getattr(_RECORDED, "cache", None)
    if cache is None:
        cache = _RECORDED.cache = collections.OrderedDict()
    launch = cache.get(key)
    if launch is None:
        with _RECORD_LOCK:  # (Warp loads a kernel's module on its first launch: once)
            launch = cache[key] = record()
        if len(cache) > _MAX_RECORDED:
            cache.popitem(last=False)
    else:
        cache.move_to_end(key)
    return launch


def _signature(n: int, device: torch.device, *xs: Tensor) -> tuple:
    """What a recording depends on: the arrays' strides and trailing sizes, and n on CUDA
    (where the scratch layouts' strides depend on it)."""
    return (n if device.type == "cuda" else None, *((x.shape[1:], x.stride()) for x in xs))


def _as(x: Tensor, dtype: torch.dtype) -> Tensor:
    """``x.to(dtype)``, without the call when it is one already (a microsecond per call)."""
    return x if x.dtype == dtype else x.to(dtype)


@functools.lru_cache(maxsize=64)
def _workspace_layout(n: int, C: int, K: int, dtype, device, layout: str) -> _Layout:
    """The forward kernel's scratch memory of n problems (two rows per problem), in
    ``layout`` (:func:`_scratch_layout`)."""
    from diffcontact.contact.warp_kernels import N_SC, N_SLOTS

    ws = _Layout(dtype, device, layout)
    rows = 2 * n
    ws.add("diag0", (rows, C))
    for name in ("Am", "Aipm", "M", "V"):
        ws.add(name, (rows, C, C))
    ws.add("vec", (rows, N_SLOTS, C))
    for name in ("b0", "bm", "bipm"):
        ws.add(name, (rows, C))
    for name in ("mu0", "lower0", "mum", "lowerm", "muipm", "loweripm", "apex"):
        ws.add(name, (rows, K))
    ws.add("sc", (rows, N_SC))
    ws.add("piv", (rows, C), 4)
    ws.add("act", (rows, K), 1)
    return ws


_WS_NAMES = (
    "diag0 Am Aipm M V vec b0 bm bipm mu0 lower0 mum lowerm muipm loweripm apex sc piv act".split()
)
_SAVED_NAMES = ("sv", "LU", "piv", "scratch")


def _record_forward(
    inputs, outputs, n, d, warm: bool, settings: SolverSettings, layout: str
) -> _Recorded:
    """Record ``fused_forward`` for the call signature of ``inputs`` (A, b, mu, lower,
    active, warm start) and ``outputs`` (f, residual, iterations, converged, unbounded,
    flags). A replay takes the pointers of the inputs, the outputs (f to unbounded), the
    saved buffer's sv, LU and piv, the flags and the workspace's arrays."""
    A, b = inputs[0], inputs[1]
    work, device = A.dtype, A.device
    C = b.shape[-1]
    K = C // d
    scalar, finfo = _scalar(work), torch.finfo(work)
    eps = finfo.eps
    ws = _workspace_layout(n, C, K, work, device, layout)
    saved = _saved_layout(n, C, d, work, device)
    w, s = ws.arrays(0), saved.arrays(0)  # (a replay sets the pointers)
    args = [_ctype(x) for x in inputs]
    n_arg = len(args)
    args += [n, 0, d, K, int(warm), int(settings.check_inputs), 2]
    args += [settings.retries, settings.max_iter]
    args += [settings.polish_steps, FIRST_STEPS_FACTOR * settings.polish_steps]
    args.append(int(settings.canonical))
    args += [
        scalar(x)
        for x in (
            settings.gap,
            min(settings.polish_tol, settings.tol),
            settings.tol,
            settings.kkt_reg,
            1e10,  # the interior point's blow-up bound, as the reference's
            eps,
            finfo.tiny,
            float("inf"),
            1e3,  # cone_qp._EQUILIBRATE_ABOVE
            eps**0.375,  # the Tikhonov term of cone_qp._unbounded
            1e2,
            1e-2 / settings.tol,
            -1e3 * eps * C,
            eps**0.5,
        )
    ]
    first_ws = len(args)
    args += [w[k] for k in _WS_NAMES]
    first_out = len(args)
    args += [_ctype(x) for x in outputs[:5]]
    args += [s[k] for k in _SAVED_NAMES[:3]] + [_ctype(outputs[5])]
    dynamic = [(i, 1) for i in range(6)]
    dynamic += [(i, 1) for i in range(first_out, len(args) - 1)] + [(len(args) - 1, 0)]
    dynamic += [(i, 2) for i in range(first_ws, first_out)]
    return _Recorded("fused_forward", n, args, dynamic, work, device, n_arg, n_arg + 1)


def _workspace_pointers(ws: _Layout):
    """The workspace's array pointers, and the buffer to keep alive until the launch
    returns: on the CPU this thread's kept buffer (see :data:`_KEEP_WORKSPACE_BYTES`),
    else a new one (CUDA's caching allocator reuses memory by itself)."""
    if ws.device.type != "cpu" or ws.nbytes > _KEEP_WORKSPACE_BYTES:
        buf = ws.allocate()
    else:
        buf = getattr(_LOCAL, "workspace", None)
        if buf is None or buf.numel() < ws.nbytes:
            _LOCAL.workspace = None  # (free the old buffer first)
            buf = _LOCAL.workspace = ws.allocate()
    base = buf.data_ptr()
    return [base + offset for *_, offset in ws.specs], buf


def release_workspace() -> None:
    """Free the calling thread's kept CPU workspace of the fused solver (the next solve
    allocates a new one)."""
    _LOCAL.workspace = None


# --- the batch split over CPU cores ----------------------------------------------------------

# a CPU launch runs its problems one after another on one core; a batch with at least this
# many problems times C^2 per part is split into parts launched on several cores at once
# (about half a millisecond of work per part), as many as torch.get_num_threads() allows
_SPLIT_WORK = 1 << 12


@functools.cache
def _cores() -> int:
    from diffcontact.threads import available_cores

    return available_cores()


@functools.cache
def _pool(workers: int):
    from concurrent.futures import ThreadPoolExecutor

    return ThreadPoolExecutor(max_workers=workers, thread_name_prefix="diffcontact-warp")


def _parts(n: int, C: int, device: torch.device) -> list[tuple[int, int]]:
    """``(first, count)`` ranges of the n problems, one per core that a CPU launch of this
    size is worth splitting over (one range on CUDA, where a launch fills the device)."""
    if device.type != "cpu":
        return [(0, n)]
    parts = min(torch.get_num_threads(), _cores(), n * C * C // _SPLIT_WORK)
    if parts <= 1:
        return [(0, n)]
    bounds = [n * i // parts for i in range(parts + 1)]
    return [(bounds[i], bounds[i + 1] - bounds[i]) for i in range(parts)]


# Whether to split is measured as calls run: a split pays on an idle machine and costs where
# another process (or torch's OpenMP threads, spinning after an operation) holds a core.
# For each kind of launch (kernel and problem size) each call runs the mode (split or one
# core) with the lower recent time per problem (exponential averages), and every
# _PROBE_EVERY-th call the other mode, so that a change of load is noticed: a busy machine
# gets the one-core time, not a multiple of it.
_PROBE_EVERY = 32
_EMA = 0.3
_split_state: dict = {}


def _run_parts(run, parts: list[tuple[int, int]], kind: tuple) -> None:
    """``run(first, count)`` for every part: the first on this thread, the others on the
    pool's at the same time (a Warp CPU launch releases the GIL); the first error raised.
    Runs the whole range on this thread instead where that has recently been faster for
    launches of this ``kind`` (see :data:`_PROBE_EVERY`). Results are bitwise the same
    either way."""
    if len(parts) == 1:
        run(*parts[0])
        return
    try:
        state = _split_state[kind]
    except KeyError:
        state = _split_state[kind] = {"calls": 0, "split": None, "single": None}
    state["calls"] += 1
    split, single = state["split"], state["single"]
    # the first call splits, the second runs on one core, then the faster; probes after
    prefer_split = split is None or (single is not None and split <= single)
    use_split = prefer_split != (state["calls"] % _PROBE_EVERY == 0)
    total = sum(count for _, count in parts)
    start = time.perf_counter()
    if use_split:
        futures = [_pool(_cores() - 1).submit(run, *part) for part in parts[1:]]
        try:
            run(*parts[0])
        finally:
            for future in futures:
                future.result()
    else:
        run(parts[0][0], total)
    cost = (time.perf_counter() - start) / total
    key = "split" if use_split else "single"
    state[key] = cost if state[key] is None else (1 - _EMA) * state[key] + _EMA * cost


class FusedConeQP(torch.autograd.Function):
    """``solve_cone_qp`` on flat inputs with the Warp backend: the forward pass is one kernel
    (``fused_forward``), the backward pass one more (``fused_backward``), each a replay of
    a launch recorded for the call's signature (:class:`_Recorded`).

    Inputs: ``A`` (n, C, C), ``b`` (n, C), ``mu``, ``lower`` (n, K), ``active`` (n, K) bool,
    ``warm_start`` (n, C) or None, ``d``, resolved settings. Outputs: ``f`` (n, C) in the
    input dtype, and the status ``converged``, ``unbounded`` (n,) bool, ``iterations`` (n,)
    int64, ``residual`` (n,) in the compute dtype, and ``flags`` (len(FLAGS),) int32, 1 where a
    problem shows the condition of :data:`FLAGS` (not differentiable)."""

    @staticmethod
    def forward(ctx, A, b, mu, lower, active, warm_start, d: int, settings: SolverSettings):
        work = settings.compute_dtype
        in_dtype, device = A.dtype, A.device
        A, b, mu, lower = (_as(x, work) for x in (A, b, mu, lower))
        n, C = b.shape
        warm = b if warm_start is None else _as(warm_start.detach(), work)
        inputs = (A, b, mu, lower, active, warm)
        f = torch.empty(n, C, dtype=work, device=device)
        res = torch.empty(n, dtype=work, device=device)
        iterations = torch.empty(n, dtype=torch.int64, device=device)
        converged = torch.empty(n, dtype=torch.bool, device=device)
        unbounded = torch.empty(n, dtype=torch.bool, device=device)
        flags = torch.zeros(len(FLAGS), dtype=torch.int32, device=device)
        outputs = (f, res, iterations, converged, unbounded, flags)
        sig = _signature(n, device, *inputs)
        layout = _scratch_layout(device)
        key = ("forward", d, work, device, warm_start is None, settings, sig, layout)

        def record() -> _Recorded:
            return _record_forward(inputs, outputs, n, d, warm_start is not None, settings, layout)

        saved = _saved_layout(n, C, d, work, device)
        keep = saved.allocate()
        base = keep.data_ptr()
        pointers = [x.data_ptr() for x in inputs] + [x.data_ptr() for x in outputs[:5]]
        pointers += [base + offset for *_, offset in saved.specs[:3]]
        pointers.append(flags.data_ptr())
        ws = _workspace_layout(n, C, C // d, work, device, layout)
        parts = _parts(n, C, device)
        # one workspace, shared by the parts where the batch is split (each problem has
        # its own rows)
        ws_pointers, work_buf = _workspace_pointers(ws)
        pointers += ws_pointers
        if len(parts) == 1:
            _recorded(key, record)(n, pointers)
        else:
            _run_parts(
                lambda first, count: _recorded(key, record)(n, pointers, first, count),
                parts,
                ("forward", C, d, work),
            )
        del work_buf
        f = _as(f, in_dtype)
        # f: the output, which carries the graph a second derivative would go through
        # (first_order_only); saved, never an attribute (no reference cycle)
        ctx.save_for_backward(keep, f)
        ctx.shape = (n, C, d)
        ctx.dtypes = (in_dtype, work)
        ctx.mark_non_differentiable(converged, unbounded, iterations, res, flags)
        ctx.set_materialize_grads(False)
        return f, converged, unbounded, iterations, res, flags

    @staticmethod
    @first_order_only
    def backward(ctx, grad_f, *_):
        if grad_f is None:  # f took no part in the loss
            return None, None, None, None, None, None, None, None
        keep, _ = ctx.saved_tensors
        n, C, d = ctx.shape
        K = C // d
        in_dtype, work = ctx.dtypes
        device = keep.device
        grad_f = _as(grad_f, work)
        want_A, want_mu = ctx.needs_input_grad[0], ctx.needs_input_grad[2]
        grad_b = torch.empty(n, C, dtype=work, device=device)
        grad_l = torch.empty(n, K, dtype=work, device=device)
        grad_A = torch.empty(n, C, C, dtype=work, device=device) if want_A else None
        grad_mu = torch.empty(n, K, dtype=work, device=device) if want_mu else None
        saved = _saved_layout(n, C, d, work, device)
        outputs = (grad_A, grad_b, grad_mu if want_mu else grad_l, grad_l)

        def record() -> _Recorded:
            s = saved.arrays(0)  # (a replay sets the pointers)
            args = [_ctype(grad_f), s["sv"], s["LU"], s["piv"], d, K, int(want_A), int(want_mu)]
            args += [0, s["scratch"]]
            args += [s["LU"] if grad_A is None else _ctype(grad_A), _ctype(grad_b)]
            args += [_ctype(outputs[2]), _ctype(grad_l)]
            dynamic = [(i, 1) for i in (0, 1, 2, 3, 9, 10, 11, 12, 13)]
            return _Recorded("fused_backward", n, args, dynamic, work, device, None, 8)

        sig = _signature(n, device, grad_f)
        key = ("backward", C, d, work, device, want_A, want_mu, sig)
        base = keep.data_ptr()
        sv, LU, piv, scratch = (base + offset for *_, offset in saved.specs)
        pointers = [grad_f.data_ptr(), sv, LU, piv, scratch]
        pointers += [LU if grad_A is None else grad_A.data_ptr(), grad_b.data_ptr()]
        pointers += [outputs[2].data_ptr(), grad_l.data_ptr()]
        _run_parts(
            lambda first, count: _recorded(key, record)(n, pointers, first, count),
            _parts(n, C, device),
            ("backward", C, d, work, want_A),
        )
        grads = [None if x is None else _as(x, in_dtype) for x in (grad_A, grad_b, grad_mu, grad_l)]
        if not ctx.needs_input_grad[1]:
            grads[1] = None
        if not ctx.needs_input_grad[3]:
            grads[3] = None
        return *grads, None, None, None, None
