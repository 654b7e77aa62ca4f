"""Data collection through TorchRL's own ``Collector``: random actions (the paper's random exploration) or a policy."""

from __future__ import annotations

import torch
from tensordict import TensorDictBase
from tensordict.nn import TensorDictModuleBase
from torchrl.collectors import Collector
from torchrl.envs import EnvBase
from tqdm.auto import tqdm

from torchrl_recon.envs.threads import keep_num_threads
from torchrl_recon.modules.checks import check_int


def default_frames_per_batch(frames: int, largest: int = 1000, smallest: int = 100) -> int:
    """The largest divisor of ``frames`` up to ``largest``, so no batch collects unused steps.

    When every such divisor is below ``smallest`` (batches that small cost per-batch overhead),
    the fewest near-equal batches up to ``largest``, whose steps past ``frames`` (fewer than one
    per batch) are dropped: 1019 frames are 2 batches of 510, 1 step dropped.

    Examples:
        >>> default_frames_per_batch(15000), default_frames_per_batch(1500), default_frames_per_batch(1019)
        (1000, 750, 510)
    """
    divisor = next(d for d in range(min(frames, largest), 0, -1) if frames % d == 0)
    if divisor >= min(smallest, frames):
        return divisor
    batches = -(-frames // largest)
    return -(-frames // batches)


def collect_random(
    env: EnvBase,
    *,
    frames: int,
    seed: int,
    frames_per_batch: int | None = None,
    progress: bool = False,
    episodes: int | None = None,
) -> TensorDictBase:
    """Collect ``frames`` steps of uniform random actions (see :func:`collect`; ``episodes``
    stops at that many whole episodes).

    Examples:
        >>> from torchrl_recon.envs import make_env
        >>> data = collect_random(make_env("drone", seed=0, max_episode_steps=100), frames=200, seed=0)
        >>> data["observation"].shape
        torch.Size([200, 12])
    """
    return collect(
        env,
        None,
        frames=frames,
        seed=seed,
        frames_per_batch=frames_per_batch,
        progress=progress,
        episodes=episodes,
    )


def collect(
    env: EnvBase,
    policy: TensorDictModuleBase | None,
    *,
    frames: int,
    seed: int,
    frames_per_batch: int | None = None,
    progress: bool = False,
    desc: str = "collection",
    episodes: int | None = None,
) -> TensorDictBase:
    """Collect ``frames`` steps from ``env`` with ``policy`` (uniform random actions when None).

    With ``episodes``, ``frames`` is a budget: collection stops at the batch in which that
    many episodes have ended, and the data are cut after the ``episodes``-th end (an env whose
    episodes terminate early collects that many short episodes, not the budget's steps).
    Episodes that never end early fill the budget exactly, so the data are the same as
    without it. One env only.

    Episode length is the env's own (see ``make_env(..., max_episode_steps=...)``).
    Returns flat transitions ``[frames]`` on the CPU (where the replay buffers store them, also
    when the env casts its data to a GPU policy) carrying ``("collector", "traj_ids")`` so a
    ``SliceSampler`` never crosses an episode. Same ``seed`` → same data.

    A batched env of ``B`` envs (``make_env(..., num_envs=B)``) steps them together, about
    ``frames / B`` steps each (rounded up to a whole batch of ``B`` steps); the result is
    env-major (all of env 0's steps, then env 1's, ...), so every trajectory is contiguous,
    and the collector's trajectory ids tell the envs' trajectories apart. The last ``frames``
    mod ``B`` steps of the last env are dropped.

    Examples:
        >>> from torchrl_recon.envs import make_env
        >>> collect(make_env("drone", seed=0), None, frames=50, seed=0).batch_size
        torch.Size([50])
        >>> data = collect(make_env("drone", seed=0, num_envs=2, parallel=False), None, frames=50, seed=0)
        >>> data.batch_size, data["collector", "traj_ids"].unique().tolist()
        (torch.Size([50]), [0, 1])
    """
    check_int("frames", frames)
    if frames_per_batch is not None:
        check_int("frames_per_batch", frames_per_batch)
    if episodes is not None and (episodes < 1 or env.batch_size.numel() > 1):
        raise ValueError(
            f"episodes={episodes} needs a count >= 1 and one env (got batch size "
            f"{tuple(env.batch_size)}); a batched env collects the frames budget."
        )
    torch.manual_seed(seed)
    # Seeded before the collector exists: its constructor resets the env, and a seed set after
    # that resets the env's state again while the collector keeps the first reset's
    # observation (the first transition jumped, the next episode repeated the first's start).
    env.set_seed(seed)
    envs = env.batch_size.numel()
    frames_per_batch = frames_per_batch or default_frames_per_batch(frames)
    if envs > 1:  # whole batched steps: every env takes the same number of steps
        frames_per_batch = -(-frames_per_batch // envs) * envs
    # whole batches (what TorchRL collects anyway, without its warning); the tail is dropped
    total = -(-frames // frames_per_batch) * frames_per_batch
    # TorchRL resets torch's thread count when the collector shuts a batched env down
    with keep_num_threads():
        collector = Collector(
            env,
            policy=policy,
            frames_per_batch=frames_per_batch,
            total_frames=total,
            split_trajs=False,
            storing_device="cpu",  # the buffers' storage (a GPU policy's env casts to it)
        )
        batches, ended = [], 0
        with tqdm(total=frames, desc=desc, disable=not progress, leave=False) as bar:
            for batch in collector:
                if envs > 1:  # [envs, time]: kept apart until the end, then env-major
                    batches.append(batch.reshape(envs, -1).clone())
                else:
                    batches.append(batch.reshape(-1).clone())
                bar.update(min(batch.numel(), frames - bar.n))
                if episodes is not None:
                    ended += int(batch["next", "done"].sum())
                    if ended >= episodes:
                        break
        collector.shutdown()
    if envs > 1:
        return torch.cat(batches, 1).reshape(-1)[:frames]
    data = torch.cat(batches, 0)[:frames]
    if episodes is not None:
        ends = data["next", "done"].reshape(len(data), -1).any(-1).nonzero().flatten()
        if len(ends) >= episodes:
            data = data[: int(ends[episodes - 1]) + 1]
    return data
