"""The random data a run starts from: its stage (uniform random steps, stored), the check that a
fit can use it, and the warm-up it implies for the policies."""

from __future__ import annotations

from omegaconf import DictConfig
from tensordict import TensorDictBase

from torchrl_recon.collectors import collect_random
from torchrl_recon.data import long_trajectories
from torchrl_recon.envs import closing_env
from torchrl_recon.errors import RecipeError
from torchrl_recon.experiments.context import RunContext
from torchrl_recon.experiments.recipe_env import build_env


def random_data_stage(
    ctx: RunContext, name: str, *, frames: int, episode_steps: int | None = None, keys: tuple = ()
) -> TensorDictBase:
    """Stage ``name``: ``frames`` uniform random steps (``num_envs`` envs as one batch), stored
    as ``buffers/<name>`` (only ``keys``, if given); returns the stored data."""

    def run() -> dict:
        seed = ctx.stage_seed(name)
        env = build_env(ctx.cfg, seed=seed, episode_steps=episode_steps, num_envs=ctx.cfg.num_envs)
        with closing_env(env):  # the collector has closed a batched env already
            data = collect_random(env, frames=frames, seed=seed, progress=ctx.cfg.progress)
        ctx.stages.save_data(name, data.select(*keys) if keys else data)
        return {"steps": data.numel()}

    ctx.stages.run(name, run)
    return ctx.stages.load_data(name)


def check_random_data(cfg: DictConfig, data: TensorDictBase, key: str = "random_steps") -> None:
    """Refuse random ``data`` (``key`` steps) without two episodes a fit can use, each ended or
    of ``training.slice_len`` steps: a fit holds whole episodes out to validate. Where episodes
    may end early (``env.termination``), it replaces the recipe check ``key >=
    env.episode_steps + training.slice_len``.

    Raises:
        RecipeError: naming ``key``, before any fit.

    Examples:
        >>> import torch
        >>> from omegaconf import OmegaConf
        >>> from tensordict import TensorDict
        >>> cfg = OmegaConf.create({"training": {"slice_len": 4}, "random_steps": 5,
        ...     "env": {"episode_steps": 10}})
        >>> data = TensorDict({("collector", "traj_ids"): torch.tensor([0, 0, 0, 1, 1]),
        ...     ("next", "done"): torch.tensor([[0], [0], [1], [0], [0]]).bool()}, [5])
        >>> check_random_data(cfg, data)  # doctest: +ELLIPSIS
        Traceback (most recent call last):
        torchrl_recon.errors.RecipeError: 'random_steps' = 5 gave 1 episode that ended or held...
    """
    t = cfg.training
    count = long_trajectories(data, t.slice_len, ended=True)
    if count < 2:
        raise RecipeError(
            f"'{key}' = {cfg[key]} gave {count} episode{'' if count == 1 else 's'} that ended or "
            f"held training.slice_len = {t.slice_len} steps; a fit holds whole episodes out to "
            f"validate, so it needs two: raise {key} (env.episode_steps + training.slice_len = "
            f"{cfg.env.episode_steps + t.slice_len} always gives two) in a new output_dir."
        )


def warmup_mode(cfg: DictConfig, data: TensorDictBase) -> str:
    """The recipe's ``warmup`` (control and online kinds), ``auto`` resolved on the random
    ``data`` as :class:`~torchrl_recon.experiments.config.ControlConfig` says (a random warm-up
    would end most MPC episodes before their first plan). Most, not all: one random episode that
    lasted longer (InvertedPendulum's reach 20-26 steps now and then) keeps ``plan``.

    Examples:
        >>> import torch
        >>> from omegaconf import OmegaConf
        >>> from tensordict import TensorDict
        >>> cfg = OmegaConf.create({"warmup": "auto", "training": {"slice_len": 4}})
        >>> ids = torch.tensor([0, 0, 0, 1, 1, 1, 1, 1, 2, 2, 3, 3])  # episodes of 3, 5, 2, 2 steps
        >>> data = TensorDict({("collector", "traj_ids"): ids}, [12])
        >>> warmup_mode(cfg, data), warmup_mode(OmegaConf.merge(cfg, {"warmup": "zeros"}), data)
        ('plan', 'zeros')
    """
    mode = str(cfg.warmup)
    if mode != "auto":
        return mode
    long, episodes = (long_trajectories(data, n) for n in (cfg.training.slice_len, 1))
    return "plan" if 2 * long < episodes else "random"
