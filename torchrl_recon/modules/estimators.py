"""Registry of the uncertainty estimators, built by name from a config."""

from __future__ import annotations

import inspect

from torchrl_recon.modules.ensemble import EnsembleUncertainty
from torchrl_recon.modules.mc_dropout import MCDropoutUncertainty
from torchrl_recon.modules.reconstruction import ReconstructionUncertainty
from torchrl_recon.modules.rnd import RNDUncertainty
from torchrl_recon.modules.uncertainty import UncertaintyEstimator
from torchrl_recon.modules.world_model_ensemble import WorldModelEnsembleUncertainty

ESTIMATORS: dict[str, type[UncertaintyEstimator]] = {
    "reconstruction": ReconstructionUncertainty,
    "ensemble": EnsembleUncertainty,
    "mc_dropout": MCDropoutUncertainty,
    "rnd": RNDUncertainty,
    "world_model_ensemble": WorldModelEnsembleUncertainty,
}

_POSITIONAL = ("self", "obs_dim", "action_dim", "window")


def make_estimator(
    kind: str, obs_dim: int, action_dim: int, *, window: int = 10, **kwargs
) -> UncertaintyEstimator:
    """Build the estimator registered as ``kind`` in :data:`ESTIMATORS`.

    Args:
        kind: ``"reconstruction"``, ``"ensemble"``, ``"mc_dropout"``, ``"rnd"`` or
            ``"world_model_ensemble"``.
        obs_dim: state size N.
        action_dim: action size M.

    Keyword Args:
        window: T, the number of steps per window.
        **kwargs: the chosen class's own keyword arguments (e.g. ``num_members`` for
            ``"ensemble"``); any other keyword is a ``ValueError`` listing the accepted ones.

    Examples:
        >>> ens = make_estimator("ensemble", 6, 3, window=5, num_members=3)
        >>> type(ens).__name__, ens.config()["num_members"]
        ('EnsembleUncertainty', 3)
        >>> make_estimator("gp", 6, 3)
        Traceback (most recent call last):
        ...
        ValueError: Unknown estimator kind 'gp'; expected one of ['ensemble', 'mc_dropout', ...].
    """
    if kind not in ESTIMATORS:
        raise ValueError(f"Unknown estimator kind {kind!r}; expected one of {sorted(ESTIMATORS)}.")
    cls = ESTIMATORS[kind]
    accepted = sorted(
        name
        for name, param in inspect.signature(cls.__init__).parameters.items()
        if name not in _POSITIONAL
        and param.kind in (param.POSITIONAL_OR_KEYWORD, param.KEYWORD_ONLY)
    )
    unknown = sorted(set(kwargs) - set(accepted))
    if unknown:
        raise ValueError(
            f"{cls.__name__} (kind {kind!r}) does not accept {unknown}; it accepts {accepted} "
            "besides obs_dim, action_dim and window."
        )
    return cls(obs_dim, action_dim, window=window, **kwargs)
