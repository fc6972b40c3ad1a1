"""Condition (c) by the shell form: ``V̇_q < 0`` on ``E ∖ B_{ε_s}`` directly, and the
Jacobian form on the small ellipse around ``B_{ε_s}``.

The test system ``x' = −x + a·x·‖x‖²`` has, with ``P ∝ I``, ``V̇_q ∝ −2‖x‖²(1 − a‖x‖²)``
and a Jacobian whose largest eigenvalue is ``−1 + 3a‖x‖²`` (along ``x``). With
``a = 0.5/ε²`` the quadratic decreases on all of ``E = B_ε`` while ``P J + JᵀP`` is
indefinite near ``‖x‖ = ε``: the minors and Frobenius forms must be refuted there, the shell
form must prove (c). With ``a = 1.5/ε²`` the property is false (``V̇_q > 0`` for
``‖x‖² > 1/a``) and nothing may certify it, nor a saved shell claim on it.
"""

import casadi as ca
import numpy as np
import pytest

import systems
from nlyap_opt.certification.roa import (
    SHELL_FRACTION,
    InnerForm,
    InnerFormKind,
    certify_inner_ellipse,
)

EPS = 0.2


def _system(a: float, n: int = 2):
    x = ca.SX.sym("x", n)
    rhs = -x + a * x * ca.sumsqr(x)
    return systems.System("shell", x, None, rhs, state_box=[[-3.0, 3.0]] * n)


def _vdot(s, P, pts):
    F = ca.Function("f", [s.x], [s.f])
    f = np.array(F(pts.T), dtype=float).T
    return 2 * np.einsum("ij,jk,ik->i", pts, P, f)


def _points_in(P, level, n, rng, k=20000):
    d = rng.standard_normal((k, n))
    q = np.einsum("ij,jk,ik->i", d, P, d)
    return d * np.sqrt(level / q)[:, None] * rng.uniform(1e-3, 1, (k, 1))


@pytest.mark.parametrize("n", [2, 3])
def test_shell_proves_decrease_where_the_jacobian_forms_are_refuted(n):
    s = _system(0.5 / EPS**2, n)
    out = certify_inner_ellipse(s, None, EPS)
    assert out["status"] == "certified"
    eps_s = EPS * SHELL_FRACTION
    assert out["form"] == f"shell r={eps_s!r} + minors"
    P = np.asarray(out["P"])
    assert out["level"] >= np.linalg.eigvalsh(P)[-1] * EPS**2          # B_ε ⊆ E
    pts = _points_in(P, out["level"], n, np.random.default_rng(0))
    assert np.all(_vdot(s, P, pts) < 0)                                 # the truth on E
    # the Jacobian forms alone are refuted on E; the minors (exact at a point) at points
    # where P J + JᵀP is not ≺ 0
    Jf = ca.Function("J", [s.x], [ca.jacobian(s.f, s.x)])
    for form in ("frobenius", "minors"):
        alone = certify_inner_ellipse(s, None, EPS, P=P, form=form)
        assert alone["status"] == "inner ellipse counterexample"
    assert len(alone["result"].counterexamples)
    for ce in alone["result"].counterexamples:
        y = np.asarray(ce.point, dtype=float)
        Jy = np.array(Jf(y), dtype=float)
        assert np.linalg.eigvalsh(P @ Jy + Jy.T @ P)[-1] >= -1e-9


def test_false_property_is_not_certified_by_any_form():
    """a = 1.5/ε²: V̇_q > 0 on E near ‖x‖ = ε; the shell's counterexample is such a point."""
    s = _system(1.5 / EPS**2)
    out = certify_inner_ellipse(s, None, EPS)
    assert out["status"] != "certified"
    P = np.eye(2)
    shell = certify_inner_ellipse(s, None, EPS, P=P, form=f"shell r={EPS / 4!r} + minors")
    assert shell["status"] == "inner ellipse counterexample"
    pts = np.array([ce.point for ce in shell["result"].counterexamples])
    assert len(pts) and np.all(_vdot(s, P, pts) >= -1e-12)
    assert np.all(np.einsum("ij,ij->i", pts, pts) <= shell["level"] * (1 + 1e-9))


def test_saved_shell_claim_is_checked_again_and_tampering_is_refused():
    s = _system(0.5 / EPS**2)
    out = certify_inner_ellipse(s, None, EPS)
    again = certify_inner_ellipse(s, None, EPS, P=out["P"], form=out["form"])
    assert again["status"] == "certified" and again["form"] == out["form"]
    assert again["level"] == out["level"]
    # a shell needs 0 < r ≤ ε and a Jacobian form inside; anything else does not apply
    for bad in ("shell r=0.0 + minors", "shell r=nan + minors", "shell r=1..2 + minors",
                f"shell r={2 * EPS!r} + minors", "shell r=0.05 + shell r=0.01 + minors",
                "shell", "shell r=-0.05 + frobenius"):
        refused = certify_inner_ellipse(s, None, EPS, P=out["P"], form=bad)
        assert refused["status"] != "certified" and "does not apply" in refused["status"], bad
    # the inner ellipse is the Jacobian form's: r = ε makes the shell empty, and then the
    # minors must hold on all of E, which they do not
    whole = certify_inner_ellipse(s, None, EPS, P=out["P"], form=f"shell r={EPS!r} + minors")
    assert whole["status"] == "inner ellipse counterexample"


# --------------------------------------------------------------------------- the typed form
_STORED = ["minors", "frobenius", "shell r=0.05 + minors", "shell r=0.1 + frobenius",
           f"shell r={EPS * SHELL_FRACTION!r} + minors", "blow-up w=[1, 2, 2], m=4",
           "blow-up w=[1, 1], m=0"]


@pytest.mark.parametrize("text", _STORED)
def test_inner_form_reads_and_writes_the_stored_text(text):
    """``to_str`` gives back exactly the text of today's ``certificate.json`` files."""
    form = InnerForm.parse(text)
    assert form.to_str() == text and InnerForm.parse(form.to_str()) == form


def test_inner_form_parameters():
    shell = InnerForm.parse("shell r=0.025 + frobenius")
    assert (shell.kind, shell.radius, shell.core) == (InnerFormKind.SHELL, 0.025,
                                                      InnerFormKind.FROBENIUS)
    blow = InnerForm.parse("blow-up w=[1, 2, 2], m=4")
    assert (blow.kind, blow.weights, blow.order) == (InnerFormKind.BLOWUP, (1, 2, 2), 4)
    # random shells and blow-ups survive the round trip bit for bit
    rng = np.random.default_rng(0)
    for r in np.exp(rng.uniform(-30, 3, 50)):
        f = InnerForm(InnerFormKind.SHELL, radius=float(r), core=InnerFormKind.MINORS)
        assert InnerForm.parse(f.to_str()) == f and InnerForm.parse(f.to_str()).radius == r
    for _ in range(20):
        w = tuple(int(v) for v in rng.integers(1, 5, rng.integers(1, 6)))
        f = InnerForm(InnerFormKind.BLOWUP, weights=w, order=int(rng.integers(0, 9)))
        assert InnerForm.parse(f.to_str()) == f


@pytest.mark.parametrize("bad", ["", "shell", "Minors", "shell r=nan + minors",
                                 "shell r=inf + minors", "shell r=-1 + minors",
                                 "shell r=1..2 + minors", "shell r=0.05 + shell r=0.01 + minors",
                                 "shell r=0.05 + blow-up", "blow-up w=[], m=4",
                                 "blow-up w=[0, 1], m=4", "blow-up w=[1,,2], m=4",
                                 "blow-up w=[1, 2]", "minors + frobenius"])
def test_inner_form_refuses_what_it_cannot_read(bad):
    with pytest.raises(ValueError, match="not an inner-ellipse form.*expected 'minors'"):
        InnerForm.parse(bad)


def test_inner_form_is_frozen_and_checks_parameters():
    f = InnerForm(InnerFormKind.MINORS)
    with pytest.raises(AttributeError):
        f.kind = InnerFormKind.FROBENIUS
    with pytest.raises(ValueError, match="no parameters"):
        InnerForm(InnerFormKind.MINORS, radius=0.1)
    with pytest.raises(ValueError, match="minors or frobenius"):
        InnerForm(InnerFormKind.SHELL, radius=0.1, core=InnerFormKind.SHELL)


def test_condition_c_pays_for_an_equilibrium_off_the_origin(offset_equilibrium_loop):
    """The loop of the ``offset_equilibrium_loop`` fixture (equilibrium near x₀ = −238):
    PJ + JᵀP ≺ 0 holds on E, but E is not invariant; the forms of (c) must also beat
    2‖Pg(0)‖ on ∂E and refuse. A loop whose g(0) is exactly 0 still certifies."""
    from nlyap_opt.design.control import InnerStatus

    s, kappa = offset_equilibrium_loop
    x = ca.SX.sym("x", 2)
    for form in ("minors", "frobenius"):
        out = certify_inner_ellipse(s, kappa, 0.1, P=np.eye(2), form=form)
        assert out["verdict"] is not InnerStatus.CERTIFIED, form
    fine = systems.System("fine", x, None, ca.vertcat(-x[0], -x[1]), state_box=[[-2, 2]] * 2)
    assert certify_inner_ellipse(fine, None, 0.1, P=np.eye(2),
                                 form="minors")["verdict"] is InnerStatus.CERTIFIED
