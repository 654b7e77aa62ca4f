"""Training loss of a learned reward and termination (:class:`~torchrl_recon.modules.RewardModel`)."""

from __future__ import annotations

import torch
from tensordict import TensorDict, TensorDictBase
from torchrl.objectives import LossModule

from torchrl_recon.modules.checks import check_finite, in_graph
from torchrl_recon.modules.reward_model import RewardModel
from torchrl_recon.objectives.sequences import sequence_mask


class RewardLoss(LossModule):
    """Fit a :class:`~torchrl_recon.modules.RewardModel` on real transitions: the mean square
    error of the standardised reward plus, where it learns the termination, its binary cross
    entropy against ``("next", "terminated")``.

    Reads any batch of transitions (flat ``[B]``, or ``[B, L]`` sequences from the fits' slice
    buffers); padded steps (``("collector", "mask")`` False) do not count. A NaN or inf reward
    is refused, naming the key and its first index.

    Args:
        reward_model: the model to train.

    Examples:
        >>> from torchrl_recon.modules import RewardModel
        >>> model = RewardModel(3, 1, termination=True)
        >>> s = torch.randn(16, 3)
        >>> td = TensorDict({"observation": s, "action": torch.randn(16, 1),
        ...     ("next", "observation"): s + 0.1, ("next", "reward"): s[:, :1],
        ...     ("next", "terminated"): s[:, :1] > 1}, [16])
        >>> model.fit_normalization(s, td["action"], s + 0.1, s[:, 0])
        >>> RewardLoss(model)(td)["loss_reward"].shape
        torch.Size([])
    """

    def __init__(self, reward_model: RewardModel) -> None:
        super().__init__()
        if not isinstance(reward_model, RewardModel):
            raise TypeError(f"RewardLoss needs a RewardModel, got {type(reward_model).__name__}.")
        self.reward_model = reward_model

    def forward(self, tensordict: TensorDictBase) -> TensorDictBase:
        model = self.reward_model
        obs, action, next_obs = (tensordict.get(k) for k in model.in_keys)
        reward_key, terminated_key = model.target_keys
        reward = tensordict.get(reward_key) if model.learns_reward else obs.new_zeros(())
        if model.learns_reward:
            check_finite(str(reward_key), reward.detach())
        terminated = (
            tensordict.get(terminated_key) if model.learns_termination else obs.new_zeros(())
        )
        mask = sequence_mask(tensordict) if tensordict.batch_dims >= 1 else None
        loss = model.loss(obs, action, next_obs, reward, terminated, mask=mask)
        if not in_graph() and not torch.isfinite(loss):  # a graph: the fit checks it
            raise FloatingPointError(
                f"reward loss is {loss.item()}; check the data and the learning rate."
            )
        return TensorDict({"loss_reward": loss}, [])
