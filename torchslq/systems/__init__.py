"""A small zoo of example systems with analytic Jacobians.

Continuous time (discretise with :func:`torchslq.discretize`): :class:`Pendulum`,
:class:`CartPole`, :class:`PendulumCartTrain` (GoPRONTO 2022, Section V).
Discrete time, in the Euler form of Sideris & Bobrow (2005):
:class:`DragVehicle` (Section 4.1) and :class:`Hopper` (Section 4.2); :class:`Unicycle`
(crocoddyl's ``ActionModelUnicycle`` step).

All parameters may be per-element tensors broadcasting against ``x[..., 0]`` (e.g.
``(B, 1)`` for inputs ``(B, T, n)``).

Each model's equations are written once, in its own module: plain functions of the
state, control and parameters that ``forward``, ``jacobians`` and ``vhp`` call with
batched tensors. On the CPU the compiled code the kernels run is generated from
``forward`` (:mod:`torchslq.dynamics.codegen`), exactly as for a user's model.
"""

from .cartpole import CartPole
from .drag_vehicle import DragVehicle
from .hopper import Hopper
from .mass_chain import MassChain
from .pendulum import Pendulum
from .pendulum_cart_train import PendulumCartTrain, PendulumCartTrainRK4
from .unicycle import Unicycle

__all__ = [
    "CartPole",
    "DragVehicle",
    "Hopper",
    "MassChain",
    "Pendulum",
    "PendulumCartTrain",
    "PendulumCartTrainRK4",
    "Unicycle",
]
