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


def first_episodes(rollout: TensorDictBase) -> list[TensorDictBase]:
    """Each env's first episode in a batched rollout ``[B, T]``: its steps up to and including
    its first done (all ``T`` when it never ends), e.g. of ``env.rollout(...,
    break_when_all_done=True)``, where envs that ended wait for the others.

    Examples:
        >>> from tensordict import TensorDict
        >>> done = torch.tensor([[False, True, True], [False, False, False]])[..., None]
        >>> [len(e) for e in first_episodes(TensorDict({("next", "done"): done}, [2, 3]))]
        [2, 3]
    """
    done = rollout["next", "done"].flatten(2).any(-1)  # [B, T]
    lengths = torch.where(done.any(1), done.int().argmax(1) + 1, done.shape[1]).tolist()
    return [rollout[i, :n] for i, n in enumerate(lengths)]


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
    magnitudes spread evenly over 0, 1/3, 2/3 and 1 (trajectory ``k`` has magnitude
    ``(k % 4) / 3``; a discarded one is drawn again with the same magnitude).

    A batched env of ``B`` envs draws ``B`` trajectories per rollout, one per missing
    trajectory slot in order (each attempt counts towards ``max_attempts``); with ``B = 1``
    (or an unbatched env) the trajectories are drawn one after the other.

    Examples:
        >>> from torchrl_recon.envs import make_env
        >>> validation_trajectories(make_env("drone", seed=0), count=2, length=5, seed=0).batch_size
        torch.Size([2, 5])
        >>> batch = make_env("drone", seed=0, num_envs=3, parallel=False)
        >>> validation_trajectories(batch, count=2, length=5, seed=0, policy="offset_noise").batch_size
        torch.Size([2, 5])
    """
    if policy not in ("random", "offset_noise"):
        raise ValueError(f"policy must be 'random' or 'offset_noise', got {policy!r}.")
    generator = torch.Generator().manual_seed(seed)
    torch.manual_seed(seed)
    env.set_seed(seed)
    action_dim = env.action_spec.shape[-1]
    batched = len(env.batch_size) > 0
    rows = env.batch_size.numel()
    slots: list[TensorDictBase | None] = [None] * count
    attempts = 0
    max_attempts = max_attempts or 10 * count
    while (missing := [k for k, td in enumerate(slots) if td is None]) != []:
        if attempts >= max_attempts:
            done = count - len(missing)
            raise RuntimeError(
                f"Only {done} of {count} trajectories reached {length} steps in {max_attempts} attempts; "
                "use shorter validation trajectories for this environment."
            )
        targets = [missing[j % len(missing)] for j in range(rows)]  # the slot each row fills
        attempts += rows
        rollout_policy = None
        if policy == "offset_noise":
            offsets = [
                (torch.rand(action_dim, generator=generator) * 2 - 1) * ((k % 4) / 3)
                for k in targets
            ]
            offset = torch.stack(offsets) if batched else offsets[0]
            rollout_policy = OffsetNoisePolicy(offset, generator=generator)
        if batched:  # finished rows wait (partial steps) until every row is done
            td = env.rollout(length, policy=rollout_policy, break_when_all_done=True)
        else:
            td = env.rollout(length, policy=rollout_policy, break_when_any_done=True)[None]
        if td.shape[1] < length:
            continue
        complete = ~td["next", "done"][:, :-1].flatten(1).any(-1)
        for row, k in enumerate(targets):
            if complete[row] and slots[k] is None:
                slots[k] = td[row]
    return torch.stack(slots, 0).contiguous()
