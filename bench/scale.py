"""How the interval verifier scales with the state dimension and the network width.

Two tables:

- **dimension** (2, 3, 4, 6): the decrease condition (a) of a quadratic certificate
  ``V = xᵀPx`` of the linear LQR feedback ``u = u_eq − Kx`` on the true ``f``, on the ball
  ``‖x‖ ≤ r`` at the level ``c = 0.9·λ_min(P)·r²`` (the largest level kept inside the ball,
  up to 10 %), with ``ε = ½·sqrt(c / λ_max(P))`` (so ``B_ε ⊆ Ω_c``). Systems: reversed
  Van der Pol (2-D, ``P`` from ``A_clᵀP + PA_cl = −I``), the cartpole without its
  position (3-D: ``v, θ, ω``; ``p`` does not enter ``f``), the cartpole (4-D) and the planar
  quadrotor (6-D), ``P`` the Lyapunov matrix of :func:`nlyap_opt.design.control.lqr`
  (``A_clᵀP + PA_cl = −I``, ``Q = I``, ``R = I``). Same relative geometry in every
  dimension; a ``--max-boxes`` cap ends a query as ``unknown``. Each system is run three
  ways: the true ``f``; its closed-loop linearisation written as the certificate writes a
  Lie derivative, ``2(Px)·(A_cl x)``; and the same quadratic simplified to ``−xᵀx``. The
  gap between the last two is the interval dependency problem (``Px`` and ``A_cl x`` are
  enclosed independently). Two more rows run the true ``f`` with intervals only (the
  natural extension and the mean-value form, ``affine=False``: no linear relaxation) and
  with the verifier's second-order centred form (``verify(..., second_order=True)``), which
  the 4-D and 6-D presets use.
- **width** (8, 16, 32, [64]): Van der Pol, ``V(x) = ‖N(x) − N(0)‖²`` with a one-hidden-
  layer tanh network ``N`` whose first ``n`` neurons carry ``a·Lx`` (``LᵀL = P``, read back
  by the output layer with ``1/a``) and the other ``width − n`` are random with output
  weights ``δ``: a true Lyapunov function close to ``xᵀPx`` in which every neuron enters
  the enclosures. Annulus ``0.1 ≤ ‖x‖ ≤ 0.6``, level ``0.9·min V`` on the outer circle
  (sampled). Each width runs with the linear relaxation (the default) and with intervals
  only (``affine=False``).

Figures only (no assertions); run ``python bench/scale.py [--max-boxes N] [--widths ...]``.
"""

from __future__ import annotations

import argparse
import time

import casadi as ca
import numpy as np

import systems
from nlyap_opt.certification.certificate import RoaProblem
from nlyap_opt.design.control import linear_controller, lqr, lyapunov_matrix, quadratic_lyapunov
from nlyap_opt.kernel.network import Layer, Network
from verification import lyapunov_problem, verify

__all__ = ["cartpole_reduced", "dimension_rows", "quadratic_queries", "width_rows", "main"]


def cartpole_reduced() -> systems.System:
    """The cartpole without the cart position: states ``(v, θ, ω)`` (3-D)."""
    cp = systems.get("cartpole")
    y = ca.SX.sym("y", 3)
    f = ca.substitute(cp.f, cp.x, ca.vertcat(0, y))[1:]
    f = ca.substitute(f, cp.x, ca.vertcat(0, y))
    u = ca.SX.sym("u", 1)
    f = ca.substitute(f, cp.u, u)
    return systems.System("cartpole_reduced", y, u, f, state_box=[[-1, 1]] * 3,
                          input_box=cp.input_box, u_eq=[0.0],
                          state_names=["v", "theta", "omega"], input_names=["force"])


def quadratic_queries(system, r: float):
    """``({variant: problem}, cond P, ε, c)`` of the dimension table.

    Variants of the decrease condition on the same region: ``true f`` (the certificate's
    ``∇V·f(x, u_eq − Kx)``), ``linear, as 2(Px)·(A_cl x)`` (the closed-loop linearisation,
    written as the certificate writes a Lie derivative) and ``linear, as −xᵀx`` (the same
    function, simplified: ``A_clᵀP + PA_cl = −I``).
    """
    if system.nu:
        res = lqr(system)
        ctrl, P = linear_controller(system, res.K), res.P
        A_cl = system.A - system.B @ res.K
    else:
        ctrl, A_cl = None, system.A
        P = lyapunov_matrix(A_cl)
    ev = np.linalg.eigvalsh(P)
    c = 0.9 * ev[0] * r**2
    eps = 0.5 * np.sqrt(c / ev[-1])
    dec = RoaProblem(system, quadratic_lyapunov(P), ctrl, inner=eps, outer=r).decrease()
    x = dec.x
    Px = ca.mtimes(ca.DM(P), x)
    lies = {"true f": dec.lie,
            "linear, as 2(Px)·(A_cl x)": 2 * ca.dot(Px, ca.mtimes(ca.DM(A_cl), x)),
            "linear, as −xᵀx": -ca.sumsqr(x)}
    probs = {k: lyapunov_problem(x, dec.V, lie, inner=eps, outer=r, level=c,
                                 check_positive=False)  # V > 0 by construction (P ≻ 0)
             for k, lie in lies.items()}
    return probs, ev[-1] / ev[0], eps, c


def _run(vp, max_boxes: int, **options) -> dict:
    t0 = time.perf_counter()
    res = verify(vp, max_boxes=max_boxes, **options)
    sec = time.perf_counter() - t0
    return {"status": res.status, "boxes": int(res.boxes), "seconds": sec,
            "boxes_per_s": res.boxes / sec if sec > 0 else float("nan"), "depth": res.depth}


def dimension_rows(max_boxes: int = 1_000_000, r: float = 0.1,
                   names=("van_der_pol", "cartpole_reduced", "cartpole", "planar_quadrotor"),
                   log=print) -> list[dict]:
    """Rows of the dimension table: one per system and decrease variant."""
    rows = []
    for name in names:
        s = cartpole_reduced() if name == "cartpole_reduced" else systems.get(name)
        probs, cp, eps, c = quadratic_queries(s, r)
        runs = {k: (lambda vp=vp: _run(vp, max_boxes)) for k, vp in probs.items()}
        runs["true f, intervals only"] = lambda vp=probs["true f"]: _run(
            vp, max_boxes, affine=False)
        runs["true f, second-order form"] = lambda vp=probs["true f"]: _run(
            vp, max_boxes, second_order=True)
        for variant, fn in runs.items():
            try:
                out = fn()
            except Exception as err:  # a verifier under development must not end the table
                out = {"status": f"error: {type(err).__name__}: {err}"[:60], "boxes": 0,
                       "seconds": 0.0, "boxes_per_s": float("nan"), "depth": 0}
            row = {"system": name, "n": s.nx, "variant": variant, "cond_P": cp, "eps": eps,
                   "level": c, **out}
            log(f"  {name} ({variant}): {row['status']} in {row['seconds']:.1f} s, "
                f"{row['boxes']} boxes")
            rows.append(row)
    return rows


def _width_network(P: np.ndarray, width: int, *, a: float = 0.3, delta: float = 0.1,
                   seed: int = 0) -> Network:
    n = P.shape[0]
    L = np.linalg.cholesky(P).T  # LᵀL = P
    rng = np.random.default_rng(seed)
    W1 = np.vstack([a * L, rng.normal(0, 1.0, (width - n, n))])
    b1 = np.concatenate([np.zeros(n), rng.uniform(-0.5, 0.5, width - n)])
    W2 = np.hstack([np.eye(n) / a, np.zeros((n, width - n))])
    W2 = W2 + np.hstack([np.zeros((n, n)), delta * rng.normal(0, 1.0, (n, width - n))
                         / np.sqrt(width)])
    return Network([Layer(W1, b1, "tanh"), Layer(W2, np.zeros(n), "linear")],
                   head={"type": "sum_of_squares", "eps": 0.0})


def width_rows(widths=(8, 16, 32), max_boxes: int = 1_000_000, inner: float = 0.1,
               outer: float = 0.6, log=print) -> list[dict]:
    """One row per network width of the width table (Van der Pol)."""
    s = systems.get("van_der_pol")
    P = lyapunov_matrix(s.A)
    rows = []
    for w in widths:
        V = _width_network(P, w)
        th = np.linspace(0, 2 * np.pi, 4001)
        ring = outer * np.stack([np.cos(th), np.sin(th)], axis=1)
        c = 0.9 * float(np.min(V.numpy(ring)))
        prob = RoaProblem(s, V, None, inner=inner, outer=outer)
        dec = prob.decrease()
        vp = lyapunov_problem(dec.x, dec.V, dec.lie, inner=inner, outer=outer, level=c,
                              check_positive=False)
        for how, opts in (("linear relaxation", {}), ("intervals only", {"affine": False})):
            row = {"system": "van_der_pol", "width": w, "level": c, "bound": how,
                   **_run(vp, max_boxes, **opts)}
            log(f"  width {w} ({how}): {row['status']} in {row['seconds']:.2f} s, "
                f"{row['boxes']} boxes")
            rows.append(row)
    return rows


def main(argv=None) -> None:
    """Print both tables (Markdown)."""
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--max-boxes", type=int, default=1_000_000)
    ap.add_argument("--radius", type=float, default=0.1, help="r of the dimension table")
    ap.add_argument("--widths", type=int, nargs="*", default=[8, 16, 32, 64])
    ap.add_argument("--skip-dimension", action="store_true")
    args = ap.parse_args(argv)
    if not args.skip_dimension:
        print(f"## dimension (quadratic V of LQR, r = {args.radius:g}, "
              f"max {args.max_boxes} boxes)")
        rows = dimension_rows(args.max_boxes, args.radius)
        print("| system | n | cond P | ε | decrease written as | status | boxes | s | boxes/s |")
        print("|---|---|---|---|---|---|---|---|---|")
        for r in rows:
            print(f"| {r['system']} | {r['n']} | {r['cond_P']:.0f} | {r['eps']:.2e} | "
                  f"{r['variant']} | {r['status']} | {r['boxes']} | {r['seconds']:.1f} | "
                  f"{r['boxes_per_s']:.0f} |")
    print(f"## width (Van der Pol, V = ‖N(x) − N(0)‖², max {args.max_boxes} boxes)")
    rows = width_rows(tuple(args.widths), args.max_boxes)
    print("| width | bound | status | boxes | s | boxes/s |")
    print("|---|---|---|---|---|---|")
    for r in rows:
        print(f"| {r['width']} | {r['bound']} | {r['status']} | {r['boxes']} | "
              f"{r['seconds']:.2f} | {r['boxes_per_s']:.0f} |")


if __name__ == "__main__":
    main()
