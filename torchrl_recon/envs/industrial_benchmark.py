"""Industrial Benchmark (Hein et al., 2017) as a gymnasium environment, plus its torch cost.

The Industrial Benchmark (IB) is a synthetic, stochastic, partially observable process motivated
by industrial control problems (gas turbines, wind turbines). Three steering variables (velocity,
gain, shift) are moved by bounded deltas; the cost combines a stochastic fatigue with a delayed,
noisy consumption that includes a hidden mis-calibration. The dynamics live in
:mod:`torchrl_recon.envs.industrial_benchmark_dynamics`; this module wraps them in the gymnasium
API and provides :func:`industrial_benchmark_cost` for planners.
"""

from __future__ import annotations

import math
from numbers import Real
from typing import Any

import gymnasium as gym
import numpy as np
import torch
from gymnasium import spaces

from torchrl_recon.envs._validation import validate_action
from torchrl_recon.envs.industrial_benchmark_dynamics import CRC, CRF, IndustrialBenchmarkDynamics

__all__ = ["IndustrialBenchmarkEnv", "industrial_benchmark_cost"]

_ENV_NAME = "IndustrialBenchmark"
# Declared observation bounds [p, v, g, h, f, c]. p, v, g, h and f (<= fb <= 300) are exact
# bounds. The consumption c is Gaussian around E in [~1, ~4971]; [-100, 10000] lies more than
# 100 standard deviations beyond any reachable noise-free value, so it is never left in practice.
_OBS_LOW = np.array([0.0, 0.0, 0.0, 0.0, 0.0, -100.0], dtype=np.float64)
_OBS_HIGH = np.array([100.0, 100.0, 100.0, 100.0, 300.0, 10000.0], dtype=np.float64)


class IndustrialBenchmarkEnv(gym.Env[np.ndarray, np.ndarray]):
    """Industrial Benchmark environment (gymnasium >= 1.0 API).

    Observation ``[p, v, g, h, f, c]`` (setpoint, velocity, gain, shift, fatigue, consumption),
    float64. Action: three deltas in ``[-1, 1]`` for velocity (x1), gain (x10) and shift (x~5.75);
    finite out-of-range values are clipped, NaN/inf or a wrong shape raise ``ValueError``. Reward
    ``-(3 f + c)``. There is no terminal state (``terminated`` is always ``False``); the registered
    id ``torchrl_recon/IndustrialBenchmark-v0`` truncates after 1000 steps via gymnasium's
    ``TimeLimit``.

    ``reset`` reproduces the reference constructor ``IDS(p, stationary_p, inital_seed)``: one
    setpoint-sequence definition (3 draws) and one internal zero-action step, so the reset
    observation is ``[p, 50, 50, 50, f, c]`` with random ``f, c``.

    Args:
        setpoint: Setpoint ("load") ``p`` in ``[0, 100]``; default 50.
        stationary_setpoint: Keep ``p`` fixed (default, as the reference gym wrapper). ``False``
            enables the reference's random setpoint drift; ``p`` is then still observed.
        reference_rng: If ``True``, draw all randomness from ``numpy.random.RandomState(seed)``
            with the reference's exact calls so that ``reset(seed=s)`` reproduces
            ``IDS(p, stationary_p, inital_seed=s)`` bit for bit. ``reset()`` without a seed
            then uses a seed drawn from ``self.np_random``. If ``False`` (default), the draws
            come from gymnasium's ``self.np_random`` (same distributions, different numbers).

    Raises:
        ValueError: If ``setpoint`` is not a finite number in ``[0, 100]``.
        TypeError: If ``setpoint`` is not a real number or a keyword is unknown.

    Examples:
        >>> env = IndustrialBenchmarkEnv(setpoint=50, reference_rng=True)
        >>> obs, info = env.reset(seed=1002)
        >>> obs.round(6).tolist()
        [50.0, 50.0, 50.0, 50.0, 22.104998, 95.662201]
        >>> obs, reward, terminated, truncated, info = env.step(np.zeros(3))
        >>> obs.shape, terminated, truncated
        ((6,), False, False)
    """

    metadata: dict[str, Any] = {"render_modes": []}

    def __init__(
        self,
        *,
        setpoint: float = 50.0,
        stationary_setpoint: bool = True,
        reference_rng: bool = False,
    ) -> None:
        if isinstance(setpoint, bool) or not isinstance(setpoint, Real):
            raise TypeError(
                f"{_ENV_NAME}: setpoint must be a real number in [0, 100], got {setpoint!r} "
                f"of type {type(setpoint).__name__}."
            )
        if not (math.isfinite(float(setpoint)) and 0.0 <= float(setpoint) <= 100.0):
            raise ValueError(f"{_ENV_NAME}: setpoint {setpoint!r} is outside [0, 100].")
        self.setpoint = float(setpoint)
        self.stationary_setpoint = bool(stationary_setpoint)
        self.reference_rng = bool(reference_rng)

        self.observation_space = spaces.Box(_OBS_LOW, _OBS_HIGH, shape=(6,), dtype=np.float64)
        self.action_space = spaces.Box(-1.0, 1.0, shape=(3,), dtype=np.float32)
        self._dynamics: IndustrialBenchmarkDynamics | None = None

    @property
    def dynamics(self) -> IndustrialBenchmarkDynamics:
        """The simulator core (full hidden state, see ``markov_state()``); requires ``reset``."""
        if self._dynamics is None:
            raise RuntimeError(f"{_ENV_NAME}: call reset() before accessing the dynamics.")
        return self._dynamics

    def reset(
        self, *, seed: int | None = None, options: dict[str, Any] | None = None
    ) -> tuple[np.ndarray, dict[str, Any]]:
        """Start a new episode (the reference constructor: sequence draws + one zero step).

        Args:
            seed: Seed for the episode's randomness. In reference mode this is the reference's
                ``inital_seed`` (``RandomState(seed)``); otherwise it seeds ``self.np_random``.
            options: Unused; accepted for API compatibility.

        Returns:
            The observation ``[p, v, g, h, f, c]`` and an empty info dict.
        """
        super().reset(seed=seed)
        if self.reference_rng:
            ref_seed = seed if seed is not None else int(self.np_random.integers(0, 2**32))
            rng: np.random.RandomState | np.random.Generator = np.random.RandomState(ref_seed)
        else:
            rng = self.np_random
        self._dynamics = IndustrialBenchmarkDynamics(
            self.setpoint, stationary_setpoint=self.stationary_setpoint, rng=rng
        )
        return np.array(self._dynamics.observation(), dtype=np.float64), {}

    def step(self, action: Any) -> tuple[np.ndarray, float, bool, bool, dict[str, Any]]:
        """Apply a ``(d_velocity, d_gain, d_shift)`` action and advance one time step.

        Args:
            action: Array-like of shape ``(3,)``; finite values are clipped to ``[-1, 1]``.

        Returns:
            ``(observation, reward, terminated=False, truncated=False, info={})``.

        Raises:
            ValueError: If the action has the wrong shape or contains NaN/inf.
            RuntimeError: If called before ``reset``.
        """
        dyn = self._dynamics
        if dyn is None:
            raise RuntimeError(f"{_ENV_NAME}: call reset() before step().")
        a_v, a_g, a_h = validate_action(action, shape=(3,), env_name=_ENV_NAME).tolist()
        reward = dyn.step(a_v, a_g, a_h)
        obs = np.array([dyn.p, dyn.v, dyn.g, dyn.h, dyn.f, dyn.c], dtype=np.float64)
        return obs, reward, False, False, {}


def industrial_benchmark_cost(
    observation: torch.Tensor, action: torch.Tensor, next_observation: torch.Tensor
) -> torch.Tensor:
    """Batched, differentiable Industrial Benchmark cost ``3 f' + c'`` of a transition.

    The cost depends only on the next observation (fatigue ``f'`` at index 4 and consumption
    ``c'`` at index 5); ``observation`` and ``action`` are accepted for the common
    ``cost(obs, action, next_obs)`` signature and only shape-checked. On real transitions
    ``env reward == -cost`` (exactly, for float64 inputs).

    Args:
        observation: ``[..., 6]`` observation before the step (unused).
        action: ``[..., 3]`` action (unused).
        next_observation: ``[..., 6]`` observation after the step ``[p, v, g, h, f, c]``.

    Returns:
        The cost with shape ``[...]`` (no trailing singleton), same dtype as ``next_observation``.

    Raises:
        ValueError: If a trailing dimension is not 6 / 3 / 6.

    Examples:
        >>> next_obs = torch.tensor([[50.0, 50.0, 50.0, 50.0, 20.0, 90.0]], requires_grad=True)
        >>> cost = industrial_benchmark_cost(torch.zeros(1, 6), torch.zeros(1, 3), next_obs)
        >>> cost
        tensor([150.], grad_fn=<AddBackward0>)
        >>> cost.sum().backward(); next_obs.grad.tolist()
        [[0.0, 0.0, 0.0, 0.0, 3.0, 1.0]]
    """
    for name, tensor, size in (
        ("observation", observation, 6),
        ("action", action, 3),
        ("next_observation", next_observation, 6),
    ):
        if tensor.ndim == 0 or tensor.shape[-1] != size:
            raise ValueError(
                f"industrial_benchmark_cost: {name} has shape {tuple(tensor.shape)}, "
                f"expected [..., {size}]."
            )
    return CRF * next_observation[..., 4] + CRC * next_observation[..., 5]
