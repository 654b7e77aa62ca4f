"""A Trainer hook that fits the models' normalisation from the first batch collected."""

from __future__ import annotations

from typing import Any

from tensordict import TensorDictBase
from torchrl.trainers import Trainer, TrainerHookBase

from torchrl_recon.modules import (
    LSTMWorldModel,
    RewardModel,
    UncertaintyEstimator,
    unfitted_normalizers,
)
from torchrl_recon.modules.checks import check_finite_keys, check_keys, check_type


class FitNormalization(TrainerHookBase):
    """Fit the world model's (and the estimator's) normalisation from the first batch a
    ``torchrl.trainers.Trainer`` collects, once, before any loss or plan reads it; later
    batches leave it as fitted (the statistics a model was trained in stay its own). A model
    already fitted (loaded from a checkpoint) is left alone.

    For a Trainer whose loss is the library's :class:`~torchrl_recon.objectives.WorldModelPredictionLoss`
    or :class:`~torchrl_recon.objectives.UncertaintyLoss` with TorchRL's own optimiser: without
    it the networks train in unfitted (identity) units and a planner refuses them.
    :class:`~torchrl_recon.trainers.ModelFitStepper` needs no such hook: its first fit fits the
    normalisation from its training split. Registered at ``batch_process``; give it the
    random batch (``init_random_frames``) so the statistics cover the env's range. A world
    model of members fits every member from the same batch; a learned ``reward_model``
    (:class:`~torchrl_recon.modules.RewardModel`) is fitted from the batch's rewards too. A batch
    holding NaN or inf is refused (``ValueError`` naming the key and its first row).

    Examples:
        >>> import torch
        >>> from tensordict import TensorDict
        >>> world = LSTMWorldModel(3, 1, window=4)
        >>> hook = FitNormalization(world)
        >>> obs = torch.randn(20, 3)
        >>> batch = TensorDict({"observation": obs, "action": torch.rand(20, 1),
        ...     ("next", "observation"): obs + 1}, [20])
        >>> _ = hook(batch)
        >>> bool(world.obs_norm.fitted), world.delta_norm.loc.tolist()
        (True, [1.0, 1.0, 1.0])
    """

    def __init__(
        self,
        world_model: LSTMWorldModel,
        estimator: UncertaintyEstimator | None = None,
        *,
        reward_model: RewardModel | None = None,
    ) -> None:
        check_type("world_model", world_model, LSTMWorldModel, "an LSTMWorldModel")
        if estimator is not None:
            check_type("estimator", estimator, UncertaintyEstimator, "an UncertaintyEstimator")
        if reward_model is not None:
            check_type("reward_model", reward_model, RewardModel, "a RewardModel")
        self.world_model, self.estimator, self.reward_model = world_model, estimator, reward_model
        self.done = False

    def __call__(self, batch: TensorDictBase) -> TensorDictBase:
        if self.done:
            return batch
        world_unfitted = bool(unfitted_normalizers(self.world_model))
        estimator_unfitted = self.estimator is not None and bool(
            unfitted_normalizers(self.estimator)
        )
        keys = ["observation", "action"]
        if world_unfitted:
            keys.append(("next", "observation"))
        if world_unfitted or estimator_unfitted:
            check_keys("the collected batch", batch, keys)
            check_finite_keys(batch, keys, where="the collected batch")
        flat = batch.reshape(-1)
        obs, action = flat["observation"], flat["action"]
        if world_unfitted:
            world = self.world_model
            members = [world] if world.num_members is None else world.split()
            for member in members:
                member.fit_normalization(obs, action, flat["next", "observation"])
            for r, member in enumerate(members if world.num_members is not None else []):
                world.load_member(r, member)
        if estimator_unfitted:
            self.estimator.fit_normalization(obs, action)
        rewards = self.reward_model
        if rewards is not None and unfitted_normalizers(rewards):
            check_finite_keys(
                batch, [("next", "observation"), ("next", "reward")], where="the collected batch"
            )
            rewards.fit_normalization(
                obs, action, flat["next", "observation"], flat["next", "reward"]
            )
        self.done = True
        return batch

    def state_dict(self) -> dict[str, Any]:
        return {"done": self.done}

    def load_state_dict(self, state_dict: dict[str, Any]) -> None:
        self.done = bool(state_dict["done"])

    def register(self, trainer: Trainer, name: str = "fit_normalization") -> None:
        trainer.register_op("batch_process", self)
        trainer.register_module(name, self)
