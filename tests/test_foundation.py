"""Foundation: systems, LQR, networks <-> CasADi <-> torch, the instruction walker."""

import casadi as ca
import numpy as np
import pytest
import torch

import systems
from baselines.lqr import lqr, saturated_controller
from nlyap_opt.kernel.network import dense_network, from_torch
from nlyap_opt.kernel.symbolic import closed_loop, lie_derivative
from nlyap_opt.kernel.walker import ArrayArithmetic, evaluate

ALL = list(systems.SEED_SYSTEMS)


# ----------------------------------------------------------------------------- LQR
def test_lqr_gains_match_reference_and_riccati():
    ip = lqr(systems.get("inverted_pendulum"), 1.0, 1.0)
    np.testing.assert_allclose(ip.K, [[1.97725, 0.97624]], atol=1e-5)
    pf = lqr(systems.get("unicycle_path_following"))
    np.testing.assert_allclose(pf.K, [[0.41421, 1.35219]], atol=1e-5)
    for res in (ip, pf):
        assert res.riccati_residual() < 1e-9
        assert np.all(res.eigenvalues.real < 0)
        # the Lyapunov equation holds for the closed loop
        Acl = res.A - res.B @ res.K
        np.testing.assert_allclose(Acl.T @ res.P + res.P @ Acl, -np.eye(2), atol=1e-10)


def test_lqr_is_optimal_against_perturbed_gains(rng):
    """The LQR cost x0ᵀ S x0 is below the cost of any perturbed stabilising gain."""
    res = lqr(systems.get("inverted_pendulum"))
    A, B, Q, R = res.A, res.B, res.Q, res.R
    x0 = np.array([1.0, -0.5])
    best = x0 @ res.S @ x0
    for _ in range(20):
        K = res.K + 0.05 * rng.standard_normal(res.K.shape)
        Acl = A - B @ K
        if np.max(np.linalg.eigvals(Acl).real) >= 0:
            continue
        from scipy.linalg import solve_continuous_lyapunov

        Pk = solve_continuous_lyapunov(Acl.T, -(Q + K.T @ R @ K))
        assert x0 @ Pk @ x0 >= best - 1e-9


@pytest.mark.parametrize("name", list(systems.names()))
def test_lqr_and_lyapunov_matrix_are_python_controls_numbers_bit_for_bit(name):
    """The solvers are called as python-control calls them (without slycot), without
    importing it: the same gains, Riccati and Lyapunov solutions to the last bit, so that
    saved certificates do not change."""
    import subprocess
    import sys

    control = pytest.importorskip("control")
    from nlyap_opt.design.control import linearisation, lyapunov_matrix

    if control.mateqn.slycot_check():
        pytest.skip("python-control uses slycot here, another solver")
    s = systems.get(name)
    if s.nu == 0:
        pytest.skip("no input")
    A, B = linearisation(s)
    Q, R = np.diag(np.arange(1.0, s.nx + 1)), 0.5 * np.eye(s.nu)
    res = lqr(s, Q, R)
    K, S, E = control.lqr(A, B, Q, R)
    assert np.array_equal(res.K, K) and np.array_equal(res.S, S)
    assert np.array_equal(res.eigenvalues, E)
    Acl = A - B @ res.K
    P = control.lyap(Acl.T, 2.0 * np.eye(s.nx))
    assert np.array_equal(lyapunov_matrix(Acl, 2.0 * np.eye(s.nx)), 0.5 * (P + P.T))
    code = ("import sys, systems\nfrom nlyap_opt.design.control import lqr\n"
            f"lqr(systems.get({name!r}))\nprint('control' in sys.modules)")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                         check=True)
    assert out.stdout.split()[-1] == "False"


def test_van_der_pol_lyapunov_matrix():
    res = lqr(systems.get("van_der_pol"))
    np.testing.assert_allclose(res.P, [[1.5, -0.5], [-0.5, 1.0]], atol=1e-12)


@pytest.mark.parametrize("name", ALL)
def test_linearisation_matches_central_differences(name):
    s = systems.get(name)
    h = 1e-6
    x0, u0 = np.zeros((1, s.nx)), s.u_eq[None, :]
    for i in range(s.nx):
        e = np.zeros((1, s.nx))
        e[0, i] = h
        col = (s.evaluate(x0 + e, u0) - s.evaluate(x0 - e, u0))[0] / (2 * h)
        np.testing.assert_allclose(col, s.A[:, i], atol=1e-8)
    for j in range(s.nu):
        e = np.zeros((1, s.nu))
        e[0, j] = h
        col = (s.evaluate(x0, u0 + e) - s.evaluate(x0, u0 - e))[0] / (2 * h)
        np.testing.assert_allclose(col, s.B[:, j], atol=1e-8)


def test_path_following_bias_is_solved():
    s = systems.get("unicycle_path_following")
    ctrl = saturated_controller(s, lqr(s).K, 5.0)
    b = ctrl.layers[0].bias[0]
    assert abs(5 * np.tanh(b) - 1.0) < 1e-15
    assert abs(b - np.arctanh(0.2)) < 1e-15
    # the closed loop keeps the origin as equilibrium and linearises to A - B K
    cl = closed_loop(s, ctrl)
    J = ca.Function("J", [cl.x], [ca.jacobian(cl.rhs, cl.x)])(np.zeros(2))
    np.testing.assert_allclose(np.array(J), s.A - s.B @ lqr(s).K, atol=1e-12)


# ----------------------------------------------------------------------------- networks
ARCHS = [
    ([2, 6, 1], "tanh"),
    ([2, 16, 16, 1], "tanh"),
    ([2, 8, 1], "sigmoid"),
    ([2, 10, 1], "relu"),
]


def _torch_net(sizes, act, seed):
    torch.manual_seed(seed)
    mods = []
    acts = {"tanh": torch.nn.Tanh, "sigmoid": torch.nn.Sigmoid, "relu": torch.nn.ReLU}
    for k in range(len(sizes) - 1):
        mods.append(torch.nn.Linear(sizes[k], sizes[k + 1]))
        if k < len(sizes) - 2:
            mods.append(acts[act]())
    return torch.nn.Sequential(*mods).double()


@pytest.mark.parametrize("sizes,act", ARCHS)
@pytest.mark.parametrize("name", ["van_der_pol", "inverted_pendulum"])
def test_torch_casadi_lie_derivative_agree(sizes, act, name, rng):
    s = systems.get(name)
    tV = _torch_net(sizes, act, 0)
    V = from_torch(tV)
    ctrl = None
    if s.nu:
        ctrl = saturated_controller(s, lqr(s).K, s.input_box[0, 1])
    cl = closed_loop(s, ctrl)
    Vx = V.casadi(cl.x)
    L = ca.Function("L", [cl.x], [Vx, ca.gradient(Vx, cl.x), lie_derivative(Vx, cl.x, cl.rhs)])
    X = rng.uniform(-2, 2, (10_000, s.nx))
    v, g, lie = evaluate(L, [X])
    # torch float64 autograd reference
    xt = torch.tensor(X, requires_grad=True)
    vt = tV(xt)[:, 0]
    (gt,) = torch.autograd.grad(vt.sum(), xt)
    ut = None if ctrl is None else ctrl.torch_module()(xt)
    ft = s.evaluate_torch(xt, ut)
    liet = (gt * ft).sum(1)
    np.testing.assert_allclose(v[:, 0], vt.detach().numpy(), rtol=0, atol=1e-12)
    np.testing.assert_allclose(g, gt.numpy(), rtol=0, atol=1e-12)
    np.testing.assert_allclose(lie[:, 0], liet.detach().numpy(), rtol=0, atol=1e-12)


# exactness over architectures, JSON round trips and bad files: tests/test_network.py


# ----------------------------------------------------------------------------- walker
def _casadi_reference(fun, X):
    outs = fun.map(X.shape[0])(X.T)
    outs = outs if isinstance(outs, (list, tuple)) else [outs]
    res = []
    for j, o in enumerate(outs):
        nnz = fun.sparsity_out(j).nnz()
        res.append(np.array(o, dtype=float).reshape(-1, X.shape[0], order="F").T
                   if nnz > 1 else np.array(o, dtype=float).reshape(X.shape[0], 1))
    return res


@pytest.mark.parametrize("name", ALL)
@pytest.mark.parametrize("graph", ["mx", "sx"])
def test_walker_equals_casadi(name, graph, rng):
    s = systems.get(name)
    V = dense_network([s.nx, 6, 1], seed=7)
    ctrl = saturated_controller(s, lqr(s).K, s.input_box[0, 1]) if s.nu else None
    cl = closed_loop(s, ctrl)
    Vx = V.casadi(cl.x)
    lie = lie_derivative(Vx, cl.x, cl.rhs)
    fun = ca.Function("F", [cl.x], [Vx, lie, ca.jacobian(ca.vertcat(Vx, lie), cl.x), cl.rhs])
    if graph == "sx":
        fun = fun.expand()
    X = rng.uniform(-1, 1, (500, s.nx)) * s.state_box[:, 1]
    for ours, ref in zip(evaluate(fun, [X]), _casadi_reference(fun, X)):
        # same operations in possibly different summation order
        np.testing.assert_allclose(ours.reshape(ref.shape), ref, rtol=1e-13, atol=1e-13)
    # and the plain system f through the walker
    U = np.tile(s.u_eq, (500, 1))
    ref_f = np.array(s.f_fun.map(500)(X.T, U.T)).T
    np.testing.assert_allclose(s.evaluate(X, U), ref_f, rtol=1e-15, atol=1e-15)


def test_walker_torch_arithmetic_is_differentiable(rng):
    s = systems.get("van_der_pol")
    X = torch.tensor(rng.standard_normal((5, 2)), requires_grad=True)
    f = s.evaluate_torch(X)
    f.sum().backward()
    x1, x2 = X.detach().numpy().T
    # d/dx of sum(f) = (-x2) + (x1 + (x1²-1) x2): [1 + 2 x1 x2, -1 + x1² - 1]
    np.testing.assert_allclose(X.grad.numpy()[:, 0], 1 + 2 * x1 * x2, atol=1e-14)
    np.testing.assert_allclose(X.grad.numpy()[:, 1], x1**2 - 2, atol=1e-14)


def test_walker_constants_are_exact():
    """str(SX) prints 6 digits; the walker must read constants exactly."""
    x = ca.SX.sym("x")
    c = 0.1234567890123456789
    f = ca.Function("f", [x], [x * c + np.pi])
    out = evaluate(f, [np.array([[1.0]])])[0]
    assert out[0, 0] == 1.0 * c + np.pi


def test_walker_arithmetic_plugs_in():
    """A custom arithmetic sees every op: count them."""

    class Counting(ArrayArithmetic):
        def __init__(self):
            super().__init__("numpy")
            self.count = 0

        def unary(self, op, a):
            self.count += 1
            return super().unary(op, a)

    x = ca.SX.sym("x")
    f = ca.Function("f", [x], [ca.sin(ca.tanh(x))])
    ar = Counting()
    evaluate(f, [np.zeros((3, 1))], ar)
    assert ar.count == 2
