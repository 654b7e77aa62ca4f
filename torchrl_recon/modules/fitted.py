"""Whether a module's normalisation was fitted: what planning refuses and losses warn about.

A :class:`~torchrl_recon.modules.Normalizer` that was never fitted is the identity (loc 0,
scale 1), so a world model or an estimator built by hand and trained or planned with before
``fit_normalization`` silently works in raw units. :func:`unfitted_normalizers` finds such
normalisers (every ``fitted`` buffer of a module, a members' stacked one ``[R]`` included),
:func:`check_fitted` refuses them with one line saying how to fit them, and
:class:`FittedCheck` does that once and re-checks only after the buffers changed.
"""

from __future__ import annotations

import warnings

import torch
from torch import nn

from torchrl_recon.modules.checks import in_graph

__all__ = [
    "FittedCheck",
    "check_fitted",
    "unfitted_before_data",
    "unfitted_normalizers",
    "warn_unfitted",
]

WORLD_MODEL, ESTIMATOR = "world model", "uncertainty estimator"
"""The roles :func:`check_fitted` knows how to advise on."""

_TRAINER_HOOK = (
    "register torchrl_recon.trainers.FitNormalization(world_model, estimator) on your torchrl "
    "Trainer (it fits them from the first batch)"
)


def _fitted_buffers(module: nn.Module) -> list[tuple[str, torch.Tensor]]:
    """``(dotted owner name, fitted buffer)`` of every submodule holding a ``fitted`` buffer
    (meta tensors left out: they hold no value; none for an object that is not a module)."""
    if not isinstance(module, nn.Module):
        return []
    found = []
    for name, sub in module.named_modules():
        buf = sub._buffers.get("fitted")
        if buf is not None and not buf.is_meta:
            found.append((name, buf))
    return found


def _all_fitted(buffers: list[torch.Tensor]) -> list[bool]:
    """Whether each buffer is fitted everywhere (every member), with one host sync per device."""
    if not buffers:
        return []
    if len({b.device for b in buffers}) == 1:
        return torch.stack([b.all() for b in buffers]).tolist()
    return [bool(b.all()) for b in buffers]


def unfitted_normalizers(module: nn.Module) -> list[str]:
    """The dotted names of ``module``'s :class:`~torchrl_recon.modules.Normalizer` submodules whose
    ``fitted`` is False; for members (``num_members=R``, stacked ``fitted`` ``[R]``), those that
    any member has not fitted. The module itself, a bare ``Normalizer``, is named ``""``.

    Examples:
        >>> from torchrl_recon.modules import LSTMWorldModel
        >>> model = LSTMWorldModel(3, 2)
        >>> unfitted_normalizers(model)
        ['obs_norm', 'action_norm', 'delta_norm']
        >>> model.fit_normalization(torch.randn(20, 3), torch.randn(20, 2), torch.randn(20, 3))
        >>> unfitted_normalizers(model)
        []
    """
    found = _fitted_buffers(module)
    flags = _all_fitted([buf for _, buf in found])
    return [name for (name, _), ok in zip(found, flags, strict=True) if not ok]


def _unfitted_members(module: nn.Module, names: list[str]) -> list[int]:
    """The members (indices of the stacked ``fitted`` buffers' first dim) with an unfitted
    normaliser among ``names``; empty for one model."""
    if getattr(module, "num_members", None) is None:
        return []
    stacked = [buf for name, buf in _fitted_buffers(module) if name in names and buf.ndim >= 1]
    if not stacked:
        return []
    fitted = torch.stack([buf.reshape(buf.shape[0], -1).all(-1) for buf in stacked]).all(0)
    return (~fitted).nonzero().flatten().tolist()


def _what(module: nn.Module, names: list[str], role: str) -> str:
    """``"the world model's normalisation (obs_norm, ... of LSTMWorldModel)"``."""
    where = type(module).__name__
    members = [] if role != WORLD_MODEL else _unfitted_members(module, names)
    if members:
        where += f" members {members} of {module.num_members}"
    listed = ", ".join(name or type(module).__name__ for name in names)
    return f"the {role}'s normalisation ({listed} of {where})"


def _direct(module: nn.Module, role: str) -> str:
    """How to fit ``module``'s normalisation from data directly, by role."""
    if role == WORLD_MODEL:
        if getattr(module, "num_members", None) is not None:
            direct = (
                "torchrl_recon.fitting.fit_world_members(world_model, buffer), each member's "
                "fit_normalization(obs, action, next_obs) before LSTMWorldModel.from_members"
            )
        else:
            direct = (
                "world_model.fit_normalization(obs, action, next_obs), "
                "torchrl_recon.fitting.fit_world_model(world_model, buffer)"
            )
    elif role == ESTIMATOR:
        direct = (
            "estimator.fit_normalization(obs, action), "
            "torchrl_recon.fitting.fit_uncertainty(estimator, buffer)"
        )
    else:
        direct = f"{role}.fit_normalization(...)"
    return direct


def _how(module: nn.Module, role: str) -> str:
    """How to fit ``module``'s normalisation, by role."""
    return f"{_direct(module, role)}, or {_TRAINER_HOOK}"


def check_fitted(module: nn.Module, role: str = WORLD_MODEL) -> None:
    """Raise unless every normaliser of ``module`` was fitted (see :func:`unfitted_normalizers`).

    Args:
        module: the module to check (a world model, an estimator, any module).
        role: ``"world model"`` or ``"uncertainty estimator"`` (what the message calls the
            module and how it says to fit it), or another name.

    Raises:
        ValueError: one line naming the unfitted normalisers (and members) and how to fit them.

    Examples:
        >>> from torchrl_recon.modules import ReconstructionUncertainty
        >>> check_fitted(ReconstructionUncertainty(3, 2), "uncertainty estimator")
        Traceback (most recent call last):
        ...
        ValueError: the uncertainty estimator's normalisation (input_norm of ReconstructionUncertainty) was never fitted; fit it from data before planning: estimator.fit_normalization(obs, action), ...
    """
    names = unfitted_normalizers(module)
    if names:
        raise ValueError(
            f"{_what(module, names, role)} was never fitted; fit it from data before planning: "
            f"{_how(module, role)}."
        )


def unfitted_before_data(
    modules: list[tuple[nn.Module | None, str]], owner: str
) -> ValueError | None:
    """The error for a policy ``owner`` that plans at an episode's first step
    (``warmup="plan"``) with one of ``modules`` (``(module, role)``, None skipped) unfitted,
    or None when all are fitted. Such a policy may be called before any data exists: TorchRL's
    ``Collector`` calls its policy once at construction to learn its outputs (unless the policy
    has a complete ``spec`` or ``use_buffers=False``), before any Trainer hook such as
    ``FitNormalization`` could fit anything, so the message says what works there instead.

    Examples:
        >>> from torchrl_recon.modules import LSTMWorldModel
        >>> err = unfitted_before_data([(LSTMWorldModel(3, 2), WORLD_MODEL), (None, ESTIMATOR)], "MPCPolicy")
        >>> print(str(err).split(":")[0])
        the world model's normalisation (obs_norm, action_norm, delta_norm of LSTMWorldModel) was never fitted, and MPCPolicy(warmup='plan') plans at an episode's first step, also when TorchRL's Collector calls it once at construction, before any data
    """
    for module, role in modules:
        names = [] if module is None else unfitted_normalizers(module)
        if names:
            return ValueError(
                f"{_what(module, names, role)} was never fitted, and {owner}(warmup='plan') "
                "plans at an episode's first step, also when TorchRL's Collector calls it once "
                "at construction, before any data: fit the models on data before building the "
                f"collector ({_direct(module, role)}), use {owner}(warmup='random') (random "
                "actions until its context is full; register FitNormalization on the Trainer), "
                "or build Collector(..., use_buffers=False) (it reads the policy's out_keys "
                "instead of calling it)."
            )
    return None


def warn_unfitted(module: nn.Module, role: str, loss: str) -> bool:
    """Warn (``UserWarning``) that ``loss`` is computed with ``module``'s normalisation never
    fitted; returns whether it warned. The losses call it once per instance.

    Examples:
        >>> from torchrl_recon.modules import LSTMWorldModel
        >>> import warnings
        >>> with warnings.catch_warnings(record=True) as caught:
        ...     warnings.simplefilter("always")
        ...     warn_unfitted(LSTMWorldModel(3, 2), "world model", "WorldModelPredictionLoss")
        True
        >>> str(caught[0].message).split(";")[0]
        "WorldModelPredictionLoss is computed with the world model's normalisation (obs_norm, action_norm, delta_norm of LSTMWorldModel) never fitted (identity statistics)"
    """
    names = unfitted_normalizers(module)
    if names:
        warnings.warn(
            f"{loss} is computed with {_what(module, names, role)} never fitted (identity "
            f"statistics); fit it from data first: {_how(module, role)}.",
            UserWarning,
            stacklevel=2,
        )
    return bool(names)


def _version(buf: torch.Tensor) -> int | None:
    """The buffer's in-place write counter (None for an inference tensor, which has none)."""
    try:
        return buf._version
    except RuntimeError:
        return None


class FittedCheck:
    """:func:`check_fitted` of a module's normalisation, done once: once it passed, a later call
    only compares the ``fitted`` buffers with those it saw (the same tensors, no in-place write
    since: ``load_state_dict``, ``fit_normalization``, ``.to()``, a member loaded in), without
    reading their values, so a plan on a GPU does no host sync. Any change re-checks. (An
    inference-mode buffer has no write counter: only its identity is compared.)

    Args:
        role: as :func:`check_fitted`'s.

    Examples:
        >>> from torchrl_recon.modules import LSTMWorldModel
        >>> model, check = LSTMWorldModel(3, 2), FittedCheck("world model")
        >>> model.fit_normalization(torch.randn(20, 3), torch.randn(20, 2), torch.randn(20, 3))
        >>> check(model)  # checks the values once
        >>> check(model)  # passes from what it remembers
        >>> _ = model.load_state_dict(LSTMWorldModel(3, 2).state_dict())  # unfitted weights
        >>> check(model)
        Traceback (most recent call last):
        ...
        ValueError: the world model's normalisation (obs_norm, action_norm, delta_norm of LSTMWorldModel) was never fitted; ...
    """

    def __init__(self, role: str = WORLD_MODEL) -> None:
        self.role = role
        self.passed: tuple | None = None
        """The module that passed and its ``(fitted buffer, version)`` pairs; None until then."""

    def _seen(self, module: nn.Module) -> tuple:
        buffers = tuple(buf for _, buf in _fitted_buffers(module))
        return module, buffers, tuple(_version(buf) for buf in buffers)

    def __call__(self, module: nn.Module) -> None:
        """Raise as :func:`check_fitted` unless ``module`` passed before and is unchanged since
        (not checked while ``torch.compile`` traces: the eager call before it checked)."""
        if in_graph():
            return
        seen = self._seen(module)
        passed = self.passed
        if (
            passed is not None
            and passed[0] is module
            and len(passed[1]) == len(seen[1])
            and all(a is b for a, b in zip(passed[1], seen[1], strict=True))
            and passed[2] == seen[2]
        ):
            return
        self.passed = None
        check_fitted(module, self.role)
        self.passed = seen
