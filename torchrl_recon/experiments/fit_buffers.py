"""The training and validation buffers of a recipe's fits: a dataset split by trajectory into
sequence buffers, and the check of what padded (short-episode) slices can train."""

from __future__ import annotations

from omegaconf import DictConfig
from tensordict import TensorDictBase
from torchrl.data import TensorDictReplayBuffer

from torchrl_recon.data import FIT_KEYS, needs_padding, sequence_buffers, split_by_trajectory
from torchrl_recon.errors import RecipeError
from torchrl_recon.modules import get_estimator_class
from torchrl_recon.modules.padding import loss_takes_mask


def check_padding(cfg: DictConfig) -> None:
    """Refuse what padded slices (:func:`split_buffers`) cannot train, before the first fit:
    ``training.window_sampling = step``, or an estimator whose loss takes no mask
    (``models.uncertainty.kind``, or each of a calibrate recipe's ``estimators``).

    Raises:
        RecipeError: naming the key to change.

    Examples:
        >>> from omegaconf import OmegaConf
        >>> cfg = OmegaConf.create({"training": {"slice_len": 8, "window_sampling": "step"},
        ...     "models": {"window": 4, "uncertainty": {"kind": "reconstruction"}}})
        >>> check_padding(cfg)  # doctest: +ELLIPSIS
        Traceback (most recent call last):
        torchrl_recon.errors.RecipeError: episodes shorter than training.slice_len = 8 steps are padded...
    """
    t = cfg.training
    where = f"episodes shorter than training.slice_len = {t.slice_len} steps are padded"
    lower = f"or lower training.slice_len (above models.window = {cfg.models.window})"
    if t.window_sampling != "trajectory":
        raise RecipeError(
            f"{where}, which needs training.window_sampling = trajectory (got "
            f"{t.window_sampling}): set it, {lower}."
        )
    if "estimators" in cfg:  # a calibrate recipe fits each of its estimators
        named = [(f"estimators[{i}].kind", spec) for i, spec in enumerate(cfg.estimators)]
    else:
        named = [("models.uncertainty.kind", cfg.models.uncertainty)]
    for key, spec in named:
        if not loss_takes_mask(get_estimator_class(spec.kind)):
            raise RecipeError(
                f"{where}, and {key} = {spec.kind} cannot train on padded slices: "
                f"use reconstruction or rnd, {lower}."
            )


def split_buffers(
    cfg: DictConfig, data: TensorDictBase, seed: int, keys: tuple = FIT_KEYS
) -> tuple[TensorDictReplayBuffer, TensorDictReplayBuffer]:
    """Training and validation sequence buffers of ``data`` (its ``keys``), split by trajectory
    (``seed``); when an episode ended shorter than ``slice_len`` steps or a split has no
    trajectory that long (``training.short_episodes``), both pad shorter ones
    (:func:`~torchrl_recon.data.sequence_buffers`), once :func:`check_padding` passes."""
    t = cfg.training
    parts = split_by_trajectory(data, t.val_fraction, seed=seed)
    short = str(t.get("short_episodes", "pad"))
    if needs_padding(t.slice_len, *parts, short_episodes=short):
        check_padding(cfg)
    sizes = dict(slice_len=t.slice_len, num_slices=t.num_slices, sampling=t.window_sampling)
    return sequence_buffers(parts, **sizes, keys=keys, short_episodes=short)
