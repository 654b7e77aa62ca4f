"""Training loss of any uncertainty estimator (the autoencoder's is paper eq. 1)."""

from __future__ import annotations

import torch
from tensordict import NestedKey, TensorDict, TensorDictBase
from torchrl.objectives import LossModule

from torchrl_recon.estimators.uncertainty import UncertaintyEstimator
from torchrl_recon.modules.checks import check_int, check_type, in_graph
from torchrl_recon.modules.fitted import ESTIMATOR, warn_unfitted
from torchrl_recon.modules.padding import loss_takes_mask
from torchrl_recon.objectives.sequences import as_sequences, sequence_mask


class UncertaintyLoss(LossModule):
    """Fit an :class:`~torchrl_recon.estimators.UncertaintyEstimator` on real (s, a) sequences.

    Delegates to ``estimator.loss``; for
    :class:`~torchrl_recon.estimators.ReconstructionUncertainty` that is the mean reconstruction
    error u over all windows (paper eq. 1). A padded batch (its ``("collector", "mask")`` marks
    real steps, see ``make_sequence_buffer(pad_short=True)``) passes the mask on: only windows of
    real steps count.

    The estimator's normalisation should be fitted first (``fit_normalization``, as
    :func:`~torchrl_recon.fitting.fit_uncertainty` does): the first call on an estimator that
    was never fitted warns once (``UserWarning``) that the loss runs in identity statistics.

    Args:
        estimator: the estimator to train.

    Keyword Args:
        slice_len: length of the sequences in a flat ``SliceSampler`` batch.
        obs_key, action_key: TensorDict keys.

    Examples:
        >>> from torchrl_recon.modules import ReconstructionUncertainty
        >>> ae = ReconstructionUncertainty(6, 3, window=4)
        >>> td = TensorDict({"observation": torch.randn(16, 6), "action": torch.randn(16, 3)}, [16])
        >>> ae.fit_normalization(td["observation"], td["action"])
        >>> loss = UncertaintyLoss(ae, slice_len=8)
        >>> loss(td)["loss_uncertainty"].shape
        torch.Size([])
    """

    def __init__(
        self,
        estimator: UncertaintyEstimator,
        *,
        slice_len: int | None = None,
        obs_key: NestedKey = "observation",
        action_key: NestedKey = "action",
    ) -> None:
        super().__init__()
        check_type("estimator", estimator, UncertaintyEstimator, "an UncertaintyEstimator")
        if slice_len is not None:
            check_int("slice_len", slice_len)
        self.estimator, self.slice_len = estimator, slice_len
        self.obs_key, self.action_key = obs_key, action_key
        self.fit_checked = False
        """Whether the estimator's normalisation was checked (at the first call, warned if unfitted)."""

    def forward(self, tensordict: TensorDictBase) -> TensorDictBase:
        td = as_sequences(tensordict, self.slice_len)
        obs, action, mask = td.get(self.obs_key), td.get(self.action_key), sequence_mask(td)
        if mask is None:
            loss = self.estimator.loss(obs, action)
        elif loss_takes_mask(self.estimator):
            loss = self.estimator.loss(obs, action, mask=mask)
        else:
            raise ValueError(
                f"{type(self.estimator).__name__} cannot train on padded slices (episodes shorter "
                "than slice_len): its loss takes no mask. Use the reconstruction or rnd estimator, "
                "or slices no longer than the episodes."
            )
        if not in_graph() and not torch.isfinite(loss):  # a graph: the fit checks it
            raise FloatingPointError(
                f"uncertainty loss is {loss.item()}; check the data and the learning rate."
            )
        if not in_graph() and not self.fit_checked:
            self.fit_checked = True
            warn_unfitted(self.estimator, ESTIMATOR, type(self).__name__)
        return TensorDict({"loss_uncertainty": loss}, [])
