"""diffcontact: batched differentiable contact models for learning colliding systems.

Implements the constrained Lagrangian/Hamiltonian networks with the two-phase
(compression/restitution, Poisson) contact model of Zhong, Dey & Chakraborty,
"Extending Lagrangian and Hamiltonian Neural Networks with Differentiable
Contact Models" (NeurIPS 2021).
"""

from importlib.metadata import PackageNotFoundError, version

try:
    __version__ = version("diffcontact")
except PackageNotFoundError:  # running from a source tree without installation
    __version__ = "0.0.0+unknown"

__all__ = [
    "PhysicalParams", "System", "__version__", "contact", "control", "learning", "load_system",
    "optimize",
]  # fmt: skip

_SUBPACKAGES = ("contact", "control", "geometry", "learning", "mechanics", "systems", "viz")


def __getattr__(name: str):
    # lazy: importing diffcontact stays cheap; torch loads with the first use
    if name in ("PhysicalParams", "System", "load_system", "load_config", "list_tasks"):
        from diffcontact import systems

        return getattr(systems, name)
    if name == "optimize":
        from diffcontact.control.optimize import optimize

        return optimize
    if name in _SUBPACKAGES:
        import importlib

        return importlib.import_module(f"diffcontact.{name}")
    raise AttributeError(f"module 'diffcontact' has no attribute {name!r}")
