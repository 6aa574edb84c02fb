"""SLQ: the Sequential Linear Quadratic algorithm of Sideris & Bobrow (2005), batched.

Algorithm 2 of the paper, for every batch element independently:

1. roll out ``x`` under the current controls ``U`` (Step 1);
2. linearise the dynamics along ``(x, u)`` (Step 2, ``A = f_x``, ``B = f_u``) and solve the
   LQ tracking problem with ``x̄(0) = 0`` and targets ``x̄° = x° - x``, ``ū° = u° - u``
   (eq. 29-30) by the shared Riccati kernel (Algorithm 1). For the quadratic cost this
   is exactly the LQ problem with linear terms ``q = Q (x - x°)`` and ``r = R (u - u°)``,
   i.e. the cost's gradient; the cost is *not* linearised (Gauss-Newton, Section 3.3);
3. stop when ``||Ū|| < tol ||U||`` and/or ``||∇_U J|| < tol`` (configurable);
4. otherwise step ``U + α Ū`` (eq. 28) with ``α`` from a line search over ``(0, 1]``:
   "exact" (Theorem 2) or "armijo" with the directional derivative of eq. (34).

Every element keeps its own step size, iteration count and status; finished or failed
elements are frozen by a mask and never affect the others.
"""

from __future__ import annotations

import time
from dataclasses import asdict, dataclass
from typing import TYPE_CHECKING, Any

import torch
from torch import Tensor

from ..costs.quadratic import compiled_cost_evaluation
from ..dynamics.linearize import linearize
from ..lq.riccati import riccati_backward, rollout_linear
from ..status import Status
from .line_search import TrialRecorder, armijo_search, exact_search
from .progress import progress_bar
from .result import SolverResult
from .rollout import costate_gradient, rollout, rollout_closed_loop
from .stopping import stall_update

if TYPE_CHECKING:  # pragma: no cover
    from ..problem import Problem

__all__ = ["SLQ", "SLQOptions"]


def _take(t: Tensor, idx: Tensor | None) -> Tensor:
    """Rows ``idx`` of ``t`` (all of it for None)."""
    return t if idx is None else t.index_select(0, idx)


def _put(full: Tensor, idx: Tensor | None, part: Tensor) -> Tensor:
    """``full`` with rows ``idx`` replaced by ``part`` (``part`` itself for None)."""
    return part if idx is None else full.index_copy(0, idx, part)


_LINE_SEARCHES = ("exact", "armijo")
_ROLLOUTS = ("open_loop", "closed_loop")
_STOPS = ("grad", "step", "either", "both")


def _checked_x_init(x_init: Tensor, x0: Tensor, T: int) -> Tensor:
    """``x_init`` as ``(B, T+1, n)``, checked against ``x0 (B, n)`` (shape, first state)."""
    if not torch.is_tensor(x_init):
        raise TypeError("x_init must be a tensor of shape (B, T+1, n) or (T+1, n)")
    Bsz, n = x0.shape
    x = x_init.reshape(-1, *x_init.shape[-2:]) if x_init.ndim in (2, 3) else x_init
    if x.ndim != 3 or x.shape[1:] != (T + 1, n) or x.shape[0] not in (1, Bsz):
        raise ValueError(
            f"x_init must have shape ({Bsz}, {T + 1}, {n}) or ({T + 1}, {n}), "
            f"got {tuple(x_init.shape)}"
        )
    x = x.to(dtype=x0.dtype, device=x0.device).expand(Bsz, T + 1, n)
    if not torch.equal(x[:, 0], x0):
        raise ValueError("x_init[:, 0] must equal x0 (x_init is the rollout of u_init from x0)")
    return x.detach().clone()


def _check_passes(passes) -> tuple[int, int | None]:
    """``armijo_passes`` as a ``(first, then)`` tuple of positive ints (``then`` may be
    None), or ValueError."""

    def positive_int(v) -> bool:
        return isinstance(v, int) and not isinstance(v, bool) and v >= 1

    ok = isinstance(passes, (tuple, list)) and len(passes) == 2
    if ok and positive_int(passes[0]) and (passes[1] is None or positive_int(passes[1])):
        return (passes[0], passes[1])
    raise ValueError(
        f"armijo_passes must be (first, then) with positive ints (then may be None), got {passes!r}"
    )


@dataclass
class SLQOptions:
    """Options of :class:`SLQ` (see its docstring)."""

    max_iter: int = 100
    tol: float = 1e-6
    line_search: str = "exact"
    stop: str = "grad"
    step_tol: float | None = None
    rtol: float = 0.0
    stall_iters: int = 10
    rollout: str = "open_loop"
    armijo_c1: float = 1e-4
    armijo_beta: float = 0.5
    max_backtracks: int = 20
    armijo_passes: tuple[int, int | None] | None = None
    linearize_method: str = "auto"
    progress: bool = True
    compact: bool = False


class SLQ:
    """Sequential Linear Quadratic solver (Sideris & Bobrow 2005, Algorithm 2).

    Args:
        max_iter: iterations per element (default 100).
        tol: tolerance of the stopping rule (default 1e-6).
        line_search: ``"exact"`` (minimise ``J(U + αŪ)`` over ``α ∈ (0, 1]``: a grid of
            steps evaluated as one batched rollout, refined by a quadratic fit) or
            ``"armijo"`` (backtracking from 1 on ``J(U+αŪ) <= J(U) + c1 α D`` with
            ``D = ∇J·Ū = -(Σ x̄'Qx̄ + ū'Rū)``, eq. 34).
        stop: ``"grad"``: ``||∇_U J|| < tol`` (the test of the paper's Section 4);
            ``"step"``: ``||Ū|| < step_tol ||U||`` (Algorithm 2, Step 2); ``"either"`` /
            ``"both"`` combine the two.
        step_tol: tolerance of the step rule (defaults to ``tol``).
        rtol: also stop (as converged) after an accepted step that changes the cost by
            at most ``rtol |J|``; 0 (default) disables this test.
        stall_iters: stop an element with status ``stalled`` (not converged) when this
            many consecutive accepted steps changed its cost by no more than rounding
            noise (``64 eps max(|J|, 1)``, eps of the dtype) and did not halve its
            gradient norm, while the stopping test was still unmet: the solve has reached
            the precision of the dtype (typically float32 with a tolerance below what
            float32 gradients can resolve), and further iterations only accept noise.
            Default 10; 0 disables.
        rollout: ``"open_loop"`` (the paper's ``U + αŪ``) or ``"closed_loop"`` (the line
            search applies the LQ feedback: ``u = u + α k + K (x_new - x)``).
        armijo_c1, armijo_beta, max_backtracks: Armijo constants.
        armijo_passes: ``(first, then)``: the Armijo trials are rolled out ``first`` at a
            time, then ``then`` at a time (None: all the rest at once) while some element
            has accepted none; the accepted steps are the same for any choice. Default
            (None): ``(1, 3)`` on the CPU, where each trial rollout costs in proportion
            (cart-pole DDP B=512: 13% faster than ``(4, None)``), ``(4, None)`` on other
            devices, where each pass costs a host sync.
        linearize_method: passed to :func:`torchslq.linearize`.
        progress: show a tqdm bar when a solve takes longer than a second.
        compact: compute each iteration only on the elements still running (finished
            ones cost nothing more). Only for problems without per-element tensors:
            the dynamics and cost are then called on a sub-batch, so a parameter shaped
            ``(B, 1)`` (registered or captured in a closure) would no longer line up.
            ``solve`` refuses it when a registered tensor of the problem (2-D or more)
            leads with the batch size. Off by default.
    """

    name = "slq"

    def __init__(
        self, max_iter: int = 100, tol: float = 1e-6, line_search: str = "exact", **kwargs: Any
    ):
        self.options = SLQOptions(max_iter=max_iter, tol=tol, line_search=line_search, **kwargs)
        o = self.options
        if not isinstance(o.max_iter, int) or o.max_iter < 0:
            raise ValueError(f"max_iter must be a non-negative int, got {o.max_iter!r}")
        if not o.tol > 0:
            raise ValueError(f"tol must be positive, got {o.tol!r}")
        if o.line_search not in _LINE_SEARCHES:
            raise ValueError(f"line_search must be one of {_LINE_SEARCHES}, got {o.line_search!r}")
        if o.rollout not in _ROLLOUTS:
            raise ValueError(f"rollout must be one of {_ROLLOUTS}, got {o.rollout!r}")
        if not o.rtol >= 0:
            raise ValueError(f"rtol must be >= 0, got {o.rtol!r}")
        if not isinstance(o.stall_iters, int) or o.stall_iters < 0:
            raise ValueError(f"stall_iters must be a non-negative int, got {o.stall_iters!r}")
        if o.stop not in _STOPS:
            raise ValueError(f"stop must be one of {_STOPS}, got {o.stop!r}")
        if o.armijo_passes is not None:
            o.armijo_passes = _check_passes(o.armijo_passes)

    def _armijo_passes(self, device: torch.device) -> tuple[int, int | None]:
        """``(first_trials, pass_size)`` of :func:`armijo_search` (option
        ``armijo_passes``, or the device's default)."""
        if self.options.armijo_passes is not None:
            return self.options.armijo_passes
        return (1, 3) if device.type == "cpu" else (4, None)

    # ------------------------------------------------------------------ one SLQ direction
    def direction(self, problem: Problem, x: Tensor, u: Tensor) -> dict[str, Tensor]:
        """Linearise at ``(x, u)`` and solve the LQ subproblem (Algorithm 2, Step 2).

        Returns a dict with the direction ``du (B,T,m)``, its state response
        ``dx (B,T+1,n)``, the gains ``K``, ``k``, the gradient ``grad (B,T,m)`` (eqs.
        8-11), the directional derivative ``slope = ∇J·Ū (B,)`` and the factor status
        ``failed (B,)``.
        """
        T = problem.horizon
        A, B = linearize(problem.transition, x[:, :T], u, method=self.options.linearize_method)
        e = problem.cost.quadratize(x, u)
        grad, _ = costate_gradient(A, B, e.lx, e.lu)
        fac = riccati_backward(A, B, e.lxx, e.luu, e.lx, e.lu, e.lux)
        dx, du = rollout_linear(A, B, fac.K, fac.k, torch.zeros_like(x[:, 0]))
        slope = (grad * du).sum(dim=(-1, -2))
        return {
            "dx": dx,
            "du": du,
            "K": fac.K,
            "k": fac.k,
            "grad": grad,
            "slope": slope,
            "failed": fac.failed,
        }

    # ------------------------------------------------------------------ solve
    def solve(
        self,
        problem: Problem,
        x0: Tensor,
        u_init: Tensor | None = None,
        logger: Any = None,
        *,
        x_init: Tensor | None = None,
    ) -> SolverResult:
        """Solve ``problem`` from initial states ``x0 (B, n)`` (or ``(n,)``).

        Args:
            u_init: initial controls ``(B, T, m)`` or ``(T, m)``; zeros by default.
            logger: e.g. :class:`torchslq.TensorBoardLogger`; None costs nothing.
            x_init: optional states ``(B, T+1, n)`` (or ``(T+1, n)``) of ``u_init`` from
                ``x0`` (``x_{t+1} = f(x_t, u_t)``), when the caller has them already (e.g.
                a closed-loop warm start): the initial rollout is then skipped. Only its
                shape and first state are checked (a trajectory that is not the rollout
                of ``u_init`` makes the first iteration's cost and step wrong).
        """
        o = self.options
        x0, u, unbatched = problem.check_inputs(x0, u_init)
        if x_init is not None:
            x_init = _checked_x_init(x_init, x0, problem.horizon)
        f = problem.transition
        cost_fn = problem.cost
        Bsz, T, n, m = x0.shape[0], problem.horizon, problem.state_dim, problem.control_dim
        step_tol = o.tol if o.step_tol is None else o.step_tol
        if o.compact:
            name = problem.per_element_tensor(Bsz)
            if name is not None:
                tensors = dict(problem.named_parameters()) | dict(problem.named_buffers())
                shape = tuple(tensors[name].shape)
                raise ValueError(
                    f"compact=True needs batch-shared problem data, but {name!r} has shape "
                    f"{shape} (batch size {Bsz}); use compact=False"
                )
        self._begin(x0)
        t_start = time.perf_counter()

        # every cost of the loop is evaluated without autograd, so quadratic costs may use
        # the CPU kernel (whose last bits differ from the torch path's) throughout
        with torch.no_grad(), compiled_cost_evaluation():
            x = rollout(f, x0, u) if x_init is None else x_init
            J = cost_fn(x, u)
            status = torch.full((Bsz,), int(Status.RUNNING), dtype=torch.int64, device=x0.device)
            finite0 = torch.isfinite(J) & torch.isfinite(x).flatten(1).all(1)
            status = status.masked_fill(~finite0, int(Status.NON_FINITE))
            iterations = torch.zeros(Bsz, dtype=torch.int64, device=x0.device)
            stalls = torch.zeros_like(iterations)  # consecutive noise-level accepted steps
            stall_grad = torch.zeros_like(J)  # gradient norm when that run started
            step = torch.zeros_like(J)
            hist_cost, hist_grad, hist_step, hist_time = [], [], [], []
            K = x0.new_zeros(Bsz, T, m, n)
            k = x0.new_zeros(Bsz, T, m)
            grad_norm = torch.full_like(J, float("nan"))
            if logger is not None:
                logger.log_options(self.name, asdict(o))
            bar = progress_bar(o.max_iter, enabled=o.progress, desc="SLQ")
            for it in range(o.max_iter + 1):
                running = status == Status.RUNNING
                # working set: every element, or (compact=True) only the running ones
                idx = running.nonzero().squeeze(1) if o.compact else None  # one host sync
                if idx is not None and idx.numel() == Bsz:
                    idx = None
                if idx is not None and idx.numel() == 0:
                    break
                self._select(idx)
                xs, us, Js, x0s = (_take(t, idx) for t in (x, u, J, x0))
                run = _take(running, idx)
                self._running = run  # read by subclasses' direction() (e.g. iLQR retries)
                self._iteration = it
                d = self.direction(problem, xs, us)
                gn = d["grad"].flatten(1).norm(dim=1)
                grad_norm = _put(grad_norm, idx, torch.where(run, gn, _take(grad_norm, idx)))
                new_gains = run if "keep_gains" not in d else run & d["keep_gains"]
                K = _put(K, idx, torch.where(new_gains[:, None, None, None], d["K"], _take(K, idx)))
                k = _put(k, idx, torch.where(new_gains[:, None, None], d["k"], _take(k, idx)))
                small_grad = gn < o.tol
                small_step = d["du"].flatten(1).norm(dim=1) < step_tol * us.flatten(1).norm(dim=1)
                done = {
                    "grad": small_grad,
                    "step": small_step,
                    "either": small_grad | small_step,
                    "both": small_grad & small_step,
                }[o.stop]
                st = _take(status, idx)
                st = st.masked_fill(run & done, int(Status.CONVERGED))
                stuck = run & ~done
                st = st.masked_fill(stuck & d["failed"], int(Status.NOT_POSITIVE_DEFINITE))
                st = st.masked_fill(stuck & ~torch.isfinite(d["slope"]), int(Status.NON_FINITE))
                status = _put(status, idx, st)
                run = st == Status.RUNNING
                hist_cost.append(J)
                hist_grad.append(grad_norm)
                hist_step.append(step)
                hist_time.append(time.perf_counter() - t_start)
                if logger is not None:
                    logger.log_iteration(
                        it,
                        cost=J,
                        grad_norm=grad_norm,
                        step=step,
                        status=status,
                        wall_time=hist_time[-1],
                    )
                n_running = int(run.sum())  # the host sync that ends the solve
                if n_running == 0 or it == o.max_iter:
                    self._scatter(idx)
                    break
                d["running"] = run  # finished elements must not hold up a line-search pass
                alpha, J_new, ok, x_new, u_new = self._line_search(f, cost_fn, x0s, xs, us, Js, d)
                accept = run & ok
                st = st.masked_fill(
                    self._after_line_search(run, ok), int(Status.LINE_SEARCH_FAILED)
                )
                a = torch.where(accept, alpha, torch.zeros_like(alpha))
                u = _put(u, idx, torch.where(accept[:, None, None], u_new, us))
                x = _put(x, idx, torch.where(accept[:, None, None], x_new, xs))
                if o.rtol > 0:  # relative cost change after an accepted step
                    st = st.masked_fill(
                        accept & ((Js - J_new).abs() <= o.rtol * Js.abs()), int(Status.CONVERGED)
                    )
                if o.stall_iters > 0:
                    stalled, ns, g_ref = stall_update(
                        _take(stalls, idx), _take(stall_grad, idx), accept, Js, J_new, gn,
                        o.stall_iters,
                    )  # fmt: skip
                    st = st.masked_fill((st == Status.RUNNING) & stalled, int(Status.STALLED))
                    stalls, stall_grad = _put(stalls, idx, ns), _put(stall_grad, idx, g_ref)
                status = _put(status, idx, st)
                J = _put(J, idx, torch.where(accept, J_new, Js))
                step = _put(torch.zeros_like(step), idx, a)
                iterations = _put(iterations, idx, _take(iterations, idx) + accept.to(torch.int64))
                self._scatter(idx)
                bar.update(1)
                bar.set_postfix(running=n_running, refresh=False)
            bar.close()
            self._iteration = 0
            status = status.masked_fill(status == Status.RUNNING, int(Status.MAX_ITER))

        result = SolverResult(
            x=x,
            u=u,
            cost=J,
            grad_norm=grad_norm,
            iterations=iterations,
            status=status,
            converged=status == Status.CONVERGED,
            K=K,
            k=k,
            history={
                "cost": torch.stack(hist_cost, dim=1),
                "grad_norm": torch.stack(hist_grad, dim=1),
                "step": torch.stack(hist_step, dim=1),
                "time": torch.tensor(hist_time, dtype=torch.float64),
            },
            options={"solver": self.name, **asdict(o)},
        )
        if logger is not None:
            logger.log_result(result, problem)
        return result.squeeze_batch() if unbatched else result

    def _converged_by_gradient(self, grad: Tensor) -> Tensor | None:
        """``(B,)`` mask of the working set's elements (``grad (B, T, m)``) that the solve
        loop will stop at this iteration whatever the step (gradient test, ``stop``
        "grad" or "either"), or None when every step is needed (other ``stop`` tests,
        and the first iteration: the result's gains ``K`` must come from a pass). A subclass may
        skip computing their step (iLQR/DDP: the second-order terms and the Riccati pass
        when every running element is in the mask); the loop then keeps their gains
        from the previous iteration (``d["keep_gains"]``), in a batch as in a single
        solve."""
        o = self.options
        if o.stop not in ("grad", "either") or getattr(self, "_iteration", 0) == 0:
            return None
        return grad.flatten(1).norm(dim=1) < o.tol

    def _begin(self, x0: Tensor) -> None:
        """Per-solve state of subclasses (e.g. iLQR's regularisation); none for SLQ."""

    # names of per-element solver state (tensors with a leading batch dim) that the
    # compacted loop narrows to the working set and writes back; see ILQR
    _per_element_state: tuple[str, ...] = ()

    def _select(self, idx: Tensor | None) -> None:
        self._full_state = {}
        if idx is None:
            return
        for name in self._per_element_state:
            v = getattr(self, name, None)
            if torch.is_tensor(v) and v.ndim > 0 and v.shape[0] > 1:
                self._full_state[name] = v
                setattr(self, name, v.index_select(0, idx))

    def _scatter(self, idx: Tensor | None) -> None:
        for name, full in getattr(self, "_full_state", {}).items():
            setattr(self, name, full.index_copy(0, idx, getattr(self, name)))
        self._full_state = {}

    def _after_line_search(self, running: Tensor, ok: Tensor) -> Tensor:
        """Elements whose failed line search ends their solve (all of them for SLQ)."""
        return running & ~ok

    def _line_search(self, f, cost_fn, x0, x, u, J, d) -> tuple[Tensor, ...]:
        """Step sizes ``(B,)``, new costs, success flags and the chosen trajectories."""
        o = self.options
        trials = TrialRecorder()

        def evaluate(alphas: Tensor) -> Tensor:  # alphas (Na, B) -> J (Na, B)
            Na = alphas.shape[0]
            x0c = x0.expand(Na, *x0.shape)
            if o.rollout == "open_loop":
                uc = u + alphas[..., None, None] * d["du"]
                xc = rollout(f, x0c, uc)
            else:
                xc, uc = rollout_closed_loop(f, x0c, x, u, d["K"], d["k"], alphas)
            trials.record(alphas, xc, uc)
            return cost_fn(xc, uc)

        if o.line_search == "exact":
            alpha, J_new, ok = exact_search(evaluate, J, slope=d["slope"])
        else:
            alpha, J_new, ok = self._armijo(evaluate, J, d)
        x_new, u_new = trials.select(alpha)
        return alpha, J_new, ok, x_new, u_new

    def _armijo(self, evaluate, J: Tensor, d: dict, curvature: Tensor | None = None):
        """:func:`armijo_search` with the solver's constants and pass sizes, told which
        elements are running (settled trials are not rolled out); ``curvature`` for the
        quadratic model of iLQR/DDP's expected improvement."""
        o = self.options
        first_trials, pass_size = self._armijo_passes(J.device)
        return armijo_search(
            evaluate,
            J,
            d["slope"],
            curvature=curvature,
            c1=o.armijo_c1,
            beta=o.armijo_beta,
            max_backtracks=o.max_backtracks,
            active=d.get("running"),
            skip_settled=True,
            first_trials=first_trials,
            pass_size=pass_size,
        )
