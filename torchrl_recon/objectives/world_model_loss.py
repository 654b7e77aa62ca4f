"""Training loss of the LSTM world model."""

from __future__ import annotations

from typing import Literal

import torch
from tensordict import NestedKey, TensorDict, TensorDictBase
from torchrl.objectives import LossModule

from torchrl_recon.modules.checks import check_int, check_type, in_graph
from torchrl_recon.modules.fitted import WORLD_MODEL, warn_unfitted
from torchrl_recon.modules.world_model import LSTMWorldModel
from torchrl_recon.objectives.sequences import as_sequences, marked_slice_len, sequence_mask


class WorldModelPredictionLoss(LossModule):
    """Δs prediction error of an :class:`~torchrl_recon.modules.LSTMWorldModel`.

    Two modes:

    * ``"one_step"``: teacher-forced; the squared error of the standardised Δs_{t+1} at every step.
    * ``"multi_step"``: warm up on the first ``window`` steps of each sequence, then roll out
      the rest with the real actions, feeding predictions back (as the planner does); the
      squared error of the predicted states, standardised by the state statistics.

    Beside TorchRL's :class:`~torchrl.objectives.WorldModelLoss`: that one fits the heads of a
    TorchRL ``WorldModel`` on single transitions (reward, done, a decoder's reconstruction, a
    latent target); this one fits the LSTM's whole multi-step prediction, rolled out as the
    planner rolls it out. Both take a TorchRL replay buffer's sample as it comes.

    A padded batch (its ``("collector", "mask")`` marks real steps, see
    ``make_sequence_buffer(pad_short=True)``) counts real steps only, episodes shorter than
    the warm-up started at rest (:meth:`~torchrl_recon.modules.LSTMWorldModel.prediction_loss`).

    The world model's normalisation should be fitted first (``fit_normalization``, as
    :func:`~torchrl_recon.fitting.fit_world_model` does): the first call on a model that was
    never fitted warns once (``UserWarning``) that the loss runs in identity statistics.

    Args:
        world_model: the model to train.

    Keyword Args:
        mode: ``"multi_step"`` (default) or ``"one_step"``.
        slice_len: length of the sequences in a flat ``SliceSampler`` batch; by default read from
            the marks the sampler writes (``("next", "truncated")`` at each slice's end), so the
            loss takes a TorchRL replay buffer's sample as TorchRL's ``WorldModelLoss`` does.
        obs_key, action_key, next_obs_key: TensorDict keys.

    Examples:
        >>> model = LSTMWorldModel(6, 3, window=4)
        >>> model.fit_normalization(torch.randn(32, 6), torch.randn(32, 3), torch.randn(32, 6))
        >>> loss = WorldModelPredictionLoss(model, slice_len=8)
        >>> td = TensorDict({"observation": torch.randn(16, 6), "action": torch.randn(16, 3),
        ...                  ("next", "observation"): torch.randn(16, 6)}, [16])
        >>> loss(td)["loss_world_model"].shape
        torch.Size([])
    """

    def __init__(
        self,
        world_model: LSTMWorldModel,
        *,
        mode: Literal["multi_step", "one_step"] = "multi_step",
        slice_len: int | None = None,
        obs_key: NestedKey = "observation",
        action_key: NestedKey = "action",
        next_obs_key: NestedKey = ("next", "observation"),
    ) -> None:
        super().__init__()
        check_type("world_model", world_model, LSTMWorldModel, "an LSTMWorldModel")
        if slice_len is not None:
            check_int("slice_len", slice_len)
        if mode not in ("multi_step", "one_step"):
            raise ValueError(f"mode must be 'multi_step' or 'one_step', got {mode!r}.")
        self.world_model, self.mode, self.slice_len = world_model, mode, slice_len
        self.obs_key, self.action_key, self.next_obs_key = obs_key, action_key, next_obs_key
        self.fit_checked = False
        """Whether the world model's normalisation was checked (at the first call, warned if unfitted)."""

    def forward(self, tensordict: TensorDictBase) -> TensorDictBase:
        slice_len = self.slice_len
        if slice_len is None and tensordict.batch_dims == 1:  # a SliceSampler's flat batch
            slice_len = marked_slice_len(tensordict)
        td = as_sequences(tensordict, slice_len)
        obs, action, next_obs = (
            td.get(self.obs_key),
            td.get(self.action_key),
            td.get(self.next_obs_key),
        )
        model = self.world_model
        mask = sequence_mask(td)
        if mask is not None:  # padded slices: only real steps count
            loss = model.prediction_loss(obs, action, next_obs, self.mode, mask=mask)
        elif self.mode == "one_step":
            pred = model.predict_delta(obs, action)
            target = model.delta_norm.normalize(next_obs - obs)
            loss = (pred - target).pow(2).mean()
        else:
            window = model.window
            if obs.shape[-2] <= window:
                raise ValueError(
                    f"multi_step loss needs sequences longer than window={window}, got length {obs.shape[-2]}."
                )
            pred = model.imagine(
                obs[..., :window, :],
                action[..., :window, :],
                obs[..., window, :],
                action[..., None, window:, :],
            )[..., 0, :, :]
            loss = ((pred - next_obs[..., window:, :]) / model.obs_norm.scale).pow(2).mean()
        if not in_graph() and not torch.isfinite(loss):  # a graph: the fit checks it
            raise FloatingPointError(
                f"world-model loss is {loss.item()}; check the data and the learning rate."
            )
        if not in_graph() and not self.fit_checked:
            self.fit_checked = True
            warn_unfitted(model, WORLD_MODEL, type(self).__name__)
        return TensorDict({"loss_world_model": loss}, [])
