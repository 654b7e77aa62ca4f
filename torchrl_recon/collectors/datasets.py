"""Building datasets: concatenating collections, drawing fixed-length validation trajectories."""

from __future__ import annotations

from typing import Literal

import torch
from tensordict import TensorDictBase
from torchrl.envs import EnvBase

from torchrl_recon.collectors.policies import OffsetNoisePolicy
from torchrl_recon.data.buffers import TRAJ_KEY


def concat_trajectories(*datasets: TensorDictBase) -> TensorDictBase:
    """Concatenate flat transition sets, renumbering trajectory ids so they stay distinct.

    Examples:
        >>> from tensordict import TensorDict
        >>> a = TensorDict({("collector", "traj_ids"): torch.tensor([0, 0, 1])}, [3])
        >>> concat_trajectories(a, a)["collector", "traj_ids"].tolist()
        [0, 0, 1, 2, 2, 3]
    """
    parts, offset = [], 0
    for data in datasets:
        if data.numel() == 0:
            continue
        data = data.clone()
        ids = data.get(TRAJ_KEY)
        _, dense = torch.unique(ids, return_inverse=True)
        data.set(TRAJ_KEY, dense + offset)
        offset += int(dense.max()) + 1
        parts.append(data)
    if not parts:
        raise ValueError("concat_trajectories got no non-empty dataset.")
    return torch.cat(parts, 0)


def validation_trajectories(
    env: EnvBase,
    *,
    count: int,
    length: int,
    seed: int,
    policy: Literal["random", "offset_noise"] = "random",
    max_attempts: int | None = None,
) -> TensorDictBase:
    """``count`` complete real trajectories of ``length`` steps, ``[count, length]``.

    Each starts from a fresh reset; episodes that terminate early (a drone crash, a fallen
    Minitaur) are discarded and drawn again. ``policy="random"`` uses uniform actions;
    ``"offset_noise"`` draws one :class:`OffsetNoisePolicy` offset per trajectory, with
    magnitudes spread evenly over 0, 1/3, 2/3 and 1.

    Examples:
        >>> from torchrl_recon.envs import make_env
        >>> validation_trajectories(make_env("drone", seed=0), count=2, length=5, seed=0).batch_size
        torch.Size([2, 5])
    """
    if policy not in ("random", "offset_noise"):
        raise ValueError(f"policy must be 'random' or 'offset_noise', got {policy!r}.")
    generator = torch.Generator().manual_seed(seed)
    torch.manual_seed(seed)
    env.set_seed(seed)
    action_dim = env.action_spec.shape[-1]
    trajectories, attempts = [], 0
    max_attempts = max_attempts or 10 * count
    while len(trajectories) < count:
        attempts += 1
        if attempts > max_attempts:
            raise RuntimeError(
                f"Only {len(trajectories)} of {count} trajectories reached {length} steps in {max_attempts} attempts; "
                "use shorter validation trajectories for this environment."
            )
        rollout_policy = None
        if policy == "offset_noise":
            magnitude = (len(trajectories) % 4) / 3
            offset = (torch.rand(action_dim, generator=generator) * 2 - 1) * magnitude
            rollout_policy = OffsetNoisePolicy(offset, generator=generator)
        td = env.rollout(length, policy=rollout_policy, break_when_any_done=True)
        if td.shape[0] == length and not td["next", "done"][:-1].any():
            trajectories.append(td)
    return torch.stack(trajectories, 0).contiguous()
