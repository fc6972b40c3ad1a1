r"""Learning a Lyapunov function and a controller (empirical Lyapunov risk, vectorised).

The candidate is :math:`V(x) = \|N(x) - N(0)\|^2 + \epsilon\|x\|^2` (the network format's
``sum_of_squares`` head): :math:`V(0) = 0` exactly and :math:`V > 0` away from the origin
*by construction*. The controller is :math:`\kappa(x) = C \tanh(Kx + b)` with ``b``
frozen at the solved equilibrium bias, so that :math:`f(0, \kappa(0)) = 0` for every ``K``.

The loss on a batch of states (the empirical Lyapunov risk, with the ROA-shaping terms written for a
target level ``1``)::

    C_dec · mean[ relu(∇V·g(x) + β + τ·V(x)) · 1{V(x) ≤ 1 + s} ] decrease (rate τ) where
                                                                   certified
  + C_in  · mean[ relu(V(x) - 1) · w_in(x) ]                     pull the level set outwards
  + C_out · mean[ relu(1 + s - V(x_r)) ]  on the outer sphere     containment (b)
  + C_grad· mean ‖∇V‖                                              keep M (and β = M·η) small
  + C_anc · ‖G − G_lqr‖²                                           keep κ's linearisation
                                                                   near the LQR gain
  + C_inw · mean[ relu(n·g(x) / ‖g(x)‖) ]  on ∂D (n outward)       κ turns the flow inward
                                                                   on ∂D where it can
  + C_loc · relu(λ_max(AᵀH + HA + 2τH)) / tr H                     first-order decrease at 0
                                                                   (H = ∇²V(0), A = ∂g/∂x(0))
  + C_fit · mean (V(x) − T(x))²                                    fit a target whose level
  + C_pde · mean (∇V·g / (−R(x)‖x‖²) − 1)²                         sets approach the ROA

``T`` is the simulated trajectory cost ``W(x) = ∫‖x(t)‖² dt`` of the model's closed loop,
rescaled so that ``T = 1`` at a high quantile of the converging states and capped
(:func:`nlyap_opt.candidates.cegis.cost_targets`): ``W`` decreases at rate ``‖x‖²`` along
trajectories and grows without bound towards the ROA boundary (a Zubov-type function),
so fitting it (value and decrease law ``Ṫ = −R‖x‖²``) puts the level sets of ``V`` close
to the boundary of the region of attraction. ``relative_decrease`` divides the hinge by
``‖x‖²`` so that states near the inner ball weigh as much as the rest.

The inward term acts on the controller only (the rest of the loss sees ``κ`` through ``g``):
a certified set lies in ``D`` and is forward invariant, so it holds only states whose
trajectories never leave ``D``; where a trajectory leaves ``D`` it crosses ``∂D`` with
``n·g > 0``. The term is the share of the flow's direction pointing out of ``D`` on
samples of ``∂D``; where the input cannot change ``n·g`` (``θ' = ω`` on the pendulum's
faces ``θ = ±4``) its gradient is zero.

``V ≥ 0`` and ``V(0) = 0`` hold by construction, so the seed's hinge on ``−V`` and
``V(0)²`` terms are identically zero and left out.
"""

from __future__ import annotations

import copy
import time
from dataclasses import dataclass, field

import numpy as np
import torch
from scipy.spatial import cKDTree

from ..design import sos_sdp
from ..kernel.determinism import deterministic_torch
from ..kernel.errors import ConfigError
from ..kernel.network import Layer, Network, dense_network, from_torch
from ..kernel.sampling import sample_ball, sample_sphere
from ..kernel.walker import ArrayArithmetic, evaluate

__all__ = ["TrainConfig", "TrainInfo", "LearnerState", "LyapunovLearner", "label_boundary_states",
           "sample_ball", "sample_sphere"]


@dataclass
class TrainInfo:
    """The loss terms of the last training step (:meth:`LyapunovLearner.train`).

    Attributes
    ----------
    loss, decrease, inside, outside : float
        The total loss and its decrease, ``V ≤ 1`` inside and ``V ≥ 1`` on the sphere terms.
    fit : float or None
        The fit to the targets (``None`` without targets).
    steps : int
        Steps run.
    seconds : float
    """

    loss: float = float("nan")
    decrease: float = float("nan")
    inside: float = float("nan")
    outside: float = float("nan")
    fit: float | None = None
    steps: int = 0
    seconds: float = 0.0


@dataclass
class TrainConfig:
    """Settings of :class:`LyapunovLearner` (all have defaults).

    Every budget is a count (``steps``); there is no wall-clock budget. With
    the same settings, seed and package versions, :meth:`LyapunovLearner.train` gives
    bit-identical weights on any machine load: it runs with ``threads`` torch threads and
    deterministic algorithms (:func:`nlyap_opt.kernel.determinism.deterministic_torch`).
    """

    hidden: list[int] = field(default_factory=lambda: [6])
    features: int = 3          # outputs of N in V = ||N(x) - N(0)||² + eps||x||²
    # of N's hidden layers: "tanh"; "square" (z²: V a polynomial, of degree 4 with one
    # hidden layer, as Fossil's square-activation V); "linear" (V a quadratic form)
    activation: str = "tanh"
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
    # κ: mean relu(n·g/‖g‖) on ∂D (n the outward normal): the closed loop turned inward on
    # ∂D where the input can do it (0: off)
    w_inward: float = 0.0
    w_fit: float = 0.0         # fit V to the trajectory-cost target (0: off)
    fit_quantile: float = 0.99  # target level 1 = this quantile of the converging states' cost
    fit_cap: float = 2.0       # target of states that do not converge (and cap of the rest)
    fit_transform: str = "log"  # "log" or "linear" (see nlyap_opt.candidates.cegis.cost_targets)
    w_pde: float = 0.0         # relative residual of the target's decrease law (0: off)
    # raise the fit target to (1 + level_slack)·g(x)^8 (g the domain's gauge, 1 on ∂D) where
    # that is larger: level sets inside D, as containment (b) needs, where the ROA leaves D
    fit_domain: bool = False
    w_local: float = 0.0       # first-order decrease at the origin (see local_violation)
    relative_decrease: bool = False  # divide the decrease hinge by ‖x‖²
    lr_schedule: str = "constant"  # or "cosine": lr → lr/100 over each train() call
    # where V starts: "random" (Glorot, seeded), or "quadratic": at the run's best certified
    # quadratic xᵀPx (config key quadratic), scaled so that V's level 1 is its certified set
    # (quadratic_start; one tanh hidden layer of at least nx neurons, features >= nx); or
    # "sos": at the run's certified SOS V of degree 2 or 4 (config section sos), exactly
    # (sos_start; one square hidden layer of at least nx(nx+3)/2 neurons)
    init: str = "random"
    seed: int = 0
    threads: int = 1           # torch threads while training (set and restored): fixed, so
    #                            that results do not depend on the machine; small batches
    #                            run fastest single-threaded


#: slope of the neurons that carry ``Lx`` in :func:`quadratic_start` (tanh(a·Lx)/a ≈ Lx)
QUADRATIC_START_SLOPE = 0.3


def check_start_architecture(init: str, nx: int, activation: str, hidden, features: int,
                             degree: int = 2) -> None:
    """Refuse a V architecture that cannot hold the warm start ``init`` (ConfigError naming
    what it needs): ``"quadratic"``: one tanh hidden layer of at least ``nx`` neurons,
    ``features >= nx`` (:func:`quadratic_start`); ``"sos"``: one square hidden layer of at
    least ``2·nx`` (degree 2) or ``nx(nx+3)/2`` (degree 4) neurons and ``features`` >= the
    number of monomials of degree 1..degree/2 (:func:`sos_start`)."""
    hidden = [hidden] if isinstance(hidden, int) else list(hidden)
    if init == "quadratic":
        act, need, feats = "tanh", nx, nx
    elif init == "sos":
        if degree not in (2, 4):
            raise ConfigError(f"train.init 'sos' needs an SOS V of degree 2 or 4 (one square "
                              f"layer holds a quadratic N(x)), got degree {degree}; set "
                              "sos.degree to 2 or 4 or use init 'random'")
        act = "square"
        need = 2 * nx + (nx * (nx - 1) // 2 if degree == 4 else 0)
        feats = nx + (nx * (nx + 1) // 2 if degree == 4 else 0)
    else:
        return
    if activation != act or len(hidden) != 1 or hidden[0] < need or features < feats:
        raise ConfigError(
            f"train.init {init!r}{f' (degree {degree})' if init == 'sos' else ''} needs one "
            f"{act} hidden layer of at least {need} neurons and features >= {feats}, got "
            f"activation {activation!r}, hidden {hidden}, features {features}; change them "
            "or use init 'random'")


def quadratic_start(P: np.ndarray, level: float, config: TrainConfig) -> Network:
    r"""A V of ``config``'s architecture that starts at the quadratic ``xᵀPx / level``.

    ``V(x) = ‖N(x) − N(0)‖² + ε‖x‖²`` with one tanh hidden layer: its first ``n`` neurons
    carry ``a·Lx`` (``LᵀL = P/level − εI``, ``a`` = :data:`QUADRATIC_START_SLOPE`), read back
    by the output layer with ``1/a``; the other neurons start random (``config.seed``) with
    output weights ``10⁻³``. Then ``V(x) = xᵀPx/level + O(a²‖x‖⁴)``: level 1 of V is, near
    the origin, the certified set ``{xᵀPx ≤ level}`` of the quadratic stage, which training
    starts from instead of a random V (the issue's warm start from the cheap certificate).

    Raises
    ------
    ConfigError
        The architecture cannot hold it (not one tanh hidden layer of at least ``n``
        neurons with at least ``n`` features), or ``P/level − εI`` is not positive definite.
    """
    P = np.asarray(P, dtype=float)
    n = P.shape[0]
    H = list(config.hidden)
    check_start_architecture("quadratic", n, config.activation, H, config.features)
    if not (np.isfinite(level) and level > 0):
        raise ConfigError(f"train.init 'quadratic': the quadratic's level must be > 0, got "
                          f"{level!r}")
    M = 0.5 * (P + P.T) / level - config.eps * np.eye(n)
    try:
        L = np.linalg.cholesky(M).T
    except np.linalg.LinAlgError:
        raise ConfigError("train.init 'quadratic': P/level − eps·I is not positive definite; "
                          "lower train.eps or use init 'random'") from None
    a, F, h = QUADRATIC_START_SLOPE, config.features, H[0]
    rnd = dense_network([n, h, F], "tanh", seed=config.seed)
    W1, b1 = rnd.layers[0].weight.copy(), rnd.layers[0].bias.copy()
    W1[:n], b1[:n] = a * L, 0.0
    W2 = 1e-3 * rnd.layers[1].weight
    W2[:n, :n] = np.eye(n) / a
    W2[:n, n:] = 0.0
    W2[n:, :n] = 0.0
    V = Network([Layer(W1, b1, "tanh"), Layer(W2, np.zeros(F), "linear")],
                head={"type": "sum_of_squares", "eps": config.eps})
    V.__post_init__()
    return V


def sos_start(V, level: float, config: TrainConfig) -> Network:
    r"""A V of ``config``'s architecture equal to the SOS polynomial ``V/level + ε‖x‖²``.

    With one ``square`` hidden layer the network's ``N(x)`` is a quadratic polynomial, so a
    degree-4 (or 2) SOS ``V = ‖L z(x)‖²`` (``z``: the monomials of degree 1..2, ``L`` from a
    Gram matrix, :func:`nlyap_opt.design.sos_sdp.gram_factor`) is represented exactly: the hidden
    neurons ``x_i²``, ``(x_i + 1)²`` and ``(x_i + x_j)²`` (``i < j``; degree 4 only) give every
    monomial of ``z`` up to a constant (``x_i = ((x_i + 1)² − x_i² − 1)/2``,
    ``x_i x_j = ((x_i + x_j)² − x_i² − x_j²)/2``), which ``N(x) − N(0)`` removes, and the
    output layer applies ``L/√level``. Then ``V_net = V/level + ε‖x‖²``: level 1 of the
    network is (up to the ``ε`` term, the Gram factor's rounding and float64) the SOS
    stage's certified set. The other neurons start random (``config.seed``) with output
    weights ``10⁻³``. A starting point of training, never a claim.

    Raises
    ------
    ConfigError
        The architecture cannot hold it (not one ``square`` hidden layer of at least
        ``nx(nx+3)/2`` neurons (``2·nx`` for degree 2) and ``features`` >= the number of
        monomials), ``V`` is not of degree 2 or 4, or ``level`` is not > 0.
    ValueError
        No Gram matrix of ``V`` was found (the caller may start at random instead).
    """

    n, deg = V.nx, V.degree
    H = list(config.hidden)
    check_start_architecture("sos", n, config.activation, H, config.features, deg)
    pairs = [(i, j) for i in range(n) for j in range(i + 1, n)] if deg == 4 else []
    need = 2 * n + len(pairs)
    if not (np.isfinite(level) and level > 0):
        raise ConfigError(f"train.init 'sos': the SOS level must be > 0, got {level!r}")
    z, L = sos_sdp.gram_factor(V)     # ValueError (not a ConfigError) when no Gram matrix is found
    h, F = H[0], config.features
    rnd = dense_network([n, h, F], "square", seed=config.seed)
    W1, b1 = rnd.layers[0].weight.copy(), rnd.layers[0].bias.copy()
    W1[:need], b1[:need] = 0.0, 0.0
    T = np.zeros((len(z), h))              # z(x) = T·hidden(x) + constant
    for i in range(n):
        W1[i, i] = 1.0                     # x_i²
        W1[n + i, i], b1[n + i] = 1.0, 1.0  # (x_i + 1)²
        T[z.index(tuple(int(k == i) for k in range(n))), [n + i, i]] = 0.5, -0.5
        if deg == 4:
            T[z.index(tuple(2 * int(k == i) for k in range(n))), i] = 1.0
    for k, (i, j) in enumerate(pairs):
        W1[2 * n + k, [i, j]] = 1.0        # (x_i + x_j)²
        row = z.index(tuple(int(m in (i, j)) for m in range(n)))
        T[row, [2 * n + k, i, j]] = 0.5, -0.5, -0.5
    W2 = 1e-3 * rnd.layers[1].weight
    W2[:, :need] = 0.0
    W2[:len(z)] = (L @ T) / np.sqrt(level)
    W2[:len(z), need:] = 0.0
    net = Network([Layer(W1, b1, "square"), Layer(W2, np.zeros(F), "linear")],
                  head={"type": "sum_of_squares", "eps": config.eps})
    net.__post_init__()
    return net


#: neighbours of each training state searched for the other label (label_boundary_states)
BOUNDARY_NEIGHBOURS = 8


def label_boundary_states(X: np.ndarray, inside: np.ndarray, n: int,
                          rng: np.random.Generator) -> np.ndarray:
    r"""``n`` states on segments that cross the boundary between two labels of ``X``.

    ``X`` (``(N, d)``) are simulated training states and ``inside`` marks those the model
    takes to the origin (the others get the target's cap). Each state is paired with those
    of its :data:`BOUNDARY_NEIGHBOURS` nearest neighbours (in ``X``) that carry the other
    label; a segment between such a pair crosses the model's ROA boundary (or the boundary
    of the states whose trajectories stay in the domain). Returns ``x_i + u (x_j − x_i)``,
    ``u`` uniform in ``[0, 1]``, for ``n`` pairs drawn uniformly with ``rng`` (empty when no
    pair exists).

    Where the boundary repels strongly (a limit cycle of a stiff oscillator, the stable
    manifold of a fast saddle), the trajectory cost rises to its cap only in a layer much
    thinner than the sample spacing: seen from the samples, the target jumps there. States
    drawn where the *cost* is high miss that layer; these segments do not, and more
    training states across the jump let ``V`` rise steeply where the target does.
    """
    X = np.asarray(X, dtype=float)
    inside = np.asarray(inside, dtype=bool)
    if n <= 0 or len(X) < 2 or inside.all() or not inside.any():
        return np.zeros((0, X.shape[1]))
    k = min(BOUNDARY_NEIGHBOURS + 1, len(X))
    _, nb = cKDTree(X).query(X, k=k)
    i = np.repeat(np.arange(len(X)), k - 1)
    j = nb[:, 1:].ravel()
    cross = inside[i] != inside[j]
    i, j = i[cross], j[cross]
    if not len(i):
        return np.zeros((0, X.shape[1]))
    pick = rng.integers(0, len(i), n)
    u = rng.random((n, 1))
    return X[i[pick]] + u * (X[j[pick]] - X[i[pick]])


def _body_jacobian_at_zero(body, n: int):
    """``∂N/∂x(0)`` of a ``Sequential`` of Linear / Tanh / scale layers (forward mode, with
    the graph kept for training); other bodies go through ``torch.func.jacrev``."""
    h = torch.zeros(n, dtype=torch.float64)
    J = torch.eye(n, dtype=torch.float64)
    for m in body:
        if isinstance(m, torch.nn.Linear):
            h, J = m(h), m.weight @ J
        elif isinstance(m, torch.nn.Tanh):
            h = torch.tanh(h)
            J = (1 - h * h)[:, None] * J
        elif type(m).__name__ == "Square":
            h, J = h * h, (2 * h)[:, None] * J
        elif hasattr(m, "scale"):
            h, J = m(h), m.scale.reshape(-1, 1) * J
        else:
            return torch.func.jacrev(lambda y: body(y[None])[0])(torch.zeros(n,
                                                                            dtype=torch.float64))
    return J


@dataclass
class LearnerState:
    """What :meth:`LyapunovLearner.state` saves: ``V``'s and Adam's state dicts and the
    controller gain (``None`` without a controller)."""

    V: dict
    opt: dict
    G: torch.Tensor | None


def _finite_loss(info: TrainInfo, it: int, X) -> TrainInfo:
    """``info``, or stop a training whose loss became NaN or infinite at step ``it`` (Adam
    carries it into every weight: there is no way back), with what to do."""
    if np.isfinite(info.loss):
        return info
    raise ConfigError(
        f"training diverged at step {it + 1}: the loss is {info.loss} (training states up to "
        f"‖x‖ = {float(X.norm(dim=1).max()):.3g}); rescale the system's states so that the "
        "domain is of order 1, or lower train.lr")


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
        if isinstance(config.threads, bool) or not isinstance(config.threads, int) \
                or config.threads < 1:
            raise ConfigError(f"TrainConfig.threads must be a positive integer, got "
                              f"{config.threads!r}")
        torch.manual_seed(config.seed)
        self.rng = np.random.default_rng(config.seed)
        if V is None:
            sizes = [system.nx, *config.hidden, config.features]
            V = dense_network(sizes, config.activation, seed=config.seed)
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

    def set_gain(self, G: torch.Tensor) -> None:
        """Start the controller from the gain ``G`` (``∂κ/∂x(0) = −G``; the anchor
        ``w_anchor`` then keeps the trained gain near it). Before training only."""
        with torch.no_grad():
            self.G.copy_(G)
        self.G0 = G.detach().clone()

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
        return self.rhs_xu(x, u)

    def rhs_xu(self, x, u):
        """``g(x, u)``: the vector field trained on, before the feedback is closed."""
        s = self.system
        if self.phi is None:
            return s.evaluate_torch(x, u)
        meta = self.dynamics.meta  # same two models as nlyap_opt.kernel.symbolic.learned_rhs
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
        if getattr(s, "has_model", True):
            f = s.evaluate_torch(x, u)
            cols = [out[:, learned.index(i)] if i in learned else f[:, i] for i in range(s.nx)]
        else:  # no model: the components known exactly, through their CasADi graph

            kf = evaluate(s.known_function(), [x, u], ArrayArithmetic("torch"))[0]
            known = list(s.known_state_derivatives)
            cols = [out[:, learned.index(i)] if i in learned else kf[:, known.index(i)]
                    for i in range(s.nx)]
        return torch.stack(cols, dim=1)

    def closed_loop_jacobian(self):
        """``A = ∂g/∂x + ∂g/∂u·∂κ/∂x`` at the origin (``∂κ/∂x(0) = −G`` by construction);
        the open-loop parts are computed once."""
        if not hasattr(self, "_AxAu"):
            s = self.system
            z = torch.zeros(1, s.nx, dtype=torch.float64, requires_grad=True)
            u = torch.as_tensor(s.u_eq, dtype=torch.float64).reshape(1, s.nu).requires_grad_(
                bool(s.nu))
            out = self.rhs_xu(z, u)[0]
            rows = [torch.autograd.grad(out[i], [z, u] if s.nu else [z], retain_graph=True,
                                        allow_unused=True) for i in range(s.nx)]

            def row(g, k):
                return torch.zeros(k, dtype=torch.float64) if g is None else g.reshape(k)

            Ax = torch.stack([row(r[0], s.nx) for r in rows]).detach()
            Au = torch.stack([row(r[1], s.nu) for r in rows]).detach() if s.nu else None
            self._AxAu = (Ax, Au)
        Ax, Au = self._AxAu
        if self.controller is None:
            return Ax
        return Ax - Au @ self.G

    def local_violation(self):
        r"""How far the linearisation is from certifying ``V`` near the origin.

        With ``H = ∇²V(0)`` and ``A`` the closed-loop Jacobian at 0,
        ``V̇ ≈ ½xᵀ(AᵀH + HA)x``; returns ``relu(λ_max(AᵀH + HA + 2τH)) / tr H`` (zero when
        ``V̇ ≤ −τV`` to first order), differentiable in ``V`` and the gain.
        """
        n = self.system.nx
        if hasattr(self.V, "body"):  # sum-of-squares head: H = 2(JᵀJ + ε I), J = ∂N/∂x(0)
            J = _body_jacobian_at_zero(self.V.body, n)
            H = 2 * (J.T @ J + self.V.eps * torch.eye(n, dtype=torch.float64))
        else:
            H = torch.autograd.functional.hessian(
                lambda y: self.V(y[None])[0, 0], torch.zeros(n, dtype=torch.float64),
                create_graph=True)
        A = self.closed_loop_jacobian()
        S = A.T @ H + H @ A + 2 * self.config.decay * H
        return torch.relu(torch.linalg.eigvalsh(0.5 * (S + S.T))[-1]) / torch.trace(H)

    def value_and_lie(self, x, create_graph=True):
        x = x.requires_grad_(True)
        v = self.V(x)[:, 0]
        (g,) = torch.autograd.grad(v.sum(), x, create_graph=create_graph)
        return v, (g * self.rhs(x)).sum(1), g

    # ------------------------------------------------------------------ training
    def train(self, states: np.ndarray, sphere: np.ndarray, margin: float,
              counterexamples: np.ndarray | None = None, steps: int | None = None,
              inside_weight: np.ndarray | None = None, progress=None,
              eta_pointwise: float = 0.0, targets: np.ndarray | None = None,
              target_rates: np.ndarray | None = None,
              sphere_normals: np.ndarray | None = None,
              lr: float | None = None) -> TrainInfo:
        """Run ``steps`` Adam steps; returns the last loss terms.

        Runs with ``config.threads`` torch threads and deterministic algorithms (restored on
        return): the weights after ``steps`` steps do not depend on the machine's load.

        ``inside_weight`` (per state, default 1) scales the pull of ``V ≤ 1`` (0 for
        states known not to converge). ``eta_pointwise`` adds ``η‖∇V(x)‖`` to the Lie
        derivative (the pointwise robust margin for learned dynamics). ``targets`` (per
        state) adds ``w_fit · mean (V(x) − target)²``. ``sphere_normals`` (outward unit
        normals of ``∂D`` at ``sphere``) adds ``w_inward · mean relu(n·g/‖g‖)`` for a
        trained controller. ``lr`` (default ``config.lr``) is this call's learning rate (the
        start of its cosine schedule).
        """
        cfg = self.config
        X = torch.as_tensor(states, dtype=torch.float64)
        W = (torch.ones(len(X), dtype=torch.float64) if inside_weight is None
             else torch.as_tensor(inside_weight, dtype=torch.float64))
        S = torch.as_tensor(sphere, dtype=torch.float64)
        T = None if targets is None or not cfg.w_fit else torch.as_tensor(targets,
                                                                          dtype=torch.float64)
        R = None if T is None or target_rates is None or not cfg.w_pde else \
            torch.as_tensor(target_rates, dtype=torch.float64)
        CE = (torch.as_tensor(counterexamples, dtype=torch.float64)
              if counterexamples is not None and len(counterexamples) else None)
        NS = None if sphere_normals is None or not cfg.w_inward or self.controller is None \
            or not cfg.train_controller else torch.as_tensor(sphere_normals, dtype=torch.float64)
        steps = cfg.steps if steps is None else steps
        lr = cfg.lr if lr is None else float(lr)
        for group in self.opt.param_groups:
            group["lr"] = lr
        with deterministic_torch(cfg.threads):
            return self._train(X, W, S, T, R, CE, margin, steps, progress, eta_pointwise, NS,
                               lr)

    def _train(self, X, W, S, T, R, CE, margin, steps, progress,
               eta_pointwise, NS=None, lr: float | None = None) -> TrainInfo:
        cfg = self.config
        lr = cfg.lr if lr is None else lr
        t0 = time.perf_counter()
        info = TrainInfo()
        it = -1
        gen = torch.Generator().manual_seed(cfg.seed)
        if cfg.lr_schedule not in ("constant", "cosine"):
            raise ValueError(f"unknown lr_schedule {cfg.lr_schedule!r}; expected 'constant' or "
                             "'cosine'")
        for it in range(steps):
            if cfg.lr_schedule == "cosine":
                for group in self.opt.param_groups:
                    group["lr"] = lr * (0.01 + 0.99 * 0.5 * (1 + np.cos(np.pi * it / steps)))
            idx = torch.randint(0, len(X), (min(cfg.batch, len(X)),), generator=gen)
            xb, wb = X[idx], W[idx]
            nb = len(idx)
            if CE is not None:
                cidx = torch.randint(0, len(CE), (min(cfg.batch // 4, len(CE)),),
                                     generator=gen)
                xb = torch.cat([xb, CE[cidx]])
                wb = torch.cat([wb, torch.ones(len(cidx), dtype=torch.float64)])
            v, lie, g = self.value_and_lie(xb.clone())
            active = (v <= 1.0 + cfg.level_slack).to(v.dtype)
            if eta_pointwise:  # the full ‖∇V‖ ≥ the verified ‖∇_L V‖: a training buffer
                lie = lie + eta_pointwise * g.norm(dim=1)
            hinge = torch.relu(lie + margin + cfg.decay * v)
            if cfg.relative_decrease:  # scale-free: as strong near the origin as far out
                hinge = hinge / (xb ** 2).sum(1).clamp_min(1e-12)
            dec = (hinge * active).mean()
            inside = (torch.relu(v - 1.0) * wb).mean()
            sidx = torch.randint(0, len(S), (min(cfg.batch // 4, len(S)),), generator=gen)
            vs = self.V(S[sidx])[:, 0]
            outside = torch.relu(1.0 + cfg.level_slack - vs).mean()
            loss = cfg.w_decrease * dec + cfg.w_inside * inside + cfg.w_outside * outside
            if NS is not None:   # the closed loop's direction on ∂D: inward where κ can
                gs = self.rhs(S[sidx])
                cos = (NS[sidx] * gs).sum(1) / gs.norm(dim=1).clamp_min(1e-12)
                loss = loss + cfg.w_inward * torch.relu(cos).mean()
            if cfg.w_local:
                local = self.local_violation()
                loss = loss + cfg.w_local * local
            if T is not None:
                fit = ((v[:nb] - T[idx]) ** 2).mean()
                loss = loss + cfg.w_fit * fit
                if R is not None:
                    # the target decreases at rate R(x)·‖x‖² along trajectories
                    want = R[idx] * (xb[:nb] ** 2).sum(1)
                    live = want > 0
                    rel = lie[:nb] / torch.where(live, want, torch.ones_like(want)) + 1.0
                    pde = torch.where(live, rel, torch.zeros_like(rel)).pow(2).mean()
                    loss = loss + cfg.w_pde * pde
            if cfg.w_grad:
                loss = loss + cfg.w_grad * g.norm(dim=1).mean()
            if self.controller is not None and cfg.train_controller and cfg.w_anchor:
                loss = loss + cfg.w_anchor * ((self.G - self.G0) ** 2).sum()
            self.opt.zero_grad()
            loss.backward()
            self.opt.step()
            info = _finite_loss(TrainInfo(loss.item(), dec.item(), inside.item(),
                                          outside.item(), None if T is None else fit.item()),
                                it, X)
            if progress is not None and (it % 100 == 0 or it == steps - 1):
                progress(it, info)
        info.steps, info.seconds = it + 1, time.perf_counter() - t0
        return info

    # ------------------------------------------------------------------ state
    def state(self) -> LearnerState:
        """A copy of everything training changes (``V``'s weights, the controller gain and
        Adam's moments), for :meth:`load_state`."""
        return LearnerState(copy.deepcopy(self.V.state_dict()),
                            copy.deepcopy(self.opt.state_dict()),
                            None if self.controller is None else self.G.detach().clone())

    def load_state(self, state: LearnerState) -> None:
        """Continue from a :meth:`state`: training afterwards is as if from that point."""
        self.V.load_state_dict(copy.deepcopy(state.V))
        if state.G is not None:
            with torch.no_grad():
                self.G.copy_(state.G)
        self.opt.load_state_dict(copy.deepcopy(state.opt))

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
