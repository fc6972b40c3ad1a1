"""Networks: CasADi graph ≡ numpy ≡ torch (values and gradients), the copies of the forward
pass elsewhere in the package ≡ :meth:`Network.casadi`, and the validation of network files.

Exactness is checked over a product of architectures (depth, width, activation, output scale,
sum-of-squares head) in float64: values to 1e-13 relative to the batch's magnitude, and CasADi
Jacobians against torch autograd. The CasADi side is evaluated by CasADi itself (``map``), not
by the project's walker, so the reference is independent of ``nlyap_opt.kernel.walker``.
"""

from __future__ import annotations

import importlib
import itertools
import json
import math
import re

import casadi as ca
import numpy as np
import pytest
import torch

import systems
from nlyap_opt.kernel.errors import DimensionError, NetworkFileError, UnsupportedLayerError
from nlyap_opt.kernel.network import ACTIVATIONS, Layer, Network, dense_network, from_torch

RTOL = 1e-13


def _casadi_eval(fun: ca.Function, Z: np.ndarray) -> np.ndarray:
    """Evaluate a one-input, one-output CasADi Function on rows of ``Z`` with CasADi itself;
    returns ``(N, *out_shape)`` (column-major entries)."""
    out = np.array(fun.map(Z.shape[0])(Z.T), dtype=float)  # (r, N·c): [out_0, out_1, ...]
    r, c = fun.size_out(0)
    return out.reshape(r, Z.shape[0], c).transpose(1, 0, 2)


def _close(a, b, rtol=RTOL):
    """``|a − b| ≤ rtol · max(1, max|b|)`` entrywise: relative to the batch's magnitude."""
    a, b = np.asarray(a, dtype=float), np.asarray(b, dtype=float)
    assert a.shape == b.shape, (a.shape, b.shape)
    tol = rtol * max(1.0, float(np.max(np.abs(b))))
    err = float(np.max(np.abs(a - b)))
    assert err <= tol, f"max difference {err:.3e} > {tol:.3e}"


def _build(depth, width, act, scale, head, n_in=3, n_out=2, seed=0):
    sizes = [n_in] + [width] * (depth - 1) + [n_out]
    base = dense_network(sizes, act, seed=seed)
    # the last layer gets the activation too when the network has a single layer
    if depth == 1:
        base.layers[0].activation = act
    s = {"one": 1.0, "scalar": 2.5,
         "vector": np.random.default_rng(seed).uniform(-2, 2, n_out)}[scale]
    h = None if head is None else {"type": "sum_of_squares", "eps": head}
    return Network(base.layers, s, {}, h)


ARCH = list(itertools.product(
    [1, 2, 3],                                # depth (number of layers)
    [1, 7],                                   # hidden width
    list(ACTIVATIONS),                        # tanh, relu, sigmoid, linear, square
    ["one", "scalar", "vector"],              # output_scale
    [None, 1e-3],                             # no head / V = ||N(x) - N(0)||² + eps||x||²
))


def _arch_id(case):
    depth, width, act, scale, head = case
    return f"d{depth}-w{width}-{act}-{scale}-{'V' if head is not None else 'N'}"


@pytest.mark.parametrize("case", ARCH, ids=[_arch_id(c) for c in ARCH])
def test_casadi_numpy_torch_values_and_gradients_agree(case):
    depth, width, act, scale, head = case
    seed = ARCH.index(case)
    net = _build(depth, width, act, scale, head, seed=seed)
    rng = np.random.default_rng(seed)
    Z = rng.uniform(-2, 2, (64, net.n_in))
    ref = net.numpy(Z)
    assert ref.shape == (64, net.n_out)
    # CasADi graph (SX and MX) evaluated by CasADi
    for sym in (ca.SX, ca.MX):
        z = sym.sym("z", net.n_in)
        expr = net.casadi(z)
        assert expr.shape == (net.n_out, 1)
        _close(_casadi_eval(ca.Function("f", [z], [expr]), Z)[:, :, 0], ref)
    # torch forward and autograd
    zt = torch.tensor(Z, requires_grad=True)
    out = net.torch_module()(zt)
    _close(out.detach().numpy(), ref)
    jac_t = np.stack([torch.autograd.grad(out[:, k].sum(), zt, retain_graph=True)[0].numpy()
                      for k in range(net.n_out)], axis=1)  # (N, n_out, n_in)
    z = ca.SX.sym("z", net.n_in)
    jac_c = _casadi_eval(ca.Function("J", [z], [ca.jacobian(net.casadi(z), z)]), Z)
    _close(jac_c, jac_t)


def test_product_of_cases_covers_every_activation_and_head():
    """The table above must exercise every activation the format supports."""
    assert {c[2] for c in ARCH} == set(ACTIVATIONS)
    assert {c[4] is None for c in ARCH} == {True, False}


def test_forward_against_an_independent_scalar_formula():
    """``c_i (Σ_j W1_ij tanh(Σ_k W0_jk z_k + b0_j) + b1_i)`` written out in plain Python."""
    net = _build(2, 5, "tanh", "vector", None, seed=4)
    (l0, l1), c = net.layers, net.output_scale
    Z = np.random.default_rng(4).uniform(-1, 1, (20, net.n_in))
    want = [[c[i] * (sum(l1.weight[i, j] * math.tanh(sum(l0.weight[j, k] * z[k]
                                                          for k in range(net.n_in))
                                                      + l0.bias[j])
                         for j in range(l0.weight.shape[0])) + l1.bias[i])
             for i in range(net.n_out)] for z in Z]
    _close(net.numpy(Z), np.array(want))
    x = ca.SX.sym("x", net.n_in)
    _close(_casadi_eval(ca.Function("f", [x], [net.casadi(x)]), Z)[:, :, 0], np.array(want))


@pytest.mark.parametrize("act", list(ACTIVATIONS))
def test_activation_table_matches_its_definition(act):
    """Each activation in numpy and CasADi equals its textbook formula."""
    z = np.linspace(-4, 4, 41)
    want = {"tanh": np.tanh(z), "relu": np.where(z > 0, z, 0.0),
            "sigmoid": 1 / (1 + np.exp(-z)), "linear": z, "square": z * z}[act]
    net = Network([Layer(np.eye(1), [0.0], act)])
    _close(net.numpy(z[:, None])[:, 0], want)
    x = ca.SX.sym("x")
    _close(_casadi_eval(ca.Function("f", [x], [net.casadi(x)]), z[:, None])[:, 0, 0], want)
    mod = net.torch_module()
    _close(mod(torch.tensor(z[:, None])).detach().numpy()[:, 0], want)
    assert from_torch(mod).layers[0].activation == act


@pytest.mark.parametrize("eps", [0.0, 1e-3, 0.5])
def test_sum_of_squares_head_is_the_lyapunov_form(eps):
    """``V(x) = ‖N(x) − N(0)‖² + ε‖x‖²``: V(0) = 0 exactly, V ≥ ε‖x‖², equal to the formula
    evaluated from the body network alone."""
    body = _build(2, 6, "tanh", "vector", None, seed=9)
    V = Network(body.layers, body.output_scale, {}, {"type": "sum_of_squares", "eps": eps})
    Z = np.random.default_rng(9).uniform(-3, 3, (100, body.n_in))
    y = body.numpy(Z) - body.numpy(np.zeros((1, body.n_in)))
    want = np.sum(y * y, axis=1) + eps * np.sum(Z * Z, axis=1)
    _close(V.numpy(Z)[:, 0], want)
    assert np.all(V.numpy(Z)[:, 0] >= eps * np.sum(Z * Z, axis=1) * (1 - 1e-15))
    assert V.numpy(np.zeros(body.n_in))[0] == 0.0
    for sym in (ca.SX, ca.MX):
        x = sym.sym("x", body.n_in)
        f = ca.Function("V", [x], [V.casadi(x)])
        assert float(f(np.zeros(body.n_in))) == 0.0
        _close(_casadi_eval(f, Z)[:, 0, 0], want)
    with torch.no_grad():
        assert float(V.torch_module()(torch.zeros(1, body.n_in, dtype=torch.float64))) == 0.0


def test_round_trip_through_torch_and_json_is_bit_exact(tmp_path):
    for k, case in enumerate(ARCH[::7]):
        net = _build(*case, seed=k)
        Z = np.random.default_rng(k).standard_normal((30, net.n_in))
        back = Network.load(net.save(tmp_path / f"n{k}.json"))
        assert np.array_equal(back.numpy(Z), net.numpy(Z))
        assert back.head == net.head
        again = from_torch(net.torch_module())
        assert np.array_equal(again.numpy(Z), net.numpy(Z))


def test_numpy_shapes():
    net = _build(2, 4, "tanh", "one", None)
    assert net.numpy(np.zeros(3)).shape == (2,)
    assert net.numpy(np.zeros((5, 3))).shape == (5, 2)
    assert net.numpy(np.zeros((4, 5, 3))).shape == (4, 5, 2)
    with pytest.raises(DimensionError, match=r"\(N, 3\)"):
        net.numpy(np.zeros((5, 2)))
    with pytest.raises(DimensionError, match=r"\(3, 1\)"):
        net.casadi(ca.SX.sym("x", 2))


# ============================================================================ other copies of φ
def _private(name: str, *modules: str):
    """A private forward-pass copy from another module; skipped (with the reason) once the
    copy has been removed, since then there is nothing left to compare."""
    for mod in modules:
        try:
            obj = getattr(importlib.import_module(mod), name, None)
        except ImportError:
            obj = None
        if obj is not None:
            return obj
    pytest.skip(f"{name} no longer exists in {', '.join(modules)} (copy removed)")


@pytest.mark.parametrize("act,scale", [("tanh", "one"), ("tanh", "vector"), ("relu", "scalar"),
                                       ("sigmoid", "vector")])
def test_learning_body_jacobian_at_zero_equals_casadi(act, scale):
    """``learning._body_jacobian_at_zero`` (forward-mode ∂N/∂x(0)) ≡ CasADi ``jacobian``."""
    jac0 = _private("_body_jacobian_at_zero", "nlyap_opt.candidates.learning")
    body = _build(3, 6, act, scale, None, seed=2)
    x = ca.SX.sym("x", body.n_in)
    want = np.array(ca.Function("J", [x], [ca.jacobian(body.casadi(x), x)])(
        np.zeros(body.n_in)), dtype=float)
    got = jac0(body.torch_module(), body.n_in).detach().numpy()
    _close(got, want)


def _pendulum_learner(**cfg):
    from nlyap_opt.candidates.learning import LyapunovLearner, TrainConfig
    from nlyap_opt.design.control import lqr, saturated_controller

    s = systems.get("inverted_pendulum")
    ctrl = saturated_controller(s, lqr(s).K, s.input_box[0, 1])
    return s, ctrl, LyapunovLearner(s, ctrl, None, TrainConfig(threads=1, **cfg))


def test_learning_controller_and_V_equal_their_networks():
    """``LyapunovLearner.kappa`` (C·tanh(Kx + b) in torch), the learner's V module and the
    second-order term ``H = 2(JᵀJ + εI)`` of ``local_violation`` ≡ the exported networks'
    CasADi graphs, also after the gain has moved."""
    s, ctrl, learner = _pendulum_learner(hidden=[5], features=3, eps=1e-3)
    X = np.random.default_rng(3).uniform(-2, 2, (50, s.nx))
    x = ca.SX.sym("x", s.nx)
    kappa0 = learner.kappa(torch.tensor(X)).detach().numpy()
    _close(kappa0, _casadi_eval(ca.Function("k", [x], [ctrl.casadi(x)]), X)[:, :, 0])
    with torch.no_grad():
        learner.G.mul_(1.3)
        learner.G.add_(0.05)
    V, k_net = learner.export()
    kappa = learner.kappa(torch.tensor(X)).detach().numpy()
    assert not np.allclose(kappa, kappa0)
    _close(kappa, _casadi_eval(ca.Function("k", [x], [k_net.casadi(x)]), X)[:, :, 0], 1e-12)
    v, _, g = learner.value_and_lie(torch.tensor(X), create_graph=False)
    Vx = V.casadi(x)
    F = ca.Function("V", [x], [ca.vertcat(Vx, ca.gradient(Vx, x))])
    ref = _casadi_eval(F, X)[:, :, 0]
    _close(v.detach().numpy(), ref[:, 0])
    _close(g.detach().numpy(), ref[:, 1:])
    jac0 = _private("_body_jacobian_at_zero", "nlyap_opt.candidates.learning")
    J = jac0(learner.V.body, s.nx)
    H = (2 * (J.T @ J + learner.V.eps * torch.eye(s.nx, dtype=torch.float64))).detach().numpy()
    H_ref = np.array(ca.Function("H", [x], [ca.hessian(Vx, x)[0]])(np.zeros(s.nx)), dtype=float)
    _close(H, H_ref, 1e-12)


def test_dynamics_levenberg_marquardt_forward_equals_casadi():
    """``phi_training.LevenbergMarquardt._forward`` (w1·tanh(W0 z + b0) + b1 in numpy) ≡
    ``Network.casadi`` of the same weights, and ``phi_training.assemble`` (normalisation folded
    into one network) ≡ σ·(block forward on normalised inputs) + μ."""
    lm_cls = _private("LevenbergMarquardt", "nlyap_opt.learned.phi_training")
    assemble = _private("assemble", "nlyap_opt.learned.phi_training")
    rng = np.random.default_rng(5)
    d, H, m = 3, 6, 2
    centre, radius = rng.uniform(-1, 1, d), rng.uniform(0.5, 3, d)
    mu, sigma = rng.uniform(-1, 1, m), rng.uniform(0.5, 2, m)
    Z = rng.uniform(-1, 1, (40, d)) * radius + centre
    Zn = (Z - centre) / radius
    blocks, per_block = [], []
    for _ in range(m):
        lm = lm_cls(Zn, np.zeros(len(Zn)), H)
        th = rng.standard_normal(H * (d + 2) + 1)
        W0, b0, w1, b1 = lm.unpack(th)
        blocks.append((W0, b0, w1, b1))
        T, r = lm._forward(th)
        net = Network([Layer(W0, b0, "tanh"), Layer(w1[None, :], b1, "linear")])
        x = ca.SX.sym("z", d)
        _close(r, _casadi_eval(ca.Function("p", [x], [net.casadi(x)]), Zn)[:, 0, 0])
        per_block.append(r)
    net = assemble(blocks, centre, radius, mu, sigma)
    want = np.stack([sigma[k] * per_block[k] + mu[k] for k in range(m)], axis=1)
    x = ca.SX.sym("z", d)
    _close(_casadi_eval(ca.Function("p", [x], [net.casadi(x)]), Z)[:, :, 0], want, 1e-12)


def test_bounds_phi_derivatives_equal_casadi_derivatives():
    """``ErrorModel._phi_derivatives`` (explicit J_φ and ∂²φ/∂z_i² of one tanh layer) ≡
    CasADi ``jacobian`` / ``hessian`` of ``Network.casadi``."""
    error_model = _private("ErrorModel", "nlyap_opt.learned.error_models",
                           "nlyap_opt.learned.bounds")
    s = systems.get("van_der_pol")
    for scale in ("one", "vector"):
        net = _build(2, 8, "tanh", scale, None, n_in=s.nx, n_out=s.nx, seed=6)
        em = error_model(s, net, [[-2.0, 2.0]] * s.nx)
        z = ca.MX.sym("z", s.nx)
        J, D2 = em._phi_derivatives(z)
        Z = np.random.default_rng(6).uniform(-2, 2, (30, s.nx))
        got_J = _casadi_eval(ca.Function("J", [z], [J]), Z)
        got_D2 = _casadi_eval(ca.Function("D2", [z], [D2]), Z)
        zs = ca.SX.sym("z", s.nx)
        phi = net.casadi(zs)
        want_J = _casadi_eval(ca.Function("J", [zs], [ca.jacobian(phi, zs)]), Z)
        d2 = ca.vertcat(*[ca.diag(ca.hessian(phi[i], zs)[0]).T for i in range(s.nx)])
        want_D2 = _casadi_eval(ca.Function("D2", [zs], [d2]), Z)
        _close(got_J, want_J)
        _close(got_D2, want_D2)


@pytest.mark.parametrize("act", ["tanh", "sigmoid", "linear"])
def test_bounds_controller_enclosure_contains_the_network(act):
    """``bounds._controller_enclosure`` (pre-activation by intervals, saturating activation
    clamped) encloses ``Network.numpy`` on every box."""
    enclosure = _private("_controller_enclosure", "nlyap_opt.learned.bounds")
    rng = np.random.default_rng(8)
    net = Network([Layer(rng.uniform(-3, 3, (2, 2)), rng.uniform(-1, 1, 2), act)],
                  [2.0, -0.5])
    lo = rng.uniform(-2, 1.5, (16, 2))
    hi = lo + rng.uniform(0.01, 0.5, (16, 2))
    elo, ehi = enclosure(net, lo, hi)
    t = rng.random((200, 1, 2))
    pts = lo[None] + t * (hi - lo)[None]          # (200, 16, 2) points inside the boxes
    vals = net.numpy(pts)
    assert np.all(vals >= elo[None]) and np.all(vals <= ehi[None])
    if act != "linear":
        cap = np.abs(net.output_scale)  # |C·σ| ≤ |C| for tanh and sigmoid
        assert np.all(np.abs(elo) <= cap) and np.all(np.abs(ehi) <= cap)


def test_network_error_bound_covers_numpy_rounding():
    """``dynamics.network_error_bound`` ≥ |Network.numpy(z) − φ(z)| with φ evaluated exactly
    (mpmath, 50 digits) on random points of the box."""
    mpmath = pytest.importorskip("mpmath", reason="mpmath (dev extra) is needed for the exact "
                                 "reference")
    bound_fn = _private("network_error_bound", "nlyap_opt.learned.dynamics")
    net = _build(2, 12, "tanh", "vector", None, n_in=3, n_out=2, seed=11)
    zmax = np.array([2.0, 1.0, 3.0])
    Z = np.random.default_rng(11).uniform(-1, 1, (40, 3)) * zmax
    bound = bound_fn(net, zmax)
    (l0, l1), c = net.layers, net.output_scale
    mpmath.mp.dps = 50
    got = net.numpy(Z)
    for z, y in zip(Z, got):
        for i in range(2):
            exact = mpmath.mpf(c[i]) * (mpmath.fsum(
                mpmath.mpf(l1.weight[i, j]) * mpmath.tanh(mpmath.fsum(
                    mpmath.mpf(l0.weight[j, k]) * mpmath.mpf(z[k]) for k in range(3))
                    + mpmath.mpf(l0.bias[j]))
                for j in range(12)) + mpmath.mpf(l1.bias[i]))
            assert abs(mpmath.mpf(y[i]) - exact) <= bound[i]
    assert np.all(bound < 1e-12)  # and the bound is not vacuous


def test_network_error_bound_covers_a_linear_neuron():
    """A φ block with the fixed linear neuron (input weights ~10⁻⁶, output weight ~10⁶,
    :func:`~nlyap_opt.learned.phi_training.with_linear`): the rounding bound still covers
    the float evaluation against mpmath, and stays at the size of the output."""
    mpmath = pytest.importorskip("mpmath", reason="mpmath (dev extra) is needed for the exact "
                                 "reference")
    from nlyap_opt.learned.phi_training import assemble, with_linear
    bound_fn = _private("network_error_bound", "nlyap_opt.learned.dynamics")
    rng = np.random.default_rng(5)
    block = (rng.uniform(-1, 1, (4, 2)), rng.uniform(-1, 1, 4), 1e-3 * rng.uniform(-1, 1, 4),
             np.array([0.0]))
    a = np.array([-3980.0, 2400.0])
    net = assemble([with_linear(block, (a, 0.5, 2.0))], np.zeros(2), np.ones(2),
                   np.array([0.0]), np.array([1.0]))
    zmax = np.ones(2)
    bound = bound_fn(net, zmax)
    Z = rng.uniform(-1, 1, (40, 2))
    got = net.numpy(Z)
    (l0, l1), c = net.layers, net.output_scale
    mpmath.mp.dps = 60
    worst = 0
    for z, y in zip(Z, got):
        exact = mpmath.mpf(np.ravel(c)[0]) * (mpmath.fsum(
            mpmath.mpf(l1.weight[0, j]) * mpmath.tanh(mpmath.fsum(
                mpmath.mpf(l0.weight[j, k]) * mpmath.mpf(z[k]) for k in range(2))
                + mpmath.mpf(l0.bias[j])) for j in range(5)) + mpmath.mpf(l1.bias[0]))
        err = abs(mpmath.mpf(y[0]) - exact)
        worst = max(worst, err)
        assert err <= bound[0]
        # the neuron is the affine map within 3.4e-13·‖a‖₁ (plus the trained neurons)
        lin = a @ z + 0.5
        assert abs(float(exact) - lin) <= 3.4e-13 * np.sum(np.abs(a)) + 2 * 4 * 1e-3
    assert bound[0] < 1e-9 * np.sum(np.abs(a))   # not the 1e6 output weight times 8u


def test_network_error_bound_covers_subnormal_pre_activations():
    """Input weights of 2⁻¹⁰⁷⁴ (each product w·z rounds by half a subnormal step) and an
    output weight of 10³⁰⁰: the bound still covers the float evaluation (mpmath)."""
    mpmath = pytest.importorskip("mpmath", reason="mpmath (dev extra) is needed for the exact "
                                 "reference")
    bound_fn = _private("network_error_bound", "nlyap_opt.learned.dynamics")
    mpmath.mp.prec = 2000
    for n, zval in ((10, 0.49), (10, 0.51), (16, 0.49)):
        W0 = np.full((1, n), 2.0**-1074)
        net = Network([Layer(W0, np.zeros(1), "tanh"),
                       Layer(np.array([[1e300]]), np.zeros(1), "linear")])
        bound = bound_fn(net, np.full(n, zval))[0]
        z = np.full(n, zval)
        got = net.numpy(z[None, :])[0, 0]
        exact = mpmath.mpf(1e300) * mpmath.tanh(mpmath.fsum(
            mpmath.mpf(W0[0, k]) * mpmath.mpf(z[k]) for k in range(n)))
        assert abs(mpmath.mpf(got) - exact) <= bound


# ============================================================================ network files
def _good() -> dict:
    net = Network([Layer([[1.0, 2.0], [0.5, -1.0], [0.0, 3.0]], [0.1, 0.2, 0.3], "tanh"),
                   Layer([[1.0, -1.0, 0.5]], [0.0], "linear")], 1.5,
                  {"kind": "test"}, {"type": "sum_of_squares", "eps": 0.001})
    return net.to_dict()


def _set(path, value):
    def mutate(d):
        obj = d
        for key in path[:-1]:
            obj = obj[key]
        obj[path[-1]] = value
        return d
    return mutate


def _drop(path):
    def mutate(d):
        obj = d
        for key in path[:-1]:
            obj = obj[key]
        del obj[path[-1]]
        return d
    return mutate


# (label, mutation of the good dict or raw text, layer named in the message (or None),
#  regex the message must match: the problem and the fix)
BAD_FILES = [
    ("list, not object", "[1, 2]", None, r"expected a JSON object.*got a list"),
    ("number, not object", "3.5", None, r"expected a JSON object.*got a number"),
    ("string, not object", '"layers"', None, r"expected a JSON object.*got a string"),
    ("null", "null", None, r"expected a JSON object.*got null"),
    ("empty file", "", None, r"not valid JSON.*re-save"),
    ("truncated", "TRUNCATE", None, r"not valid JSON.*truncated.*re-save"),
    ("deep nesting", "[" * 200_000 + "]" * 200_000, None, r"(nested too deeply|not valid)"),
    ("NaN", "NAN", None, r"NaN.*finite"),
    ("Infinity", "INF", None, r"Infinity.*finite"),
    ("overflowing literal", "HUGE", 1, r"weight\[0\]\[1\].*finite number"),
    ("missing layers", _drop(["layers"]), None, r"malformed: missing key 'layers'"),
    ("layers not a list", _set(["layers"], {"weight": [[1.0]]}), None,
     r"'layers' is an object, expected a list"),
    ("empty layers", _set(["layers"], []), None, r"'layers' is empty.*at least one layer"),
    ("layer not an object", _set(["layers", 1], [[1.0, 2.0, 3.0]]), 1,
     r"is a list, expected an object with keys 'weight', 'bias', 'activation'"),
    ("missing weight", _drop(["layers", 1, "weight"]), 1, r"missing key 'weight'; add"),
    ("missing bias", _drop(["layers", 0, "bias"]), 0, r"missing key 'bias'; add"),
    ("missing activation", _drop(["layers", 1, "activation"]), 1,
     r"missing key 'activation'.*\"linear\""),
    ("unknown layer key", _set(["layers", 0, "activaton"], "tanh"), 0,
     r"unknown key 'activaton'; did you mean 'activation'"),
    ("unknown top-level key", _set(["output_scal"], 2.0), None,
     r"unknown key 'output_scal'; did you mean 'output_scale'"),
    ("ragged weight", _set(["layers", 0, "weight"], [[1.0, 2.0], [0.5], [0.0, 3.0]]), 0,
     r"ragged: row 1 has 1 entries, row 0 has 2"),
    ("weight 1-D", _set(["layers", 1, "weight"], [1.0, -1.0, 0.5]), 1,
     r"weight\[0\] is a number, expected a row"),
    ("weight 3-D", _set(["layers", 1, "weight"], [[[1.0], [-1.0], [0.5]]]), 1,
     r"weight\[0\]\[0\] is a list.*expected a number"),
    ("weight object", _set(["layers", 0, "weight"], {"0": [1.0, 2.0]}), 0,
     r"weight is an object, expected a non-empty list of rows"),
    ("string in weight", _set(["layers", 0, "weight", 1, 0], "0.5"), 0,
     r"weight\[1\]\[0\] is a string.*expected a number"),
    ("bool in weight", _set(["layers", 1, "weight", 0, 2], True), 1,
     r"weight\[0\]\[2\] is a boolean.*expected a number"),
    ("null in weight", _set(["layers", 1, "weight", 0, 0], None), 1,
     r"weight\[0\]\[0\] is null.*expected a number"),
    ("string in bias", _set(["layers", 0, "bias", 2], "x"), 0,
     r"bias\[2\] is a string.*expected a number"),
    ("bool bias", _set(["layers", 1, "bias"], [False]), 1, r"bias\[0\] is a boolean"),
    ("bias not a list", _set(["layers", 1, "bias"], 0.0), 1,
     r"bias is a number, expected a list of numbers"),
    ("empty weight", _set(["layers", 0, "weight"], []), 0,
     r"weight is an empty list, expected a non-empty list"),
    ("empty weight row", _set(["layers", 1, "weight"], [[]]), 1, r"weight\[0\] is empty"),
    ("empty bias", _set(["layers", 1, "bias"], []), 1, r"bias is empty"),
    ("unknown activation", _set(["layers", 0, "activation"], "swish"), 0,
     r"activation 'swish' is not supported; use one of tanh, relu, sigmoid, linear"),
    ("activation not a string", _set(["layers", 0, "activation"], 1), 0,
     r"activation 1 is not supported; use one of"),
    ("bias length", _set(["layers", 0, "bias"], [0.1, 0.2]), 0,
     r"bias has 2 entries but weight has 3 rows"),
    ("layers do not chain", _set(["layers", 1, "weight"], [[1.0, -1.0]]), 1,
     r"weight has 2 columns but layer 0 gives 3 outputs.*chain"),
    ("input_dim mismatch", _set(["input_dim"], 3), None,
     r"input_dim is 3 but layer 0's weight has 2 columns"),
    ("input_dim string", _set(["input_dim"], "2"), None, r"input_dim is '2'"),
    ("NaN-like scale", _set(["output_scale"], "nan"), None, r"output_scale is a string"),
    ("scale length", _set(["output_scale"], [1.0, 2.0]), None,
     r"output_scale has 2 entries but the last layer gives 1 outputs"),
    ("head not an object", _set(["head"], "sum_of_squares"), None,
     r"head is a string, expected null or"),
    ("unknown head", _set(["head", "type"], "quadratic"), None,
     r"head type 'quadratic' is not supported; use one of sum_of_squares"),
    ("negative eps", _set(["head", "eps"], -1.0), None, r"head eps is -1.0, expected .* >= 0"),
    ("string eps", _set(["head", "eps"], "0.1"), None, r"head eps is a string"),
    ("meta not an object", _set(["meta"], [1]), None, r"meta is a list, expected an object"),
    ("wrong format", _set(["format"], "onnx"), None, r"format is 'onnx'.*not a network file"),
    ("wrong version", _set(["version"], 7), None, r"version is 7; this nlyap_opt reads version"),
]


def _write_bad(tmp_path, mutation) -> str:
    path = tmp_path / "bad net.json"
    good = json.dumps(_good(), indent=1)
    if mutation == "TRUNCATE":
        path.write_text(good[: len(good) // 2])
    elif mutation == "NAN":
        path.write_text(good.replace("0.5", "NaN", 1))
    elif mutation == "INF":
        path.write_text(good.replace("0.5", "-Infinity", 1))
    elif mutation == "HUGE":
        d = _good()
        d["layers"][1]["weight"][0][1] = "HUGE"
        path.write_text(json.dumps(d).replace('"HUGE"', "1e400"))
    elif isinstance(mutation, str):
        path.write_text(mutation)
    else:
        path.write_text(json.dumps(mutation(_good())))
    return path


@pytest.mark.parametrize("label,mutation,layer,pattern", BAD_FILES,
                         ids=[c[0] for c in BAD_FILES])
def test_bad_network_file_is_refused_in_one_line(label, mutation, layer, pattern, tmp_path):
    path = _write_bad(tmp_path, mutation)
    with pytest.raises(NetworkFileError) as info:
        Network.load(path)
    msg = str(info.value)
    assert "\n" not in msg and "Traceback" not in msg
    assert str(path) in msg, msg                       # names the file
    if layer is not None:
        assert f"layer {layer}:" in msg, msg           # names the layer
    assert re.search(pattern, msg), msg  # the problem and the fix
    assert isinstance(info.value, ValueError)


def test_good_file_loads_and_every_bad_case_differs_from_it(tmp_path):
    """The table's base file is valid (so each refusal is caused by its mutation)."""
    path = tmp_path / "good.json"
    path.write_text(json.dumps(_good()))
    net = Network.load(path)
    assert net.head == {"type": "sum_of_squares", "eps": 0.001} and net.n_in == 2
    # optional keys may be left out
    d = _good()
    for key in ("format", "version", "input_dim", "output_scale", "head", "meta"):
        del d[key]
    path.write_text(json.dumps(d))
    assert Network.load(path).head is None


def test_unreadable_network_files(tmp_path):
    with pytest.raises(NetworkFileError, match=r"cannot read network file .*missing\.json"):
        Network.load(tmp_path / "missing.json")
    with pytest.raises(NetworkFileError, match=r"cannot read network file"):
        Network.load(tmp_path)
    p = tmp_path / "latin1.json"
    p.write_bytes(b'{"layers": "\xff\xfe"}')
    with pytest.raises(NetworkFileError, match=r"cannot read network file .*latin1\.json"):
        Network.load(p)


def test_from_dict_names_its_source():
    with pytest.raises(NetworkFileError,
                       match=r"^V\.json \(in run\): layer 0: malformed: missing key 'weight'"):
        Network.from_dict({"layers": [{"bias": [0.0]}]}, "V.json (in run)")


@pytest.mark.parametrize("weight,bias,exc,pattern", [
    ([["1", "2"]], [0.0], DimensionError, "numbers only"),
    ([[True, False]], [0.0], DimensionError, "numbers only"),
    ([[1.0, 2.0], [3.0]], [0.0, 0.0], DimensionError, "rectangular|numbers only"),
    (np.ones((2, 2, 2)), [0.0, 0.0], DimensionError, "2-D"),
    (np.ones((0, 2)), [], DimensionError, "non-empty"),
    ([[1.0, np.nan]], [0.0], NetworkFileError, "finite"),
])
def test_layer_constructor_refuses_bad_arrays(weight, bias, exc, pattern):
    with pytest.raises(exc, match=pattern):
        Layer(weight, bias, "tanh")


def test_network_constructor_refuses_bad_heads_and_scales():
    layers = [Layer([[1.0, 2.0]], [0.0], "tanh")]
    with pytest.raises(UnsupportedLayerError, match="sum_of_squares"):
        Network(layers, head={"type": "cubic"})
    with pytest.raises(UnsupportedLayerError, match="must be None or a dict"):
        Network(layers, head="sum_of_squares")
    with pytest.raises(NetworkFileError, match="eps"):
        Network(layers, head={"type": "sum_of_squares", "eps": -1.0})
    with pytest.raises(DimensionError, match="output_scale"):
        Network(layers, output_scale=[1.0, 2.0])
    with pytest.raises(DimensionError, match="numbers only"):
        Network(layers, output_scale="2")
    # a vector scale with a head is the body's scale (one entry per body output)
    body = [Layer(np.eye(2), [0.0, 0.0], "tanh")]
    V = Network(body, [1.0, 3.0], head={"type": "sum_of_squares"})
    assert V.numpy(np.array([[0.0, 1.0]]))[0, 0] == pytest.approx(9 * math.tanh(1.0) ** 2)
