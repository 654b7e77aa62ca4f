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
        data, offset = renumber_trajectories(data.clone(), offset)
        parts.append(data)
    if not parts:
        raise ValueError("concat_trajectories got no non-empty dataset.")
    return torch.cat(parts, 0)


def renumber_trajectories(data: TensorDictBase, offset: int) -> tuple[TensorDictBase, int]:
    """``data`` (changed in place) with its trajectory ids made ``offset, offset + 1, ...`` in
    their order, and the first id after them.

    Examples:
        >>> from tensordict import TensorDict
        >>> a = TensorDict({("collector", "traj_ids"): torch.tensor([7, 7, 9])}, [3])
        >>> out, following = renumber_trajectories(a, 4)
        >>> out["collector", "traj_ids"].tolist(), following
        ([4, 4, 5], 6)
    """
    _, dense = torch.unique(data.get(TRAJ_KEY), return_inverse=True)
    data.set(TRAJ_KEY, dense + offset)
    return data, offset + int(dense.max()) + 1


class EpisodesTooShort(RuntimeError):
    """:func:`validation_trajectories` drew too few trajectories of ``length`` steps: the env
    ended the others sooner. ``median`` and ``longest``: the steps the attempts reached.

    Examples:
        >>> err = EpisodesTooShort(done=0, count=4, length=25, attempts=40, median=5, longest=8)
        >>> err.longest, str(err).split(";")[0]
        (8, 'Only 0 of 4 trajectories reached 25 steps in 40 attempts (median 5 steps, longest 8)')
    """

    def __init__(
        self, *, done: int, count: int, length: int, attempts: int, median: int, longest: int
    ):
        self.done, self.count, self.length = done, count, length
        self.attempts, self.median, self.longest = attempts, median, longest
        super().__init__(
            f"Only {done} of {count} trajectories reached {length} steps in {attempts} attempts "
            f"(median {median} steps, longest {longest}); use shorter validation trajectories "
            "for this environment."
        )


def episode_lengths(rollout: TensorDictBase) -> torch.Tensor:
    """The steps of each env's first episode in a rollout ``[B, T]``, up to and including its
    first done (``T`` when it never ends).

    Examples:
        >>> from tensordict import TensorDict
        >>> done = torch.tensor([[False, True, True], [False, False, False]])[..., None]
        >>> episode_lengths(TensorDict({("next", "done"): done}, [2, 3])).tolist()
        [2, 3]
    """
    done = rollout["next", "done"].flatten(2).any(-1)  # [B, T]
    return torch.where(done.any(1), done.int().argmax(1) + 1, done.shape[1])


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
    return [rollout[i, :n] for i, n in enumerate(episode_lengths(rollout).tolist())]


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

    Raises:
        EpisodesTooShort: fewer than ``count`` attempts of ``max_attempts`` (default
            ``10 * count``) reached ``length`` steps.

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
    attempts, lengths = 0, []  # the steps each attempt reached
    max_attempts = max_attempts or 10 * count
    while (missing := [k for k, td in enumerate(slots) if td is None]) != []:
        if attempts >= max_attempts:
            done, reached = count - len(missing), torch.cat(lengths)
            raise EpisodesTooShort(
                done=done,
                count=count,
                length=length,
                attempts=max_attempts,
                median=int(reached.median()),
                longest=int(reached.max()),
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
        lengths.append(episode_lengths(td))
        if td.shape[1] < length:
            continue
        complete = ~td["next", "done"][:, :-1].flatten(1).any(-1)
        for row, k in enumerate(targets):
            if complete[row] and slots[k] is None:
                slots[k] = td[row]
    return torch.stack(slots, 0).contiguous()
