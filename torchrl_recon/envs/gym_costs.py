"""Batched torch costs of standard gymnasium tasks, for ``env.cost`` in recipes.

Pendulum's is the negative of the env's own reward, so predicted and real costs compare:
``env.id=Pendulum-v1 env.cost=torchrl_recon.envs.gym_costs:pendulum``. MountainCarContinuous-v0's
is shaped (the energy the car still lacks) and comes with the env's termination:
``env.id=MountainCarContinuous-v0 env.cost=torchrl_recon.envs.gym_costs:mountain_car
env.termination=torchrl_recon.envs.gym_costs:mountain_car_termination``.
"""

from __future__ import annotations

import torch


def pendulum(obs: torch.Tensor, action: torch.Tensor, next_obs: torch.Tensor) -> torch.Tensor:
    """Pendulum-v1's cost θ² + 0.1·θ̇² + 0.001·u² of the state a step starts from (θ from
    cos θ, sin θ), ``[..., 3]``, ``[..., 1]`` → ``[...]``.

    Examples:
        >>> pendulum(torch.tensor([[1.0, 0.0, 2.0]]), torch.tensor([[1.0]]), torch.zeros(1, 3))
        tensor([0.4010])
    """
    theta = torch.atan2(obs[..., 1], obs[..., 0])
    return theta.pow(2) + 0.1 * obs[..., 2].pow(2) + 0.001 * action[..., 0].pow(2)


GRAVITY, POWER, GOAL = 0.0025, 0.0015, 0.45
"""MountainCarContinuous-v0's constants: v += POWER·u − GRAVITY·cos(3x); the goal x ≥ GOAL."""


def mountain_car_energy(obs: torch.Tensor) -> torch.Tensor:
    """The car's mechanical energy per unit mass, ½v² + (GRAVITY/3)·sin(3x): what its
    dynamics conserve when the engine is off, ``[..., 2]`` → ``[...]``."""
    return 0.5 * obs[..., 1].pow(2) + GRAVITY / 3 * torch.sin(3 * obs[..., 0])


def mountain_car(obs: torch.Tensor, action: torch.Tensor, next_obs: torch.Tensor) -> torch.Tensor:
    """A shaped cost for MountainCarContinuous-v0 (not its reward, whose +100 at the goal a short
    plan never sees): the energy still missing to reach the goal, scaled to about 0–1.65 a
    step, plus the env's 0.1·u² action cost; ``[..., 2]``, ``[..., 1]`` → ``[...]``.
    Pair it with :func:`mountain_car_termination` so a plan stops paying once at the goal.

    Examples:
        >>> bottom = torch.tensor([[-torch.pi / 6, 0.0]])
        >>> mountain_car(bottom, torch.zeros(1, 1), bottom)
        tensor([1.6464])
        >>> at_goal = torch.tensor([[0.5, 0.01]])
        >>> mountain_car(at_goal, torch.ones(1, 1), at_goal)
        tensor([0.1000])
    """
    goal = mountain_car_energy(next_obs.new_tensor([GOAL, 0.0]))
    missing = (goal - mountain_car_energy(next_obs)).clamp(min=0)
    return 1000 * missing + 0.1 * action[..., 0].pow(2)


def mountain_car_termination(
    obs: torch.Tensor, action: torch.Tensor, next_obs: torch.Tensor
) -> torch.Tensor:
    """MountainCarContinuous-v0's end: the car at the goal, x ≥ 0.45 with v ≥ 0 (bool ``[...]``).

    Examples:
        >>> mountain_car_termination(None, None, torch.tensor([[0.46, 0.0], [0.46, -0.01]]))
        tensor([ True, False])
    """
    return (next_obs[..., 0] >= GOAL) & (next_obs[..., 1] >= 0)


def inverted_pendulum_fallen(
    obs: torch.Tensor, action: torch.Tensor, next_obs: torch.Tensor
) -> torch.Tensor:
    """InvertedPendulum-v5's termination: the state a step reaches is not finite or its pole
    angle (``obs[1]``) is past 0.2 rad, ``[..., 4]`` → bool ``[...]``.

    Examples:
        >>> inverted_pendulum_fallen(None, None, torch.tensor([[0.0, 0.1, 0, 0], [0.0, -0.3, 0, 0]]))
        tensor([False,  True])
    """
    return ~torch.isfinite(next_obs).all(-1) | (next_obs[..., 1].abs() > 0.2)


def inverted_pendulum(
    obs: torch.Tensor, action: torch.Tensor, next_obs: torch.Tensor
) -> torch.Tensor:
    """InvertedPendulum-v5's cost: −1 for a step that keeps the pole up, 0 for the step it falls
    (the env's reward is 1 while not terminated). Give the planner
    :func:`inverted_pendulum_fallen` as ``env.termination`` too, so that nothing accrues after
    a predicted fall and plans that stay up win: ``env.id=InvertedPendulum-v5
    env.cost=torchrl_recon.envs.gym_costs:inverted_pendulum
    env.termination=torchrl_recon.envs.gym_costs:inverted_pendulum_fallen`` (needs
    ``pip install "torchrl-recon[mujoco]"``).

    Examples:
        >>> inverted_pendulum(None, None, torch.tensor([[0.0, 0.1, 0, 0], [0.0, -0.3, 0, 0]]))
        tensor([-1., -0.])
    """
    return -(~inverted_pendulum_fallen(obs, action, next_obs)).to(next_obs.dtype)


def inverted_pendulum_upright(
    obs: torch.Tensor, action: torch.Tensor, next_obs: torch.Tensor
) -> torch.Tensor:
    """A shaped InvertedPendulum-v5 cost: :func:`inverted_pendulum`'s −1 a step while up, plus
    10·angle² and 0.1·(cart position)² of the state reached, so that among plans that all stay
    up over the horizon (the plain cost ties them) the one keeping the pole upright and the cart
    centred wins. Both terms stay below 1 while the pole is up (angle ≤ 0.2 rad, cart within
    ±1), so falling is never cheaper. Use with :func:`inverted_pendulum_fallen` as
    ``env.termination``.

    Examples:
        >>> states = torch.tensor([[0.0, 0.0, 0, 0], [0.5, 0.1, 0, 0], [0.0, float("nan"), 0, 0]])
        >>> inverted_pendulum_upright(None, None, states)
        tensor([-1.0000, -0.8750,  0.0000])
    """
    up = ~inverted_pendulum_fallen(obs, action, next_obs)
    shape = 10 * next_obs[..., 1].pow(2) + 0.1 * next_obs[..., 0].pow(2)
    return torch.where(
        up, shape - 1, torch.zeros_like(shape)
    )  # 0, not NaN, past a non-finite state


def _double_pendulum_tip(obs: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """InvertedDoublePendulum-v5's tip (x, height) from its observation ``[..., 9]`` (cart x,
    sin θ1, sin θ2, cos θ1, cos θ2, ...): two poles of 0.6 m, θ2 relative to the first pole."""
    x, sin1, sin2, cos1, cos2 = obs[..., 0], obs[..., 1], obs[..., 2], obs[..., 3], obs[..., 4]
    sin12, cos12 = sin1 * cos2 + cos1 * sin2, cos1 * cos2 - sin1 * sin2
    return x + 0.6 * (sin1 + sin12), 0.6 * (cos1 + cos12)


def inverted_double_pendulum_fallen(
    obs: torch.Tensor, action: torch.Tensor, next_obs: torch.Tensor
) -> torch.Tensor:
    """InvertedDoublePendulum-v5's termination: the tip of the state reached at or below 1 m
    (or a non-finite state), ``[..., 9]`` → bool ``[...]``.

    Examples:
        >>> up = torch.tensor([[0.0, 0, 0, 1, 1, 0, 0, 0, 0]])  # both poles straight up: 1.2 m
        >>> inverted_double_pendulum_fallen(None, None, torch.cat([up, -up]))
        tensor([False,  True])
    """
    _, height = _double_pendulum_tip(next_obs)
    return ~torch.isfinite(next_obs).all(-1) | (height <= 1)


def inverted_double_pendulum(
    obs: torch.Tensor, action: torch.Tensor, next_obs: torch.Tensor
) -> torch.Tensor:
    """InvertedDoublePendulum-v5's cost, the negative of its reward from the state a step
    reaches: −(10 while the tip stays above 1 m) + 0.01·tip_x² + (tip_height − 2)² +
    0.001·θ̇1² + 0.005·θ̇2². The env reads the joint speeds unclipped and the observation
    holds them clipped to ±10, the only difference (none below 10 rad/s). Pair it with
    :func:`inverted_double_pendulum_fallen` as ``env.termination``.

    Examples:
        >>> up = torch.tensor([[0.0, 0, 0, 1, 1, 0, 0, 0, 0]])
        >>> inverted_double_pendulum(None, None, up)  # the best a step can do: 10 - 0.64
        tensor([-9.3600])
    """
    tip_x, height = _double_pendulum_tip(next_obs)
    alive = 10.0 * (~inverted_double_pendulum_fallen(obs, action, next_obs)).to(next_obs.dtype)
    distance = 0.01 * tip_x.pow(2) + (height - 2).pow(2)
    speed = 1e-3 * next_obs[..., 6].pow(2) + 5e-3 * next_obs[..., 7].pow(2)
    return torch.nan_to_num(distance + speed - alive, nan=0.0)


def reacher(obs: torch.Tensor, action: torch.Tensor, next_obs: torch.Tensor) -> torch.Tensor:
    """Reacher-v5's cost, the negative of its reward: the fingertip's distance to the target in
    the state reached (``next_obs[8:10]``) plus Σ a², ``[..., 10]``, ``[..., 2]`` → ``[...]``.

    Examples:
        >>> reached = torch.zeros(1, 10)
        >>> reached[0, 8:10] = torch.tensor([0.03, 0.04])
        >>> reacher(None, torch.ones(1, 2), reached)
        tensor([2.0500])
    """
    return next_obs[..., 8:10].norm(dim=-1) + action.pow(2).sum(-1)


def half_cheetah(obs: torch.Tensor, action: torch.Tensor, next_obs: torch.Tensor) -> torch.Tensor:
    """HalfCheetah-v5's cost from its observation: −(the forward speed of the state reached,
    ``next_obs[8]``) + 0.1·Σ a². The env's reward takes the mean speed over the step (its x
    moved over dt), which the observation (it leaves x out) does not hold; the speed at the
    step's end is PETS's stand-in, ``[..., 17]``, ``[..., 6]`` → ``[...]``.

    Examples:
        >>> state = torch.zeros(1, 17)
        >>> state[0, 8] = 3.0
        >>> half_cheetah(None, torch.ones(1, 6), state)
        tensor([-2.4000])
    """
    return -next_obs[..., 8] + 0.1 * action.pow(2).sum(-1)
