"""The stages of the uncertainty-aware control experiment (the paper's §3.1 and Fig. 3).

``random_data`` → ``models`` → ``setting_<name>`` for each setting (one part record per batch
of ``num_envs`` episodes); each stage takes the
:class:`~torchrl_recon.experiments.context.RunContext` and is resumable.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import torch
from omegaconf import DictConfig
from tensordict import TensorDictBase

from torchrl_recon.envs import close_env
from torchrl_recon.errors import DamagedFileError
from torchrl_recon.experiments.common import (
    build_env,
    build_planner,
    env_entry,
    planning_model,
    random_data_stage,
    state_scale,
)
from torchrl_recon.experiments.context import RunContext
from torchrl_recon.experiments.explore_stages import models_stage
from torchrl_recon.experiments.stats import mean_std
from torchrl_recon.planners import (
    Objective,
    PlanningModel,
    UncertaintyBand,
    cost_to_u_ratio,
    window_uncertainty,
)
from torchrl_recon.policies import MPCPolicy
from torchrl_recon.policies.mpc import FEASIBLE, PRED_COST, PRED_NEXT, PRED_U, REPLANNED

METRICS = (
    "env_return",
    "prediction_mse",
    "cost_error",
    "real_cost",
    "predicted_cost",
    "replans",
    "mean_u",
    "feasible_fraction",
)
STAGES = ("random_data", "models", "setting_{setting}", "random_policy")
"""Stage name templates, in run order (``{setting}`` a setting's name)."""


def episode_metrics(td: TensorDictBase, scale: torch.Tensor) -> dict[str, float]:
    """Predicted-vs-real metrics of one MPC episode (steps taken from a plan only), and its
    ``env_return`` (the env's reward summed over every step, the warm-up's too).

    ``prediction_mse`` is in units of ``scale`` per state dim; costs are summed over planned
    steps. An episode that ended before its first plan has ``env_return`` and NaN for the rest.
    """
    planned = ~torch.isnan(td[PRED_COST].squeeze(-1))
    replanned = td[REPLANNED].squeeze(-1)
    env_return = float(td["next", "reward"].double().sum())
    if not planned.any():
        return {k: float("nan") for k in METRICS} | {
            "env_return": env_return,
            "replans": 0,
            "steps": int(td.shape[0]),
        }
    err = (td[PRED_NEXT][planned] - td["next", "observation"][planned]) / scale
    predicted_cost = float(td[PRED_COST].squeeze(-1)[planned].sum())
    real_cost = float(-td["next", "reward"].squeeze(-1)[planned].sum())
    feasible = td[FEASIBLE].squeeze(-1)[replanned]
    return {
        "env_return": env_return,
        "prediction_mse": float(err.pow(2).mean()),
        "cost_error": abs(predicted_cost - real_cost),
        "real_cost": real_cost,
        "predicted_cost": predicted_cost,
        "replans": int(replanned.sum()),
        "mean_u": float(td[PRED_U].squeeze(-1)[planned].mean()),
        "feasible_fraction": float(feasible.float().mean()) if feasible.numel() else float("nan"),
        "steps": int(td.shape[0]),
    }


def episode_mean_std(episodes: list[dict], metrics: Sequence[str] = METRICS) -> tuple[dict, dict]:
    """Mean and std over episodes of each of ``metrics`` (non-finite values, from episodes
    without a planned step, left out; :func:`~torchrl_recon.experiments.stats.mean_std`).

    Examples:
        >>> mean, std = episode_mean_std([{k: 1.0 for k in METRICS}, {k: 3.0 for k in METRICS}])
        >>> mean["prediction_mse"], round(std["prediction_mse"], 3)
        (2.0, 1.414)
    """
    stats = {m: mean_std((e[m] for e in episodes if m in e), finite=True) for m in metrics}
    return {m: s[0] for m, s in stats.items()}, {m: s[1] for m, s in stats.items()}


def replan_threshold(cfg: DictConfig, per_window_u: torch.Tensor) -> float:
    """The re-planning threshold on u: a quantile of the windows' u, scaled (× ``every`` when
    it bounds Σu over the steps between plans)."""
    r = cfg.replan
    threshold = float(per_window_u.quantile(r.threshold_quantile)) * r.threshold_scale
    return threshold * r.every if r.threshold_on == "cumulative" else threshold


@dataclass
class Controller:
    """What every setting's episodes share: the planning model, the threshold, the β unit
    and the state scale of the reported MSE."""

    model: PlanningModel
    threshold: float
    beta_unit: float
    scale: torch.Tensor


def setting_objective(setting: DictConfig, beta_unit: float) -> tuple[Objective, float]:
    """The setting's objective and its β (× ``beta_unit`` when relative)."""
    b = setting.band
    band = None if b is None else UncertaintyBand(b.low, b.high, b.kind)
    beta = setting.beta * beta_unit if setting.beta_relative else setting.beta
    objective = Objective(
        alpha=setting.alpha, beta=beta, band=band, cost_threshold=setting.cost_threshold
    )
    return objective, beta


def episode_batches(episodes: int, num_envs: int) -> list[range]:
    """The episodes of a setting in batches of ``num_envs`` (the last one may be smaller).

    Examples:
        >>> [list(b) for b in episode_batches(5, 2)]
        [[0, 1], [2, 3], [4]]
    """
    return [range(i, min(i + num_envs, episodes)) for i in range(0, episodes, num_envs)]


def first_done_lengths(td: TensorDictBase) -> list[int]:
    """Per env of a batched rollout ``[B, T]``: the steps up to and including its first done
    (``T`` when it never ends).

    Examples:
        >>> from tensordict import TensorDict
        >>> done = torch.tensor([[False, True, True], [False, False, False]])[..., None]
        >>> first_done_lengths(TensorDict({("next", "done"): done}, [2, 3]))
        [2, 3]
    """
    done = td["next", "done"].flatten(2).any(-1)  # [B, T]
    return torch.where(done.any(1), done.int().argmax(1) + 1, done.shape[1]).tolist()


def episode_batch(
    ctx: RunContext, setting: DictConfig, planner, controller: Controller, batch: range
) -> list[TensorDictBase]:
    """The episodes ``batch`` of ``setting`` played side by side: one MPC rollout of
    ``len(batch)`` envs, episode ``e``'s env seeded with ``stage_seed("setting_<name>_<e>")``;
    returns each episode's steps, cut at its first done.

    The torch RNG (random warm-up actions, the planner's samples) is seeded with the first
    episode's seed and shared by the batch. Envs that ended wait (TorchRL partial steps)
    until every env is done or ``env.episode_steps`` have run.
    """
    cfg, r = ctx.cfg, ctx.cfg.replan
    policy = MPCPolicy(
        planner,
        replan=r.mode,
        replan_every=r.every,
        threshold=controller.threshold if r.mode == "uncertainty" else None,
        threshold_on=r.threshold_on,
        error_threshold=r.error_threshold,
        warmup_steps=max(cfg.warmup_random_steps, controller.model.context_length),
    )
    seeds = [ctx.stage_seed(f"setting_{setting.name}_{e}") for e in batch]
    return play_episodes(ctx, seeds, policy)


def play_episodes(
    ctx: RunContext, seeds: list[int], policy: MPCPolicy | None = None
) -> list[TensorDictBase]:
    """One episode per seed, side by side (a batch of ``len(seeds)`` envs, the torch RNG seeded
    with the first seed), cut at each one's first done; ``policy`` None takes uniform random
    actions (TorchRL's random rollout). Envs that ended wait (TorchRL partial steps) until
    every env is done or ``env.episode_steps`` have run."""
    steps = ctx.cfg.env.episode_steps
    seed = seeds if len(seeds) > 1 else seeds[0]
    device = None if policy is None else ctx.device
    env = build_env(ctx.cfg, seed=seed, episode_steps=steps, policy_device=device)
    if policy is not None:
        env.append_transform(policy.make_tensordict_primer())
    torch.manual_seed(seeds[0])
    if len(seeds) == 1:
        tds = [env.rollout(steps, policy, break_when_any_done=True).cpu()]
    else:
        td = env.rollout(steps, policy, break_when_all_done=True).cpu()
        tds = [td[i, :n] for i, n in enumerate(first_done_lengths(td))]
    close_env(env)
    return tds


def batch_part(
    ctx: RunContext, setting: DictConfig, planner, controller: Controller, batch: range
) -> dict:
    """The part record of one batch of episodes: ``{"metrics", "trajectory_example"}`` for a
    batch of one (the record of a run with ``num_envs = 1``), else ``{"episodes": [metrics
    per episode], "trajectory_example"}``; the metrics are logged, and episode 0's trajectory
    kept."""
    episodes, example = [], None
    for e, td in zip(batch, episode_batch(ctx, setting, planner, controller, batch), strict=True):
        metrics = episode_metrics(td, controller.scale)
        episodes.append(metrics)
        if ctx.logger is not None:
            for key, value in metrics.items():
                if value == value:  # NaN metrics (no planned step) are not logged
                    ctx.logger.log_scalar(f"{setting.name}/{key}", value, step=e)
        if e == 0:
            example = _trajectory(td, setting.name, env_entry(ctx.cfg).state_names)
    if len(episodes) == 1:
        return {"metrics": episodes[0], "trajectory_example": example}
    return {"episodes": episodes, "trajectory_example": example}


def part_episodes(part: dict, batch: range, marker) -> list[dict]:
    """The metrics of each episode a part record holds (checked against its batch's size)."""
    episodes = part["episodes"] if "episodes" in part else [part.get("metrics")]
    if len(episodes) != len(batch) or not all(isinstance(m, dict) for m in episodes):
        raise DamagedFileError(
            f"{marker}: expected the metrics of episodes {batch.start}..{batch.stop - 1} "
            f"({len(batch)} dicts), found {len(episodes)}; it was written with another "
            "num_envs or damaged: delete it to compute those episodes again."
        )
    return episodes


def setting_stage(ctx: RunContext, setting: DictConfig, controller: Controller) -> dict:
    """All episodes of ``setting`` (stage ``setting_<name>``), ``num_envs`` at a time: one part
    record per batch, so a setting stopped half way resumes at its next unfinished batch."""
    name = f"setting_{setting.name}"

    def run():
        objective, beta = setting_objective(setting, controller.beta_unit)
        planner = build_planner(setting.planner, controller.model, objective)
        batches = episode_batches(ctx.cfg.episodes, ctx.cfg.num_envs)
        parts = ctx.stages.run_parts(
            name,
            len(batches),
            lambda b: batch_part(ctx, setting, planner, controller, batches[b]),
            show_progress=ctx.cfg.progress,
        )
        folder = ctx.stages.run_dir / "stages" / name
        episodes = [
            metrics
            for b, (part, batch) in enumerate(zip(parts, batches, strict=True))
            for metrics in part_episodes(part, batch, folder / f"part_{b}.json")
        ]
        first = parts[0]["trajectory_example"] if parts else None
        mean, std = episode_mean_std(episodes)
        unplanned = sum(1 for e in episodes if not _planned(e))
        record = {"episodes": episodes, "mean": mean, "std": std, "trajectory_example": first}
        record["ended_in_warmup"] = unplanned
        if setting.band is not None:  # the across-seed trend test orders the settings by it
            record["band"] = {k: setting.band[k] for k in ("low", "high", "kind")}
        return record | ({"beta_effective": beta} if setting.beta_relative else {})

    return ctx.stages.run(name, run)


def _planned(episode: dict) -> bool:
    """Whether an episode's record has a planned step (its predicted cost is a number)."""
    return episode.get("predicted_cost") == episode.get("predicted_cost")  # NaN: none


def random_policy_stage(ctx: RunContext) -> dict:
    """Stage ``random_policy``: ``episodes`` episodes of uniform random actions, of the
    settings' length, played side by side (TorchRL's random rollout); their env returns."""
    cfg = ctx.cfg

    def run() -> dict:
        seeds = [ctx.stage_seed(f"random_policy_{e}") for e in range(cfg.episodes)]
        returns = [
            float(td["next", "reward"].double().sum())
            for batch in episode_batches(cfg.episodes, cfg.num_envs)
            for td in play_episodes(ctx, [seeds[e] for e in batch])
        ]
        mean, std = mean_std(returns)
        return {"env_returns": returns, "mean": {"env_return": mean}, "std": {"env_return": std}}

    record = ctx.stages.run("random_policy", run)
    record.pop("wall_time_s", None)
    return record


def run(ctx: RunContext) -> dict:
    """Run (or resume) the control experiment; return its results."""
    cfg = ctx.cfg
    frames = cfg.random_episodes * cfg.random_episode_steps
    data = random_data_stage(
        ctx, "random_data", frames=frames, episode_steps=cfg.random_episode_steps
    )
    scale = state_scale(data)
    world, estimator = models_stage(ctx, data, "models")
    length = max(cfg.models.window, cfg.training.slice_len)
    per_window_u = window_uncertainty(data, estimator, sequence_length=length)
    threshold = replan_threshold(cfg, per_window_u)
    relative = any(s.beta_relative for s in cfg.settings)
    beta_unit = cost_to_u_ratio(data, per_window_u) if relative else 1.0
    model = planning_model(cfg, world, estimator)  # the env's action bounds
    controller = Controller(model, threshold, beta_unit, scale)
    results, example = {}, None
    for setting in cfg.settings:
        record = setting_stage(ctx, setting, controller)
        first = record.pop("trajectory_example", None)  # kept once, for the first setting
        example = example or first
        record.pop("wall_time_s", None)
        results[setting.name] = record
    return {
        **ctx.results_header(),
        "replan_threshold": threshold,
        **({"beta_unit": beta_unit} if relative else {}),
        "mse_units": "squared prediction error per state dim divided by its standard deviation in the random data",
        "settings": results,
        "random_policy": random_policy_stage(ctx),
        "trajectory_example": example,
        "wall_time_s": dict(ctx.stages.wall_time_s),
    }


def _trajectory(td: TensorDictBase, setting: str, state_names: tuple[str, ...] = ()) -> dict:
    """Real and predicted next states, u and re-plans of one episode (planned steps), for a Fig. 2 plot."""
    planned = ~torch.isnan(td[PRED_COST].squeeze(-1))
    real = td["next", "observation"][planned]
    return {
        "setting": setting,
        "real": real.tolist(),
        "predicted": td[PRED_NEXT][planned].tolist(),
        "uncertainty": td[PRED_U].squeeze(-1)[planned].tolist(),
        "replanned": td[REPLANNED].squeeze(-1)[planned].tolist(),
        "state_names": list(state_names) or [f"s{i}" for i in range(real.shape[-1])],
    }
