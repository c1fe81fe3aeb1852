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

__all__ = ["__version__"]
