"""Systems whose origin is not exponentially stable: the linearisation has a centre.

The defaults detect the centre (``systems.spec.centre_dimension``), choose a V family that
can decrease like ‖x‖⁴, an ε and condition (c)'s blow-up; the tests check the detection
against the spectrum, the chosen ``P``, weights and ε against the mathematics (V̇_q < 0 at
sampled points of the certified ellipse, the leading term of the blow-up), that a centre
made unstable (``x' = +x³``) is never certified, and that the examples certify with the
default settings.
"""

import json
import subprocess
import sys
from pathlib import Path

import casadi as ca
import numpy as np
import pytest

import systems
from nlyap_opt.candidates.quadratic import certify_quadratics
from nlyap_opt.certification.certificate import RoaProblem
from nlyap_opt.certification.roa import centre_lyapunov_matrix, certify_inner_ellipse
from nlyap_opt.design.control import quadratic_lyapunov
from nlyap_opt.interface.cli import main
from nlyap_opt.workflow.configs import make_config
from systems.spec import CENTRE_INNER_FRACTION, centre_dimension

EXAMPLES = Path(__file__).resolve().parents[1] / "examples"

def _model(f, n: int, nu: int = 0, box: float = 1.0):
    x, u = ca.SX.sym("x", n), ca.SX.sym("u", nu)
    return systems.System("t_centre", x, u if nu else None, ca.vertcat(*f(x, u)),
                          state_box=[[-box, box]] * n,
                          input_box=[[-1.0, 1.0]] * nu if nu else None)


def _centre_4d(sign: float = -1.0):
    """centre_4d.toml's system, x1' = sign·x1³ + x2 y1 (sign = +1: the centre unstable)."""
    def f(x, u):
        x1, x2, y1, y2 = (x[i] for i in range(4))
        return [sign * x1**3 + x2 * y1, -x2**3 - x1 * y1, -y1 + y2 + x1**2 / 2,
                -y1 - 2 * y2 + x2**2 / 2]
    return _model(f, 4)


def test_the_example_is_the_system_of_these_tests():
    s, t = systems.load_spec(EXAMPLES / "centre_4d.toml"), _centre_4d()
    pts = np.random.default_rng(0).uniform(-1, 1, (500, 4))
    np.testing.assert_allclose(s.evaluate(pts), t.evaluate(pts), rtol=1e-14, atol=1e-15)


@pytest.mark.parametrize("f, nu, want", [
    (lambda x, u: [-x[0] ** 3, -x[1]], 0, 1),                    # diag(0, -1)
    (lambda x, u: [x[1], -x[0] - x[1] ** 3], 0, 2),              # ±i: a centre, not 0
    (lambda x, u: [-x[0] + x[1] ** 2, -2 * x[1]], 0, 0),         # Hurwitz
    (lambda x, u: [x[0] ** 2, u[0]], 1, 1),                      # 0 that u cannot move
    (lambda x, u: [x[1], u[0]], 1, 0),                           # double 0, controllable
    (lambda x, u: [x[0], -x[1]], 0, 0),                          # unstable, no centre
])
def test_centre_dimension_counts_the_imaginary_axis_eigenvalues_no_input_moves(f, nu, want):
    s = _model(f, 2, nu)
    assert centre_dimension(s) == want
    lam = np.linalg.eigvals(s.A)
    if not nu:      # an autonomous system: exactly the spectrum on the axis
        assert want == int(np.sum(np.abs(lam.real) <= 1e-12))


def test_defaults_of_a_centre_choose_a_quartic_v_and_the_centre_quadratic():
    s = systems.load_spec(EXAMPLES / "centre_4d.toml")
    d = systems.default_run_settings(s)
    assert centre_dimension(s) == 2
    assert d["inner"] == pytest.approx(CENTRE_INNER_FRACTION * 1.0)
    assert d["train"]["activation"] == "square" and d["quadratic"] == ["centre"]
    assert d["cegis"]["sim_tol"] == d["inner"]
    cfg = make_config(s.name if s.name in systems.names() else _register(s), preset=None)
    assert cfg.train.activation == "square" and cfg.outer == 1.0   # the file's [run] on top
    # a system without a centre keeps the default method
    e = systems.default_run_settings(systems.load_spec(EXAMPLES / "small_eps_2d.toml"))
    assert "train" not in e and "quadratic" not in e and e["inner"] == pytest.approx(0.3)


def test_three_or_more_states_get_twice_the_cegis_iterations_a_centre_keeps_its_own():
    from nlyap_opt.workflow.configs import DEFAULT_CEGIS
    from systems.spec import ITERATIONS_3D

    assert ITERATIONS_3D == 2 * DEFAULT_CEGIS["iterations"]
    two = systems.default_run_settings(systems.load_spec(EXAMPLES / "small_eps_2d.toml"))
    three = systems.default_run_settings(systems.load_spec(EXAMPLES / "lorenz_controlled.toml"))
    assert "cegis" not in two and three["cegis"] == {"iterations": ITERATIONS_3D}
    s = systems.load_spec(EXAMPLES / "lorenz_controlled.toml")
    cfg = make_config(s.name if s.name in systems.names() else _register(s), preset=None)
    assert cfg.cegis.iterations == ITERATIONS_3D
    centre = systems.default_run_settings(systems.load_spec(EXAMPLES / "centre_4d.toml"))
    assert centre["cegis"]["iterations"] == 6


def _register(s):
    systems.register(s.name, lambda: s)
    return s.name


def _vdot(system, P, pts):
    return 2 * np.einsum("ij,jk,ik->i", pts, P, system.evaluate(pts))


def _in_ellipse(P, level, n, rng, k=40000):
    d = rng.standard_normal((k, n))
    q = np.einsum("ij,jk,ik->i", d, P, d)
    return d * np.sqrt(level / q)[:, None] * rng.uniform(1e-3, 1, (k, 1))


def test_the_chosen_p_weights_and_eps_are_consistent():
    """For the default ε of centre_4d, condition (c)'s blow-up certifies with the centre P,
    weights 1 on the centre and 2 on the stable states, order 4; and the mathematics agrees:
    V̇_q < 0 at sampled points of E, and V̇_q(r^w ⊙ u) / r⁴ tends to a negative limit."""
    s = _centre_4d()
    eps = systems.default_run_settings(systems.load_spec(EXAMPLES / "centre_4d.toml"))["inner"]
    out = certify_inner_ellipse(s, None, eps)
    assert out["status"] == "certified" and out["form"] == "blow-up w=[1, 1, 2, 2], m=4"
    P = np.asarray(out["P"])
    np.testing.assert_array_equal(P, centre_lyapunov_matrix(s.A))
    # P: identity on the centre, A_hhᵀP_h + P_h A_hh = −I on the stable block
    A_hh = s.A[2:, 2:]
    np.testing.assert_allclose(A_hh.T @ P[2:, 2:] + P[2:, 2:] @ A_hh, -np.eye(2), atol=1e-12)
    assert out["level"] >= np.linalg.eigvalsh(P)[-1] * eps**2          # B_ε ⊆ E
    rng = np.random.default_rng(3)
    assert np.all(_vdot(s, P, _in_ellipse(P, out["level"], 4, rng)) < 0)
    u = rng.uniform(-1, 1, (2000, 4))
    u[np.arange(2000), rng.integers(0, 4, 2000)] = rng.choice([-1.0, 1.0], 2000)
    w = np.array([1, 1, 2, 2])
    ratio = [_vdot(s, P, r**w * u) / r**4 for r in (1e-2, 1e-3)]
    assert np.all(ratio[1] < 0)
    np.testing.assert_allclose(ratio[0], ratio[1], rtol=0.05, atol=1e-3)   # the r⁴ term


def _quadratic(sign: float):
    s = _centre_4d(sign)
    p = RoaProblem(s, quadratic_lyapunov(np.eye(4)), None, inner=0.2, outer=1.0)
    cen, lyap = certify_quadratics(p, ["centre", "lyapunov"], box=np.array([[-1, 1]] * 4),
                                   n=9, log=lambda m: None)
    assert lyap.P is None                   # no Hurwitz linearisation: no Lyapunov P
    return s, cen


def test_centre_quadratic_certifies_the_example():
    """V = xᵀPx with the centre P: certified on the ball r = 1 (10 s); (a) sampled on the
    certified set."""
    s, cen = _quadratic(-1.0)
    assert cen.certified
    c, P = cen.certificate.level, cen.P
    x = np.random.default_rng(4).uniform(-1, 1, (200000, 4))
    r = np.linalg.norm(x, axis=1)
    x = x[(np.einsum("ij,jk,ik->i", x, P, x) <= c) & (r >= cen.certificate.inner)]
    assert len(x) > 1000 and np.all(_vdot(s, P, x) < 0)


def test_an_unstable_centre_has_no_inner_ellipse():
    """x1' = +x1³: the origin is unstable (V̇_q > 0 along x1); condition (c) is refused."""
    s = _centre_4d(1.0)
    x = np.zeros((5, 4))
    x[:, 0] = np.linspace(0.05, 0.2, 5)
    assert np.all(_vdot(s, centre_lyapunov_matrix(s.A), x) > 0)
    for eps in (0.05, 0.2):
        assert certify_inner_ellipse(s, None, eps)["status"] != "certified"


@pytest.mark.slow   # 60 s: every radius and level is refuted
def test_centre_quadratic_does_not_certify_the_unstable_mutation():
    _, cen = _quadratic(1.0)
    assert cen.P is not None and not cen.certified


@pytest.mark.slow   # about 4 minutes on the 2-core machine with other runs beside it
def test_centre_example_certifies_with_default_settings(tmp_path):
    out = tmp_path / "c4"
    assert main(["run", str(EXAMPLES / "centre_4d.toml"), "--known-dynamics",
                 "--out", str(out)]) == 0
    cert = json.loads((out / "certificate.json").read_text())
    assert cert["status"] == "certified"
    assert cert["inner_ellipse"]["form"].startswith("blow-up w=[1, 1, 2, 2]")
    assert cert["certified_area"] > 0 and cert["certified_points_converge_in_simulation"]


@pytest.mark.slow   # about 9 minutes (φ is learned first)
def test_small_eps_example_certifies_with_learned_dynamics(tmp_path):
    out = tmp_path / "s2"
    assert main(["run", str(EXAMPLES / "small_eps_2d.toml"), "--out", str(out)]) == 0
    cert = json.loads((out / "certificate.json").read_text())
    assert cert["status"] == "certified" and cert["setting"] == "learned"
    assert cert["inner_radius"] == pytest.approx(0.01)
    assert cert["certified_points_converge_in_simulation"]


@pytest.mark.slow   # minutes: the whole default run
def test_unstable_mutation_is_not_certified_with_default_settings(tmp_path):
    """centre_4d.toml with x1' = +x1³: the run ends without a certificate (exit 2)."""
    text = (EXAMPLES / "centre_4d.toml").read_text()
    assert 'x1 = "-x1^3 + x2*y1"' in text
    spec = tmp_path / "centre_4d_unstable.toml"
    spec.write_text(text.replace('x1 = "-x1^3 + x2*y1"', 'x1 = "x1^3 + x2*y1"')
                    .replace('name = "centre_4d"', 'name = "centre_4d_unstable"'))
    out = tmp_path / "bad"
    assert main(["run", str(spec), "--known-dynamics", "--out", str(out)]) == 2
    cert = json.loads((out / "certificate.json").read_text())
    assert cert["status"] != "certified"


@pytest.mark.parametrize("name, f, n, eps, certified", [
    # a centre that rotates: x1' = x2 - x1³, x2' = -x1 - x2³ (eigenvalues ±i)
    ("rotation", lambda x, u: [x[1] - x[0] ** 3, -x[0] - x[1] ** 3], 2, 0.3, True),
    ("rotation, unstable", lambda x, u: [x[1] + x[0] ** 3, -x[0] + x[1] ** 3], 2, 0.3, False),
    # a centre that drives a stable state linearly: the centre subspace is (1, 1)
    ("shear", lambda x, u: [-x[0] ** 3, -x[1] + x[0]], 2, 0.1, True),
    ("shear, unstable", lambda x, u: [x[0] ** 3, -x[1] + x[0]], 2, 0.1, False),
    ("rotation + shear", lambda x, u: [x[1] - x[0] ** 3, -x[0] - x[1] ** 3,
                                       -x[2] + x[0] ** 2 + x[1]], 3, 0.2, True),
])
def test_centres_off_the_axes_are_proved_exactly_when_true(name, f, n, eps, certified):
    """Rotating or sheared centres: the blow-up's order comes from exact rationals, the
    sheared box is verified to cover E. A certified E has V̇_q < 0 at sampled points; an
    unstable centre (V̇_q > 0 somewhere near 0) is never certified, and a saved claim is
    checked again without a search."""
    s = _model(f, n, box=3.0)
    out = certify_inner_ellipse(s, None, eps)
    assert (out["status"] == "certified") is certified, out["status"]
    P = np.asarray(out["P"])
    pts = _in_ellipse(P, max(out["level"], np.linalg.eigvalsh(P)[-1] * eps**2), n,
                      np.random.default_rng(5))
    vdot = _vdot(s, P, pts)
    assert bool(np.all(vdot < 0)) is certified
    if certified:
        assert out["form"].startswith("blow-up") and out["form"].endswith("m=4")
        again = certify_inner_ellipse(s, None, eps, P=P, form=out["form"])
        assert again["status"] == "certified" and again["level"] == out["level"]


def test_exact_polynomials_see_cancellations_that_floats_do_not():
    """0.1·x − x/10 is not 0 in the graph (0.1 is not 1/10) and x/3 − x/3 is: the exact
    expansion keeps the first (a tiny rational) and drops the second."""
    from fractions import Fraction

    from nlyap_opt.design.polynomial import exact_polynomials

    x = ca.SX.sym("x", 1)
    p, q = exact_polynomials(ca.Function("f", [x], [ca.vertcat(0.1 * x - x / 10,
                                                              x / 3 - x / 3 + x**2)]))
    assert list(p) == [(1,)] and p[(1,)] == Fraction(0.1) - Fraction(1, 10) != 0
    assert q == {(2,): Fraction(1)}
    assert exact_polynomials(ca.Function("g", [x], [ca.sin(x)])) is None


@pytest.mark.slow  # a run through the CLI up to its refusal (about 3 s)
def test_an_input_that_cannot_reach_the_centre_is_one_line_naming_the_fix(tmp_path):
    """centre_4d.toml with an input on y1 only: no LQR start; exit 3, one line."""
    text = (EXAMPLES / "centre_4d.toml").read_text()
    spec = tmp_path / "centre_input.toml"
    spec.write_text(text.replace('states = ["x1", "x2", "y1", "y2"]',
                                 'states = ["x1", "x2", "y1", "y2"]\ninputs = ["u"]\n'
                                 'input_box = [[-2.0, 2.0]]')
                    .replace('y1 = "-y1 + y2 + x1^2/2"', 'y1 = "-y1 + y2 + x1^2/2 + u"')
                    .replace('name = "centre_4d"', 'name = "centre_4d_input"'))
    s = systems.load_spec(spec)
    assert s.nu == 1 and centre_dimension(s) == 2
    res = subprocess.run([sys.executable, "-m", "nlyap_opt.interface.cli", "run", str(spec),
                          "--known-dynamics", "--out", str(tmp_path / "o")],
                         capture_output=True, text=True, timeout=300)
    assert res.returncode == 3
    lines = res.stderr.strip().splitlines()
    assert len(lines) == 1 and "2 eigenvalue(s) on the imaginary axis" in lines[0]
    assert "drop the inputs" in lines[0] and "Traceback" not in res.stderr


def test_learned_f_eps_along_a_centre_grows_like_the_cube_root_of_eta():
    """The ε that η affords along the centre (the true f stands in for φ here): raised
    only when η needs it, by about η^{1/3} (V̇_q ~ −‖x‖⁴ against η‖∇V_q‖ ~ η‖x‖); a fixed
    ε below it is one line naming the ε that would work."""
    from nlyap_opt.kernel.domain import Ball
    from nlyap_opt.kernel.errors import ConfigError
    from nlyap_opt.workflow.pipeline import _inner_for_margin

    s, D, said = _centre_4d(), Ball(1.0, 4), []
    assert _inner_for_margin(s, None, None, 1e-4, 1 / 6, D, True, said.append) == 1 / 6
    e1 = _inner_for_margin(s, None, None, 1e-3, 0.05, D, True, said.append)
    e8 = _inner_for_margin(s, None, None, 8e-3, 0.05, D, True, said.append)
    assert "chosen by the tool" in said[-1]
    assert 0.05 < e1 < e8 < 0.5
    assert 1.5 < e8 / e1 < 2.5          # (8)^{1/3} = 2, up to the radii's grid
    # the robust decrease fails (sampled) just inside e8 / 2 and holds beyond e8 / 2
    P = centre_lyapunov_matrix(s.A)
    d = np.random.default_rng(6).standard_normal((4000, 4))
    d /= np.linalg.norm(d, axis=1, keepdims=True)

    def worst(rho):
        x = rho * d
        return np.max(_vdot(s, P, x) + 8e-3 * np.linalg.norm(2 * x @ P, axis=1))

    assert worst(0.9 * e8 / 2) >= 0 > worst(1.2 * e8 / 2)
    with pytest.raises(ConfigError, match="inner = 0.05 cannot work") as exc:
        _inner_for_margin(s, None, None, 8e-3, 0.05, D, False, said.append)
    assert f"set inner to {e8:.3g} or more" in str(exc.value)
