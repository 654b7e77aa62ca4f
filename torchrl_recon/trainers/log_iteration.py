"""A Trainer hook that records and logs each iteration of the online agent."""

from __future__ import annotations

import math
import time
from collections.abc import Callable
from typing import Any

from tensordict import TensorDictBase
from torchrl.trainers import Trainer, TrainerHookBase

from torchrl_recon.fitting.online import (
    IterationRecord,
    episode_returns,
    mean_uncertainty,
    model_error,
)
from torchrl_recon.modules import LSTMWorldModel, UncertaintyEstimator, unfitted_normalizers
from torchrl_recon.modules.checks import check_int, check_type
from torchrl_recon.policies.mpc import REPLANNED
from torchrl_recon.trainers.collector import check_batch


class LogIteration(TrainerHookBase):
    """Record each batch a ``torchrl.trainers.Trainer`` collects as an
    :class:`~torchrl_recon.fitting.online.IterationRecord` and log it through the Trainer's
    logger and progress bar (``online/return``, ``online/model_error``, ``online/mean_u``,
    ``online/replans``, ``online/fit_s``, ``online/plan_s``, ``online/env_s``).

    Before the fit (``pre_steps_log``): the returns of the episodes that ended in the batch, the
    world model's one-step error on it (NaN while the model is unfitted: the random batch),
    its mean u and its re-plans. After the fit (``post_steps_log``): the fit's seconds (from a
    :class:`~torchrl_recon.trainers.ModelFitStepper`), the planning and env seconds, then the
    record is appended to :attr:`records` and given to ``on_iteration``. An
    :class:`~torchrl_recon.trainers.OnlineCollector` says which policy played, its seconds
    and re-plans (:attr:`~torchrl_recon.trainers.OnlineCollector.batch_info`); with another
    collector the collection's wall time is the env's, and a
    :class:`~torchrl_recon.trainers.TimedPolicy` given as ``timed_policy`` splits the planning
    time off. A batch holding NaN or inf (an observation, action or reward: no return or model
    error is made of it) is refused with one ``ValueError`` naming the key and the first row.

    Args:
        world_model: the planner's world model.
        estimator: its estimator (None: mean u is NaN).

    Keyword Args:
        slice_len: the model error's window length (the fits' ``slice_len``).
        on_iteration: called with each record as it is made.
        timed_policy: the collector's policy wrapped in a ``TimedPolicy`` (another collector).

    Examples:
        >>> import torch
        >>> from tensordict import TensorDict
        >>> hook = LogIteration(LSTMWorldModel(3, 1, window=4), slice_len=8)
        >>> batch = TensorDict({"observation": torch.randn(10, 3), "action": torch.rand(10, 1),
        ...     ("next", "observation"): torch.randn(10, 3), ("next", "reward"): torch.ones(10, 1),
        ...     ("next", "done"): torch.arange(10).view(10, 1) == 9,
        ...     ("collector", "traj_ids"): torch.zeros(10, dtype=torch.long)}, [10])
        >>> hook.before_fit(batch)["online/return"]
        10.0
        >>> _ = hook.after_fit(batch)
        >>> record = hook.records[-1]
        >>> record.episode_returns, record.env_steps, math.isnan(record.model_error)
        ([10.0], 10, True)
    """

    def __init__(
        self,
        world_model: LSTMWorldModel,
        estimator: UncertaintyEstimator | None = None,
        *,
        slice_len: int,
        on_iteration: Callable[[IterationRecord], None] | None = None,
        timed_policy: Any = None,
    ) -> None:
        check_type("world_model", world_model, LSTMWorldModel, "an LSTMWorldModel")
        if estimator is not None:
            check_type("estimator", estimator, UncertaintyEstimator, "an UncertaintyEstimator")
        check_int("slice_len", slice_len)
        if on_iteration is not None and not callable(on_iteration):
            raise TypeError(f"on_iteration must be callable or None, got {on_iteration!r}.")
        self.world_model, self.estimator, self.slice_len = world_model, estimator, slice_len
        self.on_iteration, self.timed_policy = on_iteration, timed_policy
        self.records: list[IterationRecord] = []
        """One :class:`~torchrl_recon.fitting.IterationRecord` per batch, in order."""
        self._trainer: Trainer | None = None
        self._seen: dict[str, Any] = {}
        self._last_end = time.perf_counter()
        self._planned_s = 0.0

    def before_fit(self, batch: TensorDictBase) -> dict:
        """The batch's returns, model error, mean u and re-plans, before the models see it."""
        arrived = time.perf_counter()
        info = dict(getattr(self._collector(), "batch_info", None) or {})
        fitted = not unfitted_normalizers(self.world_model)
        u_ready = self.estimator is not None and not unfitted_normalizers(self.estimator)
        if "policy" not in info:  # another collector: random actions up to init_random_frames
            random_frames = getattr(self._collector(), "init_random_frames", None) or 0
            steps = self._trainer.collected_frames if self._trainer is not None else 0
            info["policy"] = "random" if steps <= random_frames else "mpc"
        if "replans" not in info:
            info["replans"] = int(batch[REPLANNED].sum()) if REPLANNED in batch.keys() else 0
        if "plan_s" not in info:
            planned = getattr(self.timed_policy, "seconds", 0.0)
            info["plan_s"], self._planned_s = planned - self._planned_s, planned
            info["env_s"] = arrived - self._last_end - info["plan_s"]
        check_batch(batch)  # a NaN reward: no return is made of it
        flat = batch.reshape(-1)
        stepper = self._stepper()
        info["fits_before"] = stepper.fits if stepper is not None else 0
        self._seen = info | {
            "returns": episode_returns(flat),
            "model_error": model_error(self.world_model, flat, self.slice_len)
            if fitted
            else math.nan,
            "mean_u": mean_uncertainty(self.estimator, flat) if u_ready else None,
        }
        returns = self._seen["returns"]
        out = {"online/replans": info["replans"]}
        if returns:
            out["online/return"] = sum(returns) / len(returns)
        for key in ("model_error", "mean_u"):
            if self._seen[key] is not None and math.isfinite(self._seen[key]):
                out[f"online/{key}"] = self._seen[key]
        return out | {"log_pbar": True}

    def after_fit(self, batch: TensorDictBase) -> dict:
        """The record of the batch, with the fit's seconds; appended to :attr:`records`."""
        seen, trainer = self._seen, self._trainer
        if seen["mean_u"] is None:  # the estimator was unfitted before this batch's fit
            seen["mean_u"] = mean_uncertainty(self.estimator, batch.reshape(-1))
        stepper = self._stepper()
        fitted_now = stepper is not None and stepper.fits > seen["fits_before"]
        fit_s = stepper.last_fit["fit_s"] if fitted_now else 0.0
        steps = trainer.collected_frames if trainer is not None else batch.numel()
        iteration = seen.get("iteration", len(self.records))
        record = IterationRecord(
            iteration,
            steps,
            seen["returns"],
            seen["model_error"],
            seen["mean_u"],
            seen["replans"],
            fit_s,
            seen["plan_s"],
            seen["env_s"],
            policy=seen["policy"],
        )
        self.records.append(record)
        if self.on_iteration is not None:
            self.on_iteration(record)
        self._last_end = time.perf_counter()
        return {"online/fit_s": fit_s, "online/plan_s": record.plan_s, "online/env_s": record.env_s}

    def _stepper(self) -> Any:
        """The Trainer's stepper if it fits whole models (a ModelFitStepper), else None."""
        stepper = getattr(self._trainer, "optimization_stepper", None)
        return stepper if hasattr(stepper, "last_fit") else None

    def _collector(self) -> Any:
        return None if self._trainer is None else self._trainer.collector

    def state_dict(self) -> dict[str, Any]:
        return {"records": [r.as_dict() for r in self.records]}

    def load_state_dict(self, state_dict: dict[str, Any]) -> None:
        self.records = [IterationRecord(**r) for r in state_dict["records"]]

    def start(self) -> None:
        """Start the clocks (``setup``: the Trainer's collection begins)."""
        self._last_end = time.perf_counter()
        self._planned_s = getattr(self.timed_policy, "seconds", 0.0)

    def register(self, trainer: Trainer, name: str = "log_iteration") -> None:
        self._trainer = trainer
        trainer.register_op("setup", self.start)
        trainer.register_op("pre_steps_log", self.before_fit)
        trainer.register_op("post_steps_log", self.after_fit)
        trainer.register_module(name, self)
