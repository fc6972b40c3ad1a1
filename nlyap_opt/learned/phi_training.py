"""Training of the dynamics network φ: Adam, Levenberg–Marquardt, Lawson minimax rounds.

One learned component at a time, in normalised units: Adam on minibatches (cosine learning
rate, float32 by default, seeded), then Levenberg–Marquardt in float64 on all training nodes
(mean squared error, a small ridge on the hidden weights), then Lawson-reweighted LM rounds
that push down the *maximum* error (α is a maximum). Every budget is a count of steps or
iterations (never wall time: the same input must give the same φ on a loaded machine).
:func:`assemble` stacks the per-component blocks into one :class:`~nlyap_opt.kernel.network.Network`
in original units, exactly. The orchestration (data,
grid, α) is :func:`nlyap_opt.learned.dynamics.learn_dynamics`.
"""

from __future__ import annotations

import math
import sys
import time

import numpy as np
from scipy.linalg import LinAlgError, cho_factor, cho_solve
from threadpoolctl import threadpool_limits

from ..kernel import deps
from ..kernel.network import Layer, Network
from .dynamics_config import DynamicsConfig

__all__ = ["train_component", "polish", "assemble", "LevenbergMarquardt", "progress_bar",
           "linear_fit", "residual", "with_linear", "LINEAR_SCALE",
           "LINEAR_RESIDUAL_MAX"]


#: a learned component whose least-squares affine fit leaves a residual of at most this
#: fraction of its standard deviation (the fit explains ≥ 99.75 % of its variance: a linear or
#: nearly linear component) gets the fixed linear neuron of :func:`with_linear`; the others
#: are fitted by the neurons alone
LINEAR_RESIDUAL_MAX = 0.05
#: input scale of the linear neuron ``tanh(s aᵀz)/s`` (:func:`with_linear`): ``|s aᵀz| ≤``
#: this on the normalised box
LINEAR_SCALE = 1e-6


def linear_fit(zn, y) -> tuple[np.ndarray, float, float] | None:
    """``(a, c, r)``: the least-squares affine fit ``aᵀz + c ≈ y`` on the training nodes and
    the standard deviation ``r`` of its residual (1 where it is 0), when the fit explains the
    normalised target (standard deviation 1) up to ``r ≤`` :data:`LINEAR_RESIDUAL_MAX`;
    else ``None`` (the neurons then fit ``y`` itself). The neurons are trained on the
    residual divided by ``r``, in the units the training's settings (learning rate, LM
    ridge) are stated for."""
    A = np.column_stack([zn, np.ones(len(zn))])
    with threadpool_limits(limits=1, user_api="blas"):   # the same bits on any machine load
        coef = np.linalg.lstsq(A, y, rcond=None)[0]
        a, c = np.asarray(coef[:-1], dtype=float), float(coef[-1])
        r = float(np.std(y - (zn @ a + c)))
    if not r <= LINEAR_RESIDUAL_MAX * max(float(np.std(y)), 1e-300):
        return None
    return a, c, (r if r > 0 else 1.0)


def residual(zn, y, fit) -> np.ndarray:
    """The training target of the neurons: ``(y − aᵀz − c)/r`` for ``fit = (a, c, r)``,
    ``y`` itself for ``fit = None``."""
    if fit is None:
        return y
    a, c, r = fit
    with threadpool_limits(limits=1, user_api="blas"):
        return (y - (zn @ a + c)) / r


def with_linear(block, fit):
    """A block ``(W0, b0, w1, b1)`` trained on :func:`residual` with its scale ``r`` restored
    and the affine fit joined as one more tanh neuron, first: ``(1/s)·tanh(s aᵀz) + c`` with
    ``s =`` :data:`LINEAR_SCALE` ``/ ‖a‖₁`` (``fit = (a, c, r)``).

    On the normalised box (``|z_i| ≤ 1``) ``|s aᵀz| ≤ 10⁻⁶``, so the neuron is ``aᵀz``
    within ``s²|aᵀz|³/3 ≤ 3.4·10⁻¹³‖a‖₁``: φ carries a system's linear part (a stiff linear
    chain's thousands per second) exactly enough, the other neurons fit only what is
    nonlinear, and the neuron adds a curvature of order ``s‖a‖²`` to φ's second-order error
    bound. The neuron is fixed: training sees only the residual (joined to the optimised
    neurons its ``1/s`` output weight would make the least-squares problem ill-conditioned).
    Without a linear part (``a = 0``) the neuron is left out; ``fit = None`` returns the block.
    """
    if fit is None:
        return block
    a, c, r = fit
    W0, b0, w1, b1 = block
    w1, b1 = w1 * r, b1 * r
    norm = float(np.sum(np.abs(a)))
    if not norm > 0:
        return W0, b0, w1, b1 + c
    s = LINEAR_SCALE / norm
    return (np.vstack([s * np.asarray(a)[None, :], W0]), np.concatenate([[0.0], b0]),
            np.concatenate([[1.0 / s], w1]), b1 + c)


def train_component(zn, y, H, cfg: DynamicsConfig, seed, progress, history, desc, t_start):
    """Adam, then Levenberg–Marquardt, then minimax (Lawson) rounds, for one output."""
    torch = deps.torch()

    total = cfg.steps + cfg.lm_iterations + cfg.minimax_rounds * cfg.minimax_iterations
    bar = progress_bar(total, progress, desc)
    dtype = torch.float32 if cfg.train_dtype == "float32" else torch.float64
    with torch.random.fork_rng(devices=[]):  # seeded init without touching the caller's RNG
        torch.manual_seed(seed)
        net = torch.nn.Sequential(torch.nn.Linear(zn.shape[1], H), torch.nn.Tanh(),
                                  torch.nn.Linear(H, 1)).to(dtype)
    Z = torch.as_tensor(zn, dtype=dtype)
    Y = torch.as_tensor(y[:, None], dtype=dtype)
    gen = torch.Generator().manual_seed(seed)
    steps, bs = cfg.steps, min(cfg.batch_size, zn.shape[0])
    lr0, lr1 = cfg.lr, cfg.lr_final
    opt = torch.optim.Adam(net.parameters(), lr=lr0)
    perm, pos = torch.randperm(Z.shape[0], generator=gen), 0
    for step in range(steps):
        for g in opt.param_groups:  # cosine schedule lr0 -> lr1
            g["lr"] = lr1 + 0.5 * (lr0 - lr1) * (1 + math.cos(math.pi * step / steps))
        if pos + bs > Z.shape[0]:
            perm, pos = torch.randperm(Z.shape[0], generator=gen), 0
        idx = perm[pos:pos + bs]
        pos += bs
        loss = torch.mean((net(Z[idx]) - Y[idx]) ** 2)
        opt.zero_grad()
        loss.backward()
        opt.step()
        if bar is not None:
            bar.update(1)
        if step % 500 == 0 or step == steps - 1:
            history.append({"component": desc, "stage": "adam", "iteration": step,
                            "loss": loss.item(), "seconds": time.perf_counter() - t_start})
            if bar is not None:
                bar.set_postfix(stage="adam", loss=f"{loss.item():.2e}")
    theta = np.concatenate([net[0].weight.detach().double().numpy().ravel(),
                            net[0].bias.detach().double().numpy(),
                            net[2].weight.detach().double().numpy().ravel(),
                            net[2].bias.detach().double().numpy()])
    out = polish(zn, y, H, cfg, theta, bar, history, desc, t_start)
    if bar is not None:
        bar.close()
    return out


def polish(zn, y, H, cfg: DynamicsConfig, theta, bar, history, desc, t_start):
    """Levenberg–Marquardt, then Lawson minimax rounds; the weights with the least max error.

    NumPy's BLAS runs with ``cfg.threads`` threads here (restored on return), like torch:
    the normal equations JᵀJ are the whole cost, and BLAS threads that spin while other
    processes hold the cores made each iteration two to four times slower on a shared
    machine.
    """
    with threadpool_limits(limits=cfg.threads, user_api="blas"):
        return _polish(zn, y, H, cfg, theta, bar, history, desc, t_start)


def _polish(zn, y, H, cfg: DynamicsConfig, theta, bar, history, desc, t_start):
    lm = LevenbergMarquardt(zn, y, H, cfg.lm_ridge)
    theta = lm.run(theta, cfg.lm_iterations, None, bar, history, desc, "lm", t_start)
    weights = np.ones(zn.shape[0])
    best, best_err = theta, float(np.max(np.abs(lm.residual(theta))))
    for r in range(cfg.minimax_rounds):
        res = np.abs(lm.residual(theta))  # Lawson: weight up where the error is large
        weights = np.clip(weights * res / max(np.mean(res), 1e-300), 1e-6, None)
        weights = np.clip(weights / np.mean(weights), 1e-4, 1e4)
        theta = lm.run(theta, cfg.minimax_iterations, weights, bar, history, desc,
                       f"minimax{r}", t_start)
        err = float(np.max(np.abs(lm.residual(theta))))
        if err < best_err:  # Lawson rounds may oscillate: keep the best maximum error
            best, best_err = theta, err
    return lm.unpack(best)


class LevenbergMarquardt:
    """Levenberg–Marquardt (Marquardt scaling) for ``w1·tanh(W0 z + b0) + b1 ≈ y``, float64."""

    def __init__(self, Z: np.ndarray, y: np.ndarray, H: int, ridge: float = 0.0):
        self.Z, self.y, self.H = np.asarray(Z, float), np.asarray(y, float), H
        self.d = Z.shape[1]
        self.lam = 1e-3
        # ρ N ‖W0‖² keeps hidden slopes moderate: a steep neuron with a negligible output
        # weight costs nothing in the fit but ruins the curvature and Lipschitz bounds
        self.ridge = float(ridge) * Z.shape[0]

    def unpack(self, th):
        H, d = self.H, self.d
        return (th[:H * d].reshape(H, d), th[H * d:H * d + H], th[H * d + H:H * d + 2 * H],
                th[-1:])

    def _forward(self, th):
        W0, b0, w1, b1 = self.unpack(th)
        T = np.tanh(self.Z @ W0.T + b0)
        return T, T @ w1 + b1[0] - self.y

    def residual(self, th):
        return self._forward(th)[1]

    def run(self, th, iters, weights, bar, history, desc, stage, t_start):
        N, H, d = self.Z.shape[0], self.H, self.d
        w = np.ones(N) if weights is None else weights
        sw = np.sqrt(w)
        T, r = self._forward(th)
        nW = H * d
        L = float(np.sum(w * r * r)) + self.ridge * float(th[:nW] @ th[:nW])
        for it in range(iters):
            w1 = self.unpack(th)[2]
            A = (1.0 - T * T) * w1
            J = np.empty((N, H * (d + 2) + 1))
            J[:, :H * d] = (A[:, :, None] * self.Z[:, None, :]).reshape(N, H * d)
            J[:, H * d:H * d + H] = A
            J[:, H * d + H:H * d + 2 * H] = T
            J[:, -1] = 1.0
            J *= sw[:, None]
            G = J.T @ J
            g = J.T @ (r * sw)
            G[np.arange(nW), np.arange(nW)] += self.ridge
            g[:nW] += self.ridge * th[:nW]
            dg = np.diag(G).copy() + 1e-12
            improved = False
            while self.lam < 1e10:
                try:
                    step = cho_solve(cho_factor(G + self.lam * np.diag(dg)), g)
                except (LinAlgError, ValueError):
                    self.lam *= 10.0
                    continue
                th2 = th - step
                T2, r2 = self._forward(th2)
                L2 = float(np.sum(w * r2 * r2)) + self.ridge * float(th2[:nW] @ th2[:nW])
                if np.isfinite(L2) and L2 < L:
                    th, T, r, L = th2, T2, r2, L2
                    self.lam = max(self.lam / 3.0, 1e-12)
                    improved = True
                    break
                self.lam *= 4.0
            if bar is not None:
                bar.update(1)
            if it % 10 == 0 or it == iters - 1 or not improved:
                history.append({"component": desc, "stage": stage, "iteration": it,
                                "loss": float(L / np.sum(w)), "max_error": float(np.max(np.abs(r))),
                                "seconds": time.perf_counter() - t_start})
                if bar is not None:
                    bar.set_postfix(stage=stage, max_err=f"{np.max(np.abs(r)):.2e}")
            if not improved:
                self.lam = 1e-3
                break
        return th


def assemble(blocks, centre, radius, mu, sigma, prune: float = 0.0) -> Network:
    """One network from per-component blocks, in original units (normalisation folded in).

    Block ``k`` computes ``y_k = σ_k (w1_k · tanh(W0_k (z − c)/r + b0_k) + b1_k) + μ_k``; the
    hidden layers are stacked and the output layer is block-structured (exact). Neurons with
    ``|σ_k w1_j| ≤ prune`` are dropped (α is measured afterwards, on the saved network).
    """
    if prune > 0:
        kept = []
        for k, (W0, b0, w1, b1) in enumerate(blocks):
            keep = np.abs(sigma[k] * w1) > prune
            if not np.any(keep):
                keep[np.argmax(np.abs(w1))] = True
            kept.append((W0[keep], b0[keep], w1[keep], b1))
        blocks = kept
    W0 = np.vstack([b[0] for b in blocks]) / radius[None, :]
    b0 = np.concatenate([b[1] for b in blocks]) - W0 @ centre
    m, H = len(blocks), W0.shape[0]
    W1 = np.zeros((m, H))
    b1 = np.zeros(m)
    start = 0
    for k, (_, _, w1, bk) in enumerate(blocks):
        W1[k, start:start + w1.size] = sigma[k] * w1
        b1[k] = sigma[k] * bk[0] + mu[k]
        start += w1.size
    return Network([Layer(W0, b0, "tanh"), Layer(W1, b1, "linear")])


def _interactive() -> bool:
    """Standard error is a terminal, or this runs in a Jupyter kernel (whose bars tqdm
    draws as widgets)."""
    err = sys.stderr
    return bool(err is not None and getattr(err, "isatty", lambda: False)()) \
        or "ipykernel" in sys.modules


def progress_bar(total: int, enabled: bool, desc: str):
    """A progress bar on standard error, or ``None`` (not enabled, or standard error is
    neither a terminal nor a Jupyter kernel's: a log file gets no carriage-return
    updates)."""
    if not enabled or total <= 0 or not _interactive():
        return None
    try:
        tqdm = deps.tqdm()
    except ImportError:  # pragma: no cover
        return None
    return tqdm(total=total, desc=desc, leave=False, mininterval=0.5)
