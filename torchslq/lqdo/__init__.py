"""Linear-quadratic dynamic optimisation (Herber & Sundarrajan 2020).

Direct transcription of nonlinear dynamic optimisation problems (trapezoidal and
Legendre-Gauss-Lobatto pseudospectral) to quadratic programs, ordinary-LQ elements built
once, QP backends (a sparse CPU solver and a batched, differentiable dense solver in
torch), quasilinearization (Algorithm 1) with an optional safeguard, and the two-level
fixed-parameter method (nested co-design) with exact upper-level gradients.
See ``docs/lqdo.md``.
"""

from .._backend.specialisation import limit_specialised_qp_sizes
from .backends import QPSolution, qp_solve, solve, solve_dense, solve_sparse
from .problem import LQDOProblem, detect_olq
from .qlin import QLINResult, Quasilinearization
from .qp import DenseQP, SparseQP
from .transcription import Transcription, lgl, transcribe
from .twolevel import LowerLevel, TLFPResult, TwoLevel

__all__ = [
    "DenseQP",
    "QLINResult",
    "QPSolution",
    "Quasilinearization",
    "LQDOProblem",
    "LowerLevel",
    "SparseQP",
    "TLFPResult",
    "Transcription",
    "TwoLevel",
    "detect_olq",
    "lgl",
    "limit_specialised_qp_sizes",
    "qp_solve",
    "solve",
    "solve_dense",
    "solve_sparse",
    "transcribe",
]
