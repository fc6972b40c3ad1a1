r"""Learning a Lyapunov function and a controller (empirical Lyapunov risk, vectorised).

The candidate is :math:`V(x) = \|N(x) - N(0)\|^2 + \epsilon\|x\|^2` (the network format's
``sum_of_squares`` head): :math:`V(0) = 0` exactly and :math:`V > 0` away from the origin
*by construction*. The controller is :math:`\kappa(x) = C \tanh(Kx + b)` with ``b``
frozen at the solved equilibrium bias, so that :math:`f(0, \kappa(0)) = 0` for every ``K``.

The loss on a batch of states (METHOD §2.5, with the ROA-shaping terms written for a
target level ``1``)::

    C_dec · mean[ relu(∇V·g(x) + β + τ·V(x)) · 1{V(x) ≤ 1 + s} ] decrease (rate τ) where
                                                                   certified
  + C_in  · mean[ relu(V(x) - 1) · w_in(x) ]                     pull the level set outwards
  + C_out · mean[ relu(1 + s - V(x_r)) ]  on the outer sphere     containment (b)
  + C_grad· mean ‖∇V‖                                              keep M (and β = M·η) small
  + C_anc · ‖G − G_lqr‖²                                           keep κ's linearisation
                                                                   near the LQR gain

``V ≥ 0`` and ``V(0) = 0`` hold by construction, so the seed's hinge on ``−V`` and
``V(0)²`` terms are identically zero and left out.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field

import numpy as np
import torch

from .network import Layer, Network, dense_network, from_torch

__all__ = ["TrainConfig", "LyapunovLearner", "sample_ball", "sample_sphere"]


@dataclass
class TrainConfig:
    """Settings of :class:`LyapunovLearner` (all have defaults)."""

    hidden: list[int] = field(default_factory=lambda: [6])
    features: int = 3          # outputs of N in V = ||N(x) - N(0)||² + eps||x||²
    eps: float = 1e-3
    lr: float = 1e-2
    steps: int = 1000
    batch: int = 2048
    decay: float = 0.1         # τ: the hinge asks for dV/dt <= -β - τ·V (also near 0)
    level_slack: float = 0.1   # s, where the decrease is enforced beyond level 1
    w_decrease: float = 1.0
    w_inside: float = 0.5
    w_outside: float = 1.0
    w_grad: float = 0.0
    train_controller: bool = True
    w_anchor: float = 1.0      # penalty ‖G − G_lqr‖² keeping the gain near its LQR start
    seed: int = 0
    time_budget: float = 60.0
    threads: int = 1           # torch threads; small batches run fastest single-threaded


def sample_ball(n: int, dim: int, radius: float, rng: np.random.Generator,
                inner: float = 0.0) -> np.ndarray:
    """Uniform samples of the annulus ``inner ≤ ‖x‖ ≤ radius`` in ``dim`` dimensions."""
    d = rng.standard_normal((n, dim))
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    r = (inner**dim + (radius**dim - inner**dim) * rng.random(n)) ** (1.0 / dim)
    return d * r[:, None]


def sample_sphere(n: int, dim: int, radius: float, rng: np.random.Generator) -> np.ndarray:
    """Uniform samples of the sphere ``‖x‖ = radius``."""
    d = rng.standard_normal((n, dim))
    return radius * d / np.linalg.norm(d, axis=1, keepdims=True)


class LyapunovLearner:
    """Trains ``V`` (and ``κ``) on a vector field ``g(x, u)`` given in torch.

    Parameters
    ----------
    system : systems.System
    controller : Network or None
        Initial controller (one tanh layer with output scale ``C``); ``None`` for a
        fixed feedback / input-free system.
    dynamics : Network or None
        Learned ``φ``; ``None`` trains on the true ``f`` (the known-dynamics setting).
    config : TrainConfig
    """

    def __init__(self, system, controller: Network | None, dynamics: Network | None,
                 config: TrainConfig, V: Network | None = None):
        self.system, self.config = system, config
        torch.set_num_threads(config.threads)
        torch.manual_seed(config.seed)
        self.rng = np.random.default_rng(config.seed)
        if V is None:
            sizes = [system.nx, *config.hidden, config.features]
            V = dense_network(sizes, "tanh", seed=config.seed)
            V.head = {"type": "sum_of_squares", "eps": config.eps}
            V.__post_init__()
        self.V = V.torch_module()
        self.controller = controller
        self.k_module = None
        if controller is not None:
            if len(controller.layers) != 1 or controller.layers[0].activation != "tanh":
                raise ValueError("the controller must be one tanh layer: C·tanh(Kx + b)")
            L = controller.layers[0]
            self.b = torch.as_tensor(L.bias, dtype=torch.float64)          # frozen
            self.C = torch.as_tensor(np.broadcast_to(controller.output_scale, L.bias.shape).copy(),
                                     dtype=torch.float64)
            # train the gain in LQR units: κ(x) = C tanh(-G x / s + b), s = C (1 - tanh²b),
            # so that ∂κ/∂x(0) = -G (Adam's step is then relative to the LQR gain)
            self.slope = self.C * (1 - torch.tanh(self.b) ** 2)
            G0 = -torch.as_tensor(L.weight, dtype=torch.float64) * self.slope[:, None]
            self.G = torch.nn.Parameter(G0)
            self.G0 = G0.clone()
        self.dynamics = dynamics
        self.phi = dynamics.torch_module() if dynamics is not None else None
        if self.phi is not None:
            for p in self.phi.parameters():
                p.requires_grad_(False)
        params = list(self.V.parameters())
        if controller is not None and config.train_controller:
            params.append(self.G)
        self.opt = torch.optim.Adam(params, lr=config.lr)

    # ------------------------------------------------------------------ model pieces
    @property
    def K(self):
        """Pre-activation weights ``K'`` of ``C·tanh(K'x + b)``."""
        return -self.G / self.slope[:, None]

    def kappa(self, x):
        return self.C * torch.tanh(x @ self.K.T + self.b)

    def rhs(self, x):
        """``g(x, κ(x))`` in torch (learned φ completed with known components, or f)."""
        s = self.system
        if self.controller is not None:
            u = self.kappa(x)
        else:
            u = torch.as_tensor(s.u_eq, dtype=x.dtype).expand(x.shape[0], s.nu)
        if self.phi is None:
            return s.evaluate_torch(x, u)
        meta = self.dynamics.meta  # same two models as nlyap_opt.symbolic.learned_rhs
        learned = meta.get("learned_components")
        if meta.get("model", "full") == "control_affine":
            out = self.phi(x)
            if s.nu:
                B = torch.as_tensor(np.asarray(meta["input_matrix"], dtype=float)).reshape(
                    out.shape[1], s.nu)
                out = out + u @ B.T
        else:
            out = self.phi(torch.cat([x, u], dim=1))
        if learned is None or list(learned) == list(range(s.nx)):
            return out
        f = s.evaluate_torch(x, u)
        cols = [out[:, learned.index(i)] if i in learned else f[:, i] for i in range(s.nx)]
        return torch.stack(cols, dim=1)

    def value_and_lie(self, x, create_graph=True):
        x = x.requires_grad_(True)
        v = self.V(x)[:, 0]
        (g,) = torch.autograd.grad(v.sum(), x, create_graph=create_graph)
        return v, (g * self.rhs(x)).sum(1), g

    # ------------------------------------------------------------------ training
    def train(self, states: np.ndarray, sphere: np.ndarray, margin: float,
              counterexamples: np.ndarray | None = None, steps: int | None = None,
              inside_weight: np.ndarray | None = None, progress=None,
              eta_pointwise: float = 0.0) -> dict:
        """Run ``steps`` Adam steps; returns the last loss terms.

        ``inside_weight`` (per state, default 1) scales the pull of ``V ≤ 1`` (0 for
        states known not to converge). ``eta_pointwise`` adds ``η‖∇V(x)‖`` to the Lie
        derivative (the pointwise robust margin for learned dynamics).
        """
        cfg = self.config
        X = torch.as_tensor(states, dtype=torch.float64)
        W = (torch.ones(len(X), dtype=torch.float64) if inside_weight is None
             else torch.as_tensor(inside_weight, dtype=torch.float64))
        S = torch.as_tensor(sphere, dtype=torch.float64)
        CE = (torch.as_tensor(counterexamples, dtype=torch.float64)
              if counterexamples is not None and len(counterexamples) else None)
        steps = cfg.steps if steps is None else steps
        t0 = time.perf_counter()
        info = {}
        gen = torch.Generator().manual_seed(cfg.seed)
        for it in range(steps):
            idx = torch.randint(0, len(X), (min(cfg.batch, len(X)),), generator=gen)
            xb, wb = X[idx], W[idx]
            if CE is not None:
                cidx = torch.randint(0, len(CE), (min(cfg.batch // 4, len(CE)),),
                                     generator=gen)
                xb = torch.cat([xb, CE[cidx]])
                wb = torch.cat([wb, torch.ones(len(cidx), dtype=torch.float64)])
            v, lie, g = self.value_and_lie(xb.clone())
            active = (v <= 1.0 + cfg.level_slack).to(v.dtype)
            if eta_pointwise:
                lie = lie + eta_pointwise * g.norm(dim=1)
            dec = (torch.relu(lie + margin + cfg.decay * v) * active).mean()
            inside = (torch.relu(v - 1.0) * wb).mean()
            sidx = torch.randint(0, len(S), (min(cfg.batch // 4, len(S)),), generator=gen)
            vs = self.V(S[sidx])[:, 0]
            outside = torch.relu(1.0 + cfg.level_slack - vs).mean()
            loss = cfg.w_decrease * dec + cfg.w_inside * inside + cfg.w_outside * outside
            if cfg.w_grad:
                loss = loss + cfg.w_grad * g.norm(dim=1).mean()
            if self.controller is not None and cfg.train_controller and cfg.w_anchor:
                loss = loss + cfg.w_anchor * ((self.G - self.G0) ** 2).sum()
            self.opt.zero_grad()
            loss.backward()
            self.opt.step()
            info = {"loss": loss.item(), "decrease": dec.item(), "inside": inside.item(),
                    "outside": outside.item()}
            if progress is not None and (it % 100 == 0 or it == steps - 1):
                progress(it, info)
            if time.perf_counter() - t0 > cfg.time_budget:
                break
        info["steps"] = it + 1
        info["seconds"] = time.perf_counter() - t0
        return info

    # ------------------------------------------------------------------ export
    def export(self) -> tuple[Network, Network | None]:
        """The current ``V`` and ``κ`` as float64 Networks (the objects that get verified)."""
        V = from_torch(self.V)
        V.meta = {"kind": "lyapunov"}
        ctrl = None
        if self.controller is not None:
            ctrl = Network([Layer(self.K.detach().numpy().copy(), self.b.numpy().copy(),
                                  "tanh")], self.controller.output_scale,
                           {"kind": "controller", "form": "C*tanh(Kx+b)"})
        return V, ctrl
