"""The paper's reconstruction-uncertainty estimator: an autoencoder over T-step (s, a) windows."""

from __future__ import annotations

import torch
from tensordict import NestedKey
from torch import nn

from torchrl_recon.estimators.uncertainty import UncertaintyEstimator, window_view
from torchrl_recon.modules.activations import ACTIVATIONS, INPLACE_ACTIVATIONS
from torchrl_recon.modules.checks import check_activation, check_int
from torchrl_recon.modules.normalization import Normalizer

_BLOCK = 2048  # windows per block in the no-grad path


class ReconstructionUncertainty(UncertaintyEstimator):
    """Feed-forward autoencoder whose reconstruction error is the uncertainty u (paper §2.2).

    The input is the flattened window of T consecutive standardised (s, a) pairs,
    size T·(N + M), with one hidden layer (paper: 100 units). For the window ending at t,

        u_t = (1/T) · sqrt( Σ_{i=t-T+1..t} ‖x_i − x̂_i‖² )            (paper eq. 2)

    where x_i = ((s_i − μ_s)/σ_s, (a_i − μ_a)/σ_a) are standardised with statistics fitted
    on the training data. Standardising makes every feature count equally whatever its
    units (IB states span 0–100, actions ±1); the paper does not state its normalisation.
    Training minimises the mean of u over windows (paper eq. 1), see
    :class:`~torchrl_recon.objectives.UncertaintyLoss`.

    Args:
        obs_dim: state size N.
        action_dim: action size M.

    Keyword Args:
        window: T, the number of steps per window (paper: 10).
        hidden_size: hidden units (paper: 100).
        activation: ``"relu"``, ``"tanh"`` or ``"elu"``.
        obs_key, action_key, out_key: TensorDict keys used by ``forward``.

    Examples:
        >>> ae = ReconstructionUncertainty(6, 3, window=10)
        >>> ae.score(torch.randn(4, 30, 6), torch.randn(4, 30, 3)).shape
        torch.Size([4, 21])
    """

    window_local = True  # u of a window depends on that window alone

    def __init__(
        self,
        obs_dim: int,
        action_dim: int,
        *,
        window: int = 10,
        hidden_size: int = 100,
        activation: str = "relu",
        obs_key: NestedKey = "observation",
        action_key: NestedKey = "action",
        out_key: NestedKey = "uncertainty",
    ) -> None:
        super().__init__(
            obs_dim, action_dim, window, obs_key=obs_key, action_key=action_key, out_key=out_key
        )
        check_activation(activation)
        check_int("hidden_size", hidden_size)
        self.hidden_size, self.activation = hidden_size, activation
        size = window * self.feature_dim
        self.encoder = nn.Linear(size, hidden_size)
        self.decoder = nn.Linear(hidden_size, size)
        self.input_norm = Normalizer(self.feature_dim)

    def config(self) -> dict:
        return {
            "obs_dim": self.obs_dim,
            "action_dim": self.action_dim,
            "window": self.window,
            "hidden_size": self.hidden_size,
            "activation": self.activation,
        }

    def score_sequence(self, x: torch.Tensor) -> torch.Tensor:
        rows, length, dim = x.shape
        x = self.input_norm.normalize(x).contiguous()
        needs_grad = torch.is_grad_enabled() and (
            x.requires_grad or self.encoder.weight.requires_grad
        )
        if needs_grad:
            return self._window_errors(x)
        return self._window_errors_blocked(x)

    def _window_errors(self, x: torch.Tensor) -> torch.Tensor:
        """u for every window of standardised sequences ``[R, L, D]`` → ``[R, L - T + 1]`` (differentiable)."""
        return window_errors(x, self.window, self.activation, *self._weights())

    def _window_errors_blocked(self, x: torch.Tensor) -> torch.Tensor:
        """The same without autograd, in cache-sized blocks (see :func:`window_errors_blocked`)."""
        return window_errors_blocked(x, self.window, self.activation, *self._weights())

    def _weights(self) -> tuple[torch.Tensor, ...]:
        return self.encoder.weight, self.encoder.bias, self.decoder.weight, self.decoder.bias


def window_errors(
    x: torch.Tensor, window: int, activation: str, *weights: torch.Tensor
) -> torch.Tensor:
    """u of every window of standardised sequences, differentiable.

    Args:
        x: ``[R, L, D]`` for one autoencoder, or ``[P, R, L, D]`` for a population of P.
        window: T (steps per window).
        activation: the hidden layer's activation name.
        weights: ``enc_w, enc_b, dec_w, dec_b`` in ``nn.Linear`` layout, ``[P, ...]`` each
            for a population (its matmuls are batched over the members).

    Returns:
        ``[*P, R, L - T + 1]``.
    """
    enc_w, enc_b, dec_w, dec_b = weights
    *members, rows, length, dim = x.shape
    num_windows = length - window + 1
    windows = window_view(x.reshape(-1, length, dim), window).reshape(
        *members, rows * num_windows, window * dim
    )
    act = ACTIVATIONS[activation]
    if enc_w.dim() == 2:
        hidden = act(torch.addmm(enc_b, windows, enc_w.t()))
        error = torch.addmm(dec_b, hidden, dec_w.t()) - windows
    else:
        hidden = act(torch.baddbmm(enc_b.unsqueeze(-2), windows, enc_w.transpose(-1, -2)))
        error = torch.baddbmm(dec_b.unsqueeze(-2), hidden, dec_w.transpose(-1, -2)) - windows
    u = torch.linalg.vector_norm(error, dim=-1) / window
    return u.reshape(*members, rows, num_windows)


@torch.no_grad()
def window_errors_blocked(
    x: torch.Tensor, window: int, activation: str, *weights: torch.Tensor
) -> torch.Tensor:
    """:func:`window_errors` of one autoencoder without autograd, in blocks of about ``_BLOCK`` windows.

    Per block: one pass copies the windows minus the decoder bias b2, the encoder is a
    matmul plus an in-place bias and activation (its bias folded to b1 + W1·b2), and the
    error ``W2·h + b2 − window`` is one in-place ``addmm_(beta=-1)`` on that copy. Timings
    are in docs/benchmarks.md.
    """
    enc_w, enc_b, dec_w, b2 = weights
    rows, length, dim = x.shape
    size, num_windows = window * dim, length - window + 1
    w1t, w2t = enc_w.t().contiguous(), dec_w.t().contiguous()
    c1 = enc_b + enc_w @ b2
    act_ = INPLACE_ACTIVATIONS[activation]
    out = x.new_empty(rows, num_windows)
    # Traced into a compiled graph: one block of every row, the same ops (a loop over blocks
    # would be unrolled into the graph and pin the number of rows).
    compiling = torch.compiler.is_compiling()
    step = rows if compiling else max(1, _BLOCK // num_windows)
    # Block buffers allocated once and reused (fresh ~1 MB buffers per block are page-faulted in).
    shifted_buf = x.new_empty(step * num_windows, size)
    hidden_buf = x.new_empty(step * num_windows, enc_w.shape[0])
    for i in (0,) if compiling else range(0, rows, step):
        block = x[i : i + step]
        n = block.shape[0] * num_windows
        windows = window_view(block, window)
        shifted = shifted_buf[:n]
        torch.sub(windows, b2, out=shifted.view(block.shape[0], num_windows, size))
        hidden = act_(torch.mm(shifted, w1t, out=hidden_buf[:n]).add_(c1))
        error = shifted.addmm_(hidden, w2t, beta=-1)
        torch.linalg.vector_norm(error, dim=-1, out=out[i : i + block.shape[0]].view(-1))
    return out.div_(window)
