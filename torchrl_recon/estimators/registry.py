"""Registry of the uncertainty estimators, built by name (or ``module:Class``) from a config."""

from __future__ import annotations

from torchrl_recon.estimators.ensemble import EnsembleUncertainty
from torchrl_recon.estimators.mc_dropout import MCDropoutUncertainty
from torchrl_recon.estimators.reconstruction import ReconstructionUncertainty
from torchrl_recon.estimators.rnd import RNDUncertainty
from torchrl_recon.estimators.uncertainty import UncertaintyEstimator
from torchrl_recon.estimators.world_model_ensemble import WorldModelEnsembleUncertainty
from torchrl_recon.plugins import check_keywords, resolve_class

ESTIMATORS: dict[str, type[UncertaintyEstimator]] = {
    "reconstruction": ReconstructionUncertainty,
    "ensemble": EnsembleUncertainty,
    "mc_dropout": MCDropoutUncertainty,
    "rnd": RNDUncertainty,
    "world_model_ensemble": WorldModelEnsembleUncertainty,
}
"""The shipped uncertainty estimators by the name a recipe gives (``estimator.kind``)."""


def get_estimator_class(kind: str) -> type[UncertaintyEstimator]:
    """The estimator class ``kind`` names: a key of :data:`ESTIMATORS` or ``module:Class`` (a
    subclass of :class:`UncertaintyEstimator` in a module on ``PYTHONPATH``).

    Raises:
        ValueError: one line: unknown name, a class that cannot be imported, or one that is
            not an :class:`UncertaintyEstimator`.

    Examples:
        >>> get_estimator_class("rnd").__name__
        'RNDUncertainty'
        >>> get_estimator_class("torchrl_recon.estimators:EnsembleUncertainty").__name__
        'EnsembleUncertainty'
    """
    return resolve_class(kind, ESTIMATORS, UncertaintyEstimator, "estimator")


def make_estimator(
    kind: str, obs_dim: int, action_dim: int, *, window: int = 10, **kwargs
) -> UncertaintyEstimator:
    """Build the estimator ``kind`` names as ``Class(obs_dim, action_dim, window=window, **kwargs)``.

    Args:
        kind: a key of :data:`ESTIMATORS` (``"reconstruction"``, ``"ensemble"``,
            ``"mc_dropout"``, ``"rnd"``, ``"world_model_ensemble"``) or ``"module:Class"``, a
            user's own :class:`UncertaintyEstimator`.
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
        ValueError: unknown estimator 'gp'; expected one of ['ensemble', 'mc_dropout', ...] or 'module:Class' (...).
    """
    cls = get_estimator_class(kind)
    try:
        check_keywords(cls, kwargs, positional=2, keywords=("window",))
    except TypeError as e:
        raise ValueError(f"{e} (kind {kind!r}; obs_dim, action_dim and window are given)") from None
    return cls(obs_dim, action_dim, window=window, **kwargs)
