"""Colored (1/f^β) Gaussian noise along the planning horizon, for iCEM's candidate sampling."""

from __future__ import annotations

import math

import torch

from torchrl_recon.modules.checks import check_int, check_real, check_type, in_graph

__all__ = ["colored_noise"]


def colored_noise(white: torch.Tensor, horizon: int, beta: float) -> torch.Tensor:
    """Shape standard normal draws into noise whose power spectrum falls as 1/f^β along time.

    The method of Timmer & König (1995), as in the ``colorednoise`` package and mbrl-lib's
    ``powerlaw_psd_gaussian`` that iCEM uses (Pinneri et al. 2020, "Sample-efficient
    Cross-Entropy Method for Real-time Planning", CoRL): the real and imaginary parts of each
    frequency's coefficient are drawn N(0, f^-β), transformed back to time, and divided by the
    resulting standard deviation (unit variance at every step, in expectation; the zero
    frequency is counted, which the package's scaling leaves out). β = 0 is white noise; β = 1 pink, β = 2 red (Brownian-like): larger
    β gives smoother action sequences, whose low frequencies let a short search move far.

    Args:
        white: standard normal draws ``[..., 2, F]`` with ``F = horizon // 2 + 1`` (real and
            imaginary parts); the caller draws them so that a seed or a generator fixes them.
        horizon: H, the number of time steps of the result.
        beta: the exponent β >= 0.

    Returns:
        ``[..., H]``: unit-variance noise, correlated along the last dim.

    Examples:
        >>> white = torch.randn(20000, 2, 9, generator=torch.Generator().manual_seed(0))
        >>> red = colored_noise(white, 16, beta=2.0)
        >>> red.shape, round(red.var().item(), 1)
        (torch.Size([20000, 16]), 1.0)
        >>> lag1 = lambda x: (x[:, 1:] * x[:, :-1]).mean() / x.var()
        >>> round(lag1(colored_noise(white, 16, beta=0.0)).item(), 1), lag1(red).item() > 0.5
        (0.0, True)
    """
    if not in_graph():  # (a compiled plan's graph: checked when eager)
        check_type("white", white, torch.Tensor, "a tensor [..., 2, F] of standard normal draws")
        check_int("horizon", horizon)
        check_real("beta", beta, minimum=0.0)
    freqs = horizon // 2 + 1
    if white.shape[-2:] != (2, freqs):
        raise ValueError(
            f"white has shape {tuple(white.shape)}; expected [..., 2, {freqs}] for horizon {horizon}."
        )
    if horizon == 1:  # one step has no spectrum: white noise
        return white[..., 0, :1]
    f = torch.fft.rfftfreq(horizon, device=white.device, dtype=white.dtype)
    scale = f.clamp(min=1.0 / horizon).pow(-beta / 2.0)  # f = 0 takes the lowest frequency's scale
    real, imag = white[..., 0, :] * scale, white[..., 1, :] * scale
    # The zero frequency (and for even H the Nyquist one) of a real signal is real.
    real[..., 0] = real[..., 0] * math.sqrt(2.0)
    imag[..., 0] = 0.0
    # Each time step's variance: 2·s² for the real-only terms, 4·s² for the others, over H².
    weight = torch.full_like(scale, 4.0)
    weight[0] = 2.0
    if horizon % 2 == 0:
        real[..., -1] = real[..., -1] * math.sqrt(2.0)
        imag[..., -1] = 0.0
        weight[-1] = 2.0
    std = (weight * scale.pow(2)).sum().sqrt() / horizon
    return torch.fft.irfft(torch.complex(real, imag), n=horizon, dim=-1) / std
