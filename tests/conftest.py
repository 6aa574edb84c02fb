"""Shared pytest fixtures."""

from __future__ import annotations

import os

import pytest
import torch


@pytest.fixture(autouse=True)
def _generated_code_for_the_zoo(request, monkeypatch):
    """Generated compiled code (:mod:`torchslq.dynamics.codegen`, on by default for every
    model) for three of the zoo's models only, unless a module tests it
    (``pytestmark = pytest.mark.codegen``): the suite defines many small models of its
    own, each of which would be traced and compiled once (seconds each) for tests about
    other things, which the torch path serves. ``TORCHSLQ_TEST_CODEGEN=1`` runs every
    test with it."""
    if request.node.get_closest_marker("codegen") or os.environ.get("TORCHSLQ_TEST_CODEGEN"):
        return
    import torchslq.systems as zoo
    from torchslq.dynamics import ContinuousDynamics, Dynamics

    monkeypatch.setattr(ContinuousDynamics, "generate_compiled_code", False)
    monkeypatch.setattr(Dynamics, "generate_compiled_code", False)
    for cls in (zoo.CartPole, zoo.MassChain, zoo.Unicycle):  # the compiled paths' models
        monkeypatch.setattr(cls, "generate_compiled_code", True, raising=False)


@pytest.fixture(autouse=True)
def _generated_derivatives_where_tested(request, monkeypatch):
    """A learned model's generated Jacobians and Hessians
    (:mod:`torchslq.dynamics.network_reverse`, on by default) only where a test checks
    them (``pytest.mark.network_derivatives``): each model's two functions compile in
    5-20 s with a cold cache, and the learned models of the other modules' solves are
    served by the traced-graph pass, which ``tests/test_graph_jacobian.py`` checks.
    ``TORCHSLQ_TEST_CODEGEN=1`` runs every test with them."""
    if request.node.get_closest_marker("network_derivatives") or os.environ.get(
        "TORCHSLQ_TEST_CODEGEN"
    ):
        return
    from torchslq.dynamics import network_codegen

    monkeypatch.setattr(network_codegen, "MAX_DERIVATIVE_NODES", {"jacobians": -1, "hessians": -1})


@pytest.fixture(autouse=True)
def _steps_on_rows_where_tested(request, monkeypatch):
    """A learned model's step on many rows at once (``step_rows``, on by default from
    ``dispatch.MIN_BLOCK_ROWS`` rows) only where a test sets that threshold itself: each
    model's function and the two kernels that call it compile in seconds with a cold
    cache, and the other modules' learned models are served by the one-row step, which
    ``tests/test_fused_line_search.py`` checks them against. ``TORCHSLQ_TEST_CODEGEN=1``
    runs every test with it."""
    if os.environ.get("TORCHSLQ_TEST_CODEGEN"):
        return
    from torchslq._backend import dispatch

    monkeypatch.setattr(dispatch, "MIN_BLOCK_ROWS", 10**9)


@pytest.fixture(autouse=True)
def _bound_kernels_by_the_test_alone(monkeypatch):
    """Each test starts with no generated model's bound kernel taken (:mod:`torchslq.
    _backend.bound`: a pass under ``MIN_ROWS`` rows runs them once a large pass has taken
    them, in this process or, noted in a ``.taken`` file, an earlier one), so the kernels
    a test runs depend on its own passes, not on which tests its worker ran before: the
    bound kernels' results (the model's functions inlined) have been seen to differ from
    the generic kernels' in the last bit, and one bit can move a long solve by an
    iteration."""
    from torchslq._backend import bound

    monkeypatch.setattr(bound, "_TAKEN", set())
    monkeypatch.setattr(bound, "_NOTED", {})
    monkeypatch.setattr(bound, "_taken_file", lambda module: None)


#: the sizes that keep LQ kernels compiled for their own (n, m) in the suite: the
#: cart-pole's, the pendulum's and the unicycle's, which most solver tests use
SPECIALISED_SIZES = ((4, 1), (2, 1), (3, 2))
#: the QPs' reduced sizes that keep interior-point kernels of their own in the suite: the
#: most used one (3) and the container crane PS10's (8); the LQDO tests meet six others,
#: each 10-12 s of compilation (the set-up's and the iterations' kernels) with a cold cache
SPECIALISED_QP_SIZES = (3, 8)


@pytest.fixture(autouse=True)
def _specialised_sizes_of_the_zoo(request):
    """Size-specialised LQ kernels (:mod:`torchslq._backend.specialisation`, on by
    default for every size up to 7 x 4) for :data:`SPECIALISED_SIZES` only, unless a
    test checks them (``pytest.mark.all_sizes``): each size is compiled once, 5-20 s
    with a cold cache, and the suite's random problems draw dozens of sizes. Every
    other size runs the kernels that read their sizes at run time, which
    ``tests/test_lq_kernel.py`` and ``tests/test_gain_codegen.py`` check the
    specialised ones against. The same for the QP interior point's reduced sizes
    (:data:`SPECIALISED_QP_SIZES`; ``tests/test_lqdo_qp.py`` checks the two kinds of
    kernels against each other). ``TORCHSLQ_TEST_ALL_SIZES=1`` runs every test with all
    sizes specialised."""
    if request.node.get_closest_marker("all_sizes") or os.environ.get("TORCHSLQ_TEST_ALL_SIZES"):
        yield
        return
    from torchslq._backend.specialisation import (
        limit_specialised_qp_sizes,
        limit_specialised_sizes,
    )

    old = limit_specialised_sizes(SPECIALISED_SIZES)
    old_qp = limit_specialised_qp_sizes(SPECIALISED_QP_SIZES)
    try:
        yield
    finally:
        limit_specialised_sizes(old)
        limit_specialised_qp_sizes(old_qp)


@pytest.fixture
def single_thread():
    """One intra-op thread for the test: the problems are tiny, threading only adds
    overhead (and noise). Modules opt in with ``pytestmark = pytest.mark.usefixtures(...)``."""
    n = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(n)


@pytest.fixture
def float64_default():
    """float64 as torch's default dtype for the test, restored afterwards (a module-level
    ``set_default_dtype`` would leak into other modules' tests in the same worker).
    Modules opt in with ``pytestmark = pytest.mark.usefixtures("float64_default")``."""
    old = torch.get_default_dtype()
    torch.set_default_dtype(torch.float64)
    yield
    torch.set_default_dtype(old)


BACKENDS = ("compiled", "torch")


@pytest.fixture(params=BACKENDS)
def backend(request):
    """Run the test once on each CPU backend: ``"compiled"`` (the numba kernels, where
    :func:`torchslq._backend.can_use_compiled` holds) and ``"torch"`` (batched torch ops
    everywhere, as on a GPU), switched process-wide with :func:`torchslq.lq.set_compiled`
    and restored after the test. The two must give the same results (up to rounding);
    a test that compares against an independent computation (a dense KKT solve, finite
    differences, per-element solves, a paper's numbers) takes this fixture to check
    both."""
    from torchslq.lq import compiled_available, set_compiled

    if request.param == "compiled" and not compiled_available():
        pytest.skip("numba kernels not available")
    old = set_compiled(request.param == "compiled")
    try:
        yield request.param
    finally:
        set_compiled(old)
