"""The one rollout engine every planner uses: (context, K×H actions) → states, cost, uncertainty."""

from __future__ import annotations

import contextlib
import contextvars
import functools
import math
from collections.abc import Callable, Iterator, Sequence
from dataclasses import dataclass
from typing import TYPE_CHECKING

import torch
from torch import nn
from torchrl.envs import EnvBase

from torchrl_recon.devices import module_device, module_dtype
from torchrl_recon.estimators.uncertainty import UncertaintyEstimator, checked_scores
from torchrl_recon.modules.checks import (
    check_features,
    check_finite,
    check_int,
    check_window,
    in_graph,
)
from torchrl_recon.modules.fitted import ESTIMATOR, WORLD_MODEL, FittedCheck
from torchrl_recon.modules.reward_model import LEARNED_REWARD, RewardModel
from torchrl_recon.modules.world_model import LSTMWorldModel
from torchrl_recon.planners.bounds import action_bounds, bounds_from_spec
from torchrl_recon.planners.executors import executor_for

if TYPE_CHECKING:
    from torchrl_recon.planners.executors import Eager

__all__ = ["PlanningModel", "Prediction", "TerminationFn", "check_step_fn"]

CostFn = Callable[[torch.Tensor, torch.Tensor, torch.Tensor], torch.Tensor]
TerminationFn = Callable[[torch.Tensor, torch.Tensor, torch.Tensor], torch.Tensor]
"""``termination(obs, action, next_obs) -> bool [...]``: whether the step ends the episode."""


def check_step_fn(
    name: str,
    fn: Callable,
    obs_dim: int,
    action_dim: int,
    *,
    dtype: torch.dtype = torch.float32,
    device: torch.device | str = "cpu",
    boolean: bool = False,
) -> None:
    """Call a user's per-step function (a cost or a termination) once on zeros ``[2, 3, .]``
    and check it returns one value per step, ``[2, 3]`` (bools for a termination).

    Raises:
        ValueError: naming the function, the shapes it was given and what it returned.

    Examples:
        >>> check_step_fn("cost_fn", lambda s, a, s1: s1.pow(2).sum(-1), 3, 1)
        >>> check_step_fn("cost_fn", lambda s, a, s1: s1, 3, 1)
        Traceback (most recent call last):
        ValueError: cost_fn(obs [2, 3, 3], action [2, 3, 1], next_obs [2, 3, 3]) must return one value per step, a tensor [2, 3], got [2, 3, 3].
    """
    obs = torch.zeros(2, 3, obs_dim, dtype=dtype, device=device)
    action = torch.zeros(2, 3, action_dim, dtype=dtype, device=device)
    call = f"{name}(obs [2, 3, {obs_dim}], action [2, 3, {action_dim}], next_obs [2, 3, {obs_dim}])"
    try:
        with torch.no_grad():
            out = fn(obs, action, obs)
    except Exception as e:  # the user's function: any error is theirs to fix
        raise ValueError(f"{call} failed: {e!r}") from e
    if not isinstance(out, torch.Tensor) or tuple(out.shape) != (2, 3):
        got = list(out.shape) if isinstance(out, torch.Tensor) else type(out).__name__
        raise ValueError(f"{call} must return one value per step, a tensor [2, 3], got {got}.")
    if boolean and out.dtype != torch.bool:
        raise ValueError(
            f"{call} must return bools (True where the step ends the episode), got {out.dtype}."
        )


WORLD_MODEL_PARTS = ("imagine", "obs_dim", "action_dim", "window")
"""What a planning model reads of its world model."""
ESTIMATOR_PARTS = ("score_sequence", "obs_dim", "action_dim", "window")
"""What a planning model reads of its uncertainty estimator."""


def check_parts(name: str, value: object, parts: Sequence[str], expected: str) -> None:
    """Raise ``TypeError`` unless ``value`` has every attribute of ``parts`` (its int dims
    ``*_dim`` and ``window`` at least 1), naming those it lacks.

    Examples:
        >>> check_parts("world_model", "wm", WORLD_MODEL_PARTS, "a world model")
        Traceback (most recent call last):
        ...
        TypeError: world_model must be a world model, got str without imagine, obs_dim, action_dim, window.
    """
    missing = [part for part in parts if not hasattr(value, part)]
    if missing:
        raise TypeError(
            f"{name} must be {expected}, got {type(value).__name__} without {', '.join(missing)}."
        )
    for part in parts:
        if part.endswith("_dim") or part == "window":
            check_int(f"{name}.{part}", getattr(value, part))


BLOCK_ROWS = 1024
"""Candidate rows per block on the CPU, where a block's rollout state and u windows then stay in
cache (``block_rows="auto"``, the sampling planners' default)."""


def resolve_block_rows(block_rows: int | str | None, device: torch.device) -> int | None:
    """The rows per block for ``device``: ``"auto"`` is :data:`BLOCK_ROWS` on the CPU and None
    (all rows in one pass) on any other device, where a pass is bound by kernel launches, not
    cache: K = 10,000 candidates of H = 30 steps hold a few tens of MB (states, actions, the
    LSTM's gates of one step, u's windows), far below a GPU's memory. An int or None is kept.

    Examples:
        >>> resolve_block_rows("auto", torch.device("cpu")), resolve_block_rows("auto", torch.device("cuda"))
        (1024, None)
        >>> resolve_block_rows(256, torch.device("cuda")), resolve_block_rows("all", torch.device("cpu"))
        Traceback (most recent call last):
        ...
        ValueError: block_rows must be a positive int, None (one pass) or 'auto', got 'all'.
    """
    check_block_rows(block_rows)
    if block_rows == "auto":
        return BLOCK_ROWS if device.type == "cpu" else None
    return block_rows


def check_block_rows(block_rows: int | str | None) -> None:
    """Refuse a ``block_rows`` that is not a positive int, None or ``"auto"``."""
    if block_rows is None or block_rows == "auto":
        return
    if isinstance(block_rows, str):
        raise ValueError(
            f"block_rows must be a positive int, None (one pass) or 'auto', got {block_rows!r}."
        )
    check_int("block_rows", block_rows)


_INPUTS_CHECKED: contextvars.ContextVar[bool] = contextvars.ContextVar(
    "planning_inputs_checked", default=False
)
"""True within :func:`inputs_checked`."""


@contextlib.contextmanager
def inputs_checked() -> Iterator[None]:
    """Within it, :meth:`PlanningModel.forward` skips its input checks: a planner's ``plan``
    checked the context and makes the candidates itself, so its passes read no values on the
    host."""
    token = _INPUTS_CHECKED.set(True)
    try:
        yield
    finally:
        _INPUTS_CHECKED.reset(token)


def gather_candidates(x: torch.Tensor, index: torch.Tensor) -> torch.Tensor:
    """Pick candidates ``index`` ``[*B, k]`` along the candidate dim of ``x`` ``[*B, K, ...]`` → ``[*B, k, ...]``."""
    dim = index.ndim - 1
    expanded = index.view(*index.shape, *([1] * (x.ndim - index.ndim))).expand(
        *index.shape, *x.shape[index.ndim :]
    )
    return x.gather(dim, expanded)


def without_grad(fn: Callable) -> Callable:
    """Run ``fn`` under ``torch.inference_mode()``, or ``torch.no_grad()`` inside a graph
    (Inductor cannot compile views of parameters made in inference mode)."""

    @functools.wraps(fn)
    def call(*args, **kwargs):
        mode = torch.no_grad() if in_graph() else torch.inference_mode()
        with mode:
            return fn(*args, **kwargs)

    return call


@dataclass
class Prediction:
    """What the planning model predicts for ``K`` candidates of ``H`` steps.

    Attributes:
        states: predicted s_{t+1..t+H}, ``[*B, K, H, N]``.
        cost: per-step cost c(s_k, a_k, s_{k+1}), ``[*B, K, H]`` (reward is ``-cost``).
        uncertainty: per-step u of the window ending at step k, ``[*B, K, H]``, or None.
    """

    states: torch.Tensor
    cost: torch.Tensor
    uncertainty: torch.Tensor | None

    def take(self, index: torch.Tensor) -> Prediction:
        """The predictions of candidates ``index`` ``[*B, k]``."""
        u = None if self.uncertainty is None else gather_candidates(self.uncertainty, index)
        return Prediction(
            gather_candidates(self.states, index), gather_candidates(self.cost, index), u
        )

    def detach(self) -> Prediction:
        """A copy without autograd history."""
        u = None if self.uncertainty is None else self.uncertainty.detach()
        return Prediction(self.states.detach(), self.cost.detach(), u)

    def first(self, k: int) -> Prediction:
        """The first ``k`` candidates."""
        u = None if self.uncertainty is None else self.uncertainty[..., :k, :]
        return Prediction(self.states[..., :k, :, :], self.cost[..., :k, :], u)

    def cat(self, other: Prediction) -> Prediction:
        """Candidates of ``self`` followed by those of ``other``."""
        return Prediction.concat([self, other])

    @staticmethod
    def concat(predictions: Sequence[Prediction]) -> Prediction:
        """The candidates of every prediction, in order, in one (a single copy of each).

        Examples:
            >>> part = Prediction(torch.zeros(2, 3, 5, 6), torch.zeros(2, 3, 5), None)
            >>> Prediction.concat([part, part, part]).states.shape
            torch.Size([2, 9, 5, 6])
            >>> Prediction.concat([])
            Traceback (most recent call last):
            ...
            ValueError: predictions must hold at least one Prediction, got none.
        """
        if not predictions:
            raise ValueError("predictions must hold at least one Prediction, got none.")
        u = None
        if predictions[0].uncertainty is not None:
            u = torch.cat([p.uncertainty for p in predictions], -2)
        return Prediction(
            torch.cat([p.states for p in predictions], -3),
            torch.cat([p.cost for p in predictions], -2),
            u,
        )

    @property
    def cumulative_cost(self) -> torch.Tensor:
        """Σ_k cost, ``[*B, K]``."""
        return self.cost.sum(-1)

    @property
    def cumulative_uncertainty(self) -> torch.Tensor | None:
        """Σ_k u, ``[*B, K]`` (None without an estimator)."""
        return None if self.uncertainty is None else self.uncertainty.sum(-1)


GRAD_BLOCK_WINDOWS = 4096
"""With autograd, u is scored in row blocks of about this many windows (gradient planning of
many envs at once; one env's 16 restarts × 200 steps stay in one block)."""


def _entering(observation: torch.Tensor, states: torch.Tensor) -> torch.Tensor:
    """s_k for k = 0..H-1: the real state, then the predicted ones but the last, ``[*B, K, H, N]``."""
    start = observation[..., None, None, :].expand(*states.shape[:-2], 1, states.shape[-1])
    return torch.cat([start, states[..., :-1, :]], -2)


class PlanningModel(nn.Module):
    """Compose a world model, a torch cost function and (optionally) an uncertainty estimator.

    Neither network knows about the other: the world model imagines states, the estimator
    scores every T-window of (context + imagined) (s, a) pairs in one call, and the cost
    function scores every transition in one call.

    Both networks' normalisation must be fitted from data: the first :meth:`warmup` or call
    (not the constructor: a policy is built before any data exists) refuses a world model or
    estimator whose normalisation was never fitted, with a ``ValueError`` that says how to fit
    it (:meth:`check_fitted`).

    Args:
        world_model: anything with ``imagine(context_obs, context_action, observation, actions)``
            and ``obs_dim``, ``action_dim``, ``window`` attributes (e.g. :class:`LSTMWorldModel`).
        cost_fn: batched torch cost ``cost(obs, action, next_obs) -> [...]`` (see the env registry).

    A world model with ``num_members=R`` (an :class:`LSTMWorldModel` of R members, an ensemble
    as PETS's) imagines every candidate with each member from the same real context; a
    candidate's cost is the members' mean (PETS's expected cost over its ensemble, one
    deterministic particle per member), its predicted states the members' mean (u and the
    plan's predictions are of those). It costs R rollouts per candidate.

    Keyword Args:
        uncertainty: an :class:`~torchrl_recon.modules.UncertaintyEstimator` or None.
        termination_fn: batched torch ``termination(obs, action, next_obs) -> bool [...]``
            (the env's own rule, e.g. a pole past its limit), or None (episodes never end in
            the model). A candidate stops accruing cost and u after the first step predicted
            to end the episode (that step's cost counts): with a reward, an early end forgoes
            the reward of the steps left; with an alive bonus, falling costs it.
        action_low, action_high: action bounds (floats or ``[M]`` tensors); must be finite.
            Stored as buffers on the world model's device and dtype (``.to()`` moves them
            with the rest); planners draw their candidates there. The defaults (−1, 1) fit
            the shipped envs only: for any other env use :meth:`from_env`, which reads them
            from the env's action spec.
        compile: compile the one-block pass (rollout, cost, u), and a sampling planner's
            whole call: True for the default mode, or a mode name of :data:`COMPILE_MODES`
            (``"reduce-overhead"``: CUDA graphs). The same predictions up to float rounding;
            the first call of each new shape compiles (seconds). Off by default: on a 2-core
            CPU it was slower than eager, on an H200 1.1–1.3× faster a CEM call
            (``docs/benchmarks.md``). On the CPU it needs a C++ compiler (refused here
            without one).
        threads: on the CPU, evaluate the candidates in ``threads`` row blocks (or a
            multiple) on as many threads at once, one core each: each block is one call
            compiled with Inductor's C++ wrapper, which runs without the GIL, so this needs
            ``compile``. The same predictions up to float rounding. The planners then compile
            only this pass, not their whole call. A pass with autograd (the gradient planner)
            and a pass on another device run in one thread. Default 1: one thread. On the
            2-core development machine a CEM call ran 1.52–1.70× faster at 2 (``docs/benchmarks.md``).

    ``compile`` and ``threads`` choose the model's ``executor``
    (:mod:`~torchrl_recon.planners.executors`), which runs its pass and its planners' calls;
    the model itself is the eager algorithm.

    Examples:
        >>> from torchrl_recon.envs.industrial_benchmark import industrial_benchmark_cost
        >>> from torchrl_recon.modules import ReconstructionUncertainty
        >>> world_model, estimator = LSTMWorldModel(6, 3), ReconstructionUncertainty(6, 3)
        >>> obs, action = torch.rand(50, 6), torch.rand(50, 3)  # fit the normalisation on data
        >>> world_model.fit_normalization(obs, action, obs + 0.1 * torch.randn(50, 6))
        >>> estimator.fit_normalization(obs, action)
        >>> pm = PlanningModel(world_model, industrial_benchmark_cost, uncertainty=estimator)
        >>> pred = pm(torch.rand(10, 6), torch.rand(10, 3), torch.rand(6), torch.rand(100, 30, 3))
        >>> pred.states.shape, pred.cost.shape, pred.uncertainty.shape
        (torch.Size([100, 30, 6]), torch.Size([100, 30]), torch.Size([100, 30]))
    """

    def __init__(
        self,
        world_model: LSTMWorldModel,
        cost_fn: CostFn,
        *,
        uncertainty: UncertaintyEstimator | None = None,
        termination_fn: TerminationFn | None = None,
        action_low: float | torch.Tensor = -1.0,
        action_high: float | torch.Tensor = 1.0,
        compile: bool | str = False,
        threads: int = 1,
    ) -> None:
        super().__init__()
        check_parts(
            "world_model", world_model, WORLD_MODEL_PARTS, "a world model (e.g. an LSTMWorldModel)"
        )
        if uncertainty is not None:
            check_parts(
                "uncertainty", uncertainty, ESTIMATOR_PARTS, "an UncertaintyEstimator or None"
            )
        self.world_model, self.cost_fn, self.uncertainty = world_model, cost_fn, uncertainty
        self.termination_fn = termination_fn
        self.obs_dim, self.action_dim = world_model.obs_dim, world_model.action_dim
        if uncertainty is not None and (uncertainty.obs_dim, uncertainty.action_dim) != (
            self.obs_dim,
            self.action_dim,
        ):
            raise ValueError(
                f"uncertainty estimator dims (obs {uncertainty.obs_dim}, action {uncertainty.action_dim}) differ from "
                f"the world model's (obs {self.obs_dim}, action {self.action_dim})."
            )
        # The bounds, and every candidate drawn within them, follow the world model's device and
        # dtype; they are checked on the CPU first.
        dtype, device = torch.float32, torch.device("cpu")
        if isinstance(world_model, nn.Module):
            dtype, device = module_dtype(world_model), module_device(world_model)
        low, high = action_bounds(action_low, action_high, self.action_dim, dtype=dtype)
        self.register_buffer("action_low", low.to(device))
        self.register_buffer("action_high", high.to(device))
        self.executor: Eager = executor_for(compile, threads, device)
        """What runs the pass and the planners' calls (eagerly, compiled, or in row-block
        threads), chosen here from ``compile`` and ``threads``."""
        check_step_fn("cost_fn", cost_fn, self.obs_dim, self.action_dim, dtype=dtype, device=device)
        if termination_fn is not None:
            check_step_fn(
                "termination_fn",
                termination_fn,
                self.obs_dim,
                self.action_dim,
                dtype=dtype,
                device=device,
                boolean=True,
            )
        self._world_model_fitted = FittedCheck(WORLD_MODEL)
        self._uncertainty_fitted = FittedCheck(ESTIMATOR)
        self._learned_fitted = FittedCheck(LEARNED_REWARD)

    @classmethod
    def from_env(
        cls,
        world_model: LSTMWorldModel,
        cost_fn: CostFn,
        env: EnvBase,
        *,
        uncertainty: UncertaintyEstimator | None = None,
        termination_fn: TerminationFn | None = None,
        compile: bool | str = False,
        threads: int = 1,
    ) -> PlanningModel:
        """A planning model whose action bounds are the env's (its ``Bounded`` action spec).

        Raises:
            ValueError: the env's actions are discrete (the planners need continuous bounded
                actions), its action spec is unbounded (pass ``action_low`` / ``action_high``
                to the constructor instead), or its size is not the world model's
                ``action_dim``.

        Examples:
            >>> from torchrl.envs import GymEnv
            >>> env = GymEnv("Pendulum-v1")
            >>> pm = PlanningModel.from_env(LSTMWorldModel(3, 1), lambda s, a, s1: a.pow(2).sum(-1), env)
            >>> pm.action_low.tolist(), pm.action_high.tolist()
            ([-2.0], [2.0])
        """
        if not isinstance(env, EnvBase):
            raise TypeError(f"env must be a torchrl EnvBase, got {type(env).__name__}.")
        low, high = bounds_from_spec(env.action_spec)
        if low.numel() != world_model.action_dim:
            raise ValueError(
                f"the env's action spec has {low.numel()} dims but the world model's action_dim "
                f"is {world_model.action_dim}; build the world model for this env's actions."
            )
        return cls(
            world_model,
            cost_fn,
            uncertainty=uncertainty,
            termination_fn=termination_fn,
            action_low=low,
            action_high=high,
            compile=compile,
            threads=threads,
        )

    @classmethod
    def from_torchrl(
        cls,
        world_model: nn.Module,
        *,
        env: EnvBase | None = None,
        cost_fn: CostFn | None = None,
        uncertainty: UncertaintyEstimator | None = None,
        termination_fn: TerminationFn | None = None,
        action_low: float | torch.Tensor | None = None,
        action_high: float | torch.Tensor | None = None,
        **adapter_kwargs,
    ) -> PlanningModel:
        """A planning model over a TorchRL ``WorldModel`` (or the one a ``WorldModelEnv`` drives),
        through :class:`~torchrl_recon.planners.torchrl_models.TorchRLWorldModelAdapter`: every
        candidate rolled out in one batch, its reward head as the cost (or ``cost_fn`` on the
        states it predicts, decoded where it has a decoder), its done head as the termination (or
        ``termination_fn``), ``uncertainty`` scored on those states. The action bounds are
        ``env``'s (or the ``WorldModelEnv``'s) action spec unless given; ``adapter_kwargs`` go
        to the adapter (``obs_dim``, ``latent_key``, ...).

        Examples:
            >>> from tensordict.nn import TensorDictModule
            >>> from torchrl.envs import GymEnv
            >>> from torchrl.modules import MLP, WorldModel
            >>> encoder = TensorDictModule(nn.Identity(), in_keys=["observation"], out_keys=["latent"])
            >>> dynamics = TensorDictModule(MLP(in_features=4, out_features=3, depth=1),
            ...                             in_keys=["latent", "action"], out_keys=[("next", "latent")])
            >>> reward = TensorDictModule(nn.Linear(3, 1), in_keys=[("next", "latent")],
            ...                           out_keys=[("next", "reward")])
            >>> pm = PlanningModel.from_torchrl(WorldModel(encoder, dynamics, reward), env=GymEnv("Pendulum-v1"))
            >>> pm.action_high.tolist(), pm(torch.zeros(1, 3), torch.zeros(1, 1), torch.zeros(3), torch.rand(64, 10, 1)).cost.shape
            ([2.0], torch.Size([64, 10]))
        """
        from torchrl_recon.planners.torchrl_models import planning_model_from_torchrl

        return planning_model_from_torchrl(
            world_model,
            env=env,
            cost_fn=cost_fn,
            uncertainty=uncertainty,
            termination_fn=termination_fn,
            action_low=action_low,
            action_high=action_high,
            **adapter_kwargs,
        )

    @property
    def compile_mode(self) -> str | None:
        """The ``compile`` mode of the pass, or None (eager)."""
        return self.executor.compile_mode

    @property
    def threads(self) -> int:
        """The threads the pass's row blocks run on (on the CPU, without autograd)."""
        return self.executor.threads

    def later(self, fn: Callable[[], torch.Tensor]) -> Callable[[], torch.Tensor]:
        """``fn``'s result as a call that returns it: started now on a block thread when the pass
        runs its row blocks on threads (the serial work before the call overlaps it), else run
        when called. Either way the same value, drawn in the same order.

        Examples:
            >>> model = PlanningModel(LSTMWorldModel(3, 1, window=2), lambda o, a, n: n.sum(-1))
            >>> model.later(lambda: torch.ones(2))()
            tensor([1., 1.])
        """
        return self.executor.later(self, fn)

    @property
    def context_length(self) -> int:
        """Real (s, a) pairs the planner needs before the current state."""
        u_window = 0 if self.uncertainty is None else self.uncertainty.window - 1
        return max(self.world_model.window, u_window)

    def check_fitted(self) -> None:
        """Refuse a world model or estimator whose normalisation was never fitted (one
        ``ValueError`` line saying how to fit it); :meth:`warmup` and :meth:`forward` call it.

        The values are read once; after they passed, a call only sees that the ``fitted``
        buffers are the same tensors, not written since (a ``load_state_dict`` or a new fit
        re-checks), so later plans do no host sync (:class:`~torchrl_recon.modules.fitted.FittedCheck`).
        """
        self._world_model_fitted(self.world_model)
        if self.uncertainty is not None:
            self._uncertainty_fitted(self.uncertainty)
        if self.reward_model is not None:
            self._learned_fitted(self.reward_model)

    @property
    def reward_model(self) -> RewardModel | None:
        """The :class:`~torchrl_recon.modules.RewardModel` behind a learned cost or termination
        (:class:`~torchrl_recon.modules.LearnedCost`, :class:`~torchrl_recon.modules.LearnedTermination`),
        else None. The fits find it here to train it with the world model."""
        for fn in (self.cost_fn, self.termination_fn):
            found = getattr(fn, "reward_model", None)
            if isinstance(found, RewardModel):
                return found
        return None

    @torch.no_grad()
    def warmup(
        self, context_obs: torch.Tensor, context_action: torch.Tensor
    ) -> tuple[torch.Tensor, ...] | None:
        """The world model's recurrent state after the real context (None for a stateless model).

        Pass it as ``state=`` to every call on the same context instead of recomputing it.
        """
        self.check_fitted()
        warmup = getattr(self.world_model, "warmup", None)
        if warmup is None:
            return None
        return warmup(self._per_member(context_obs), self._per_member(context_action))

    @property
    def num_members(self) -> int | None:
        """R when the world model holds R members (``num_members``), else None."""
        return getattr(self.world_model, "num_members", None)

    def _per_member(self, x: torch.Tensor) -> torch.Tensor:
        """``x`` once per member, ``[R, ...]`` (``x`` itself for one model)."""
        r = self.num_members
        return x if r is None else x.expand(r, *x.shape)

    def check_context(
        self, context_obs: torch.Tensor, context_action: torch.Tensor, observation: torch.Tensor
    ) -> None:
        """Validate a real context: dims, length >= :attr:`context_length`, device, dtype,
        finite values."""
        check_features("observation", observation, self.obs_dim)
        check_features("context_obs", context_obs, self.obs_dim, min_ndim=2)
        check_features("context_action", context_action, self.action_dim, min_ndim=2)
        check_window("context_obs", context_obs, self.context_length)
        if (
            context_obs.shape[:-1] != context_action.shape[:-1]
            or context_obs.shape[:-2] != observation.shape[:-1]
        ):
            raise ValueError(
                f"context_obs {tuple(context_obs.shape)}, context_action {tuple(context_action.shape)} and "
                f"observation {tuple(observation.shape)} disagree on batch dims."
            )
        for name, x in (
            ("observation", observation),
            ("context_obs", context_obs),
            ("context_action", context_action),
        ):
            self.check_placed(name, x)

    def check_placed(self, name: str, x: torch.Tensor) -> None:
        """Refuse ``x`` (called ``name``) off the planning model's device or dtype, or holding
        NaN or inf.

        Examples:
            >>> from torchrl_recon.modules import LSTMWorldModel
            >>> model = PlanningModel(LSTMWorldModel(2, 1), lambda s, a, s2: s2[..., 0])
            >>> model.check_placed("init", torch.zeros(3, 1, dtype=torch.float64))
            Traceback (most recent call last):
            ...
            ValueError: init has dtype torch.float64 but the planning model computes in torch.float32; pass init.to(torch.float32).
        """
        device, dtype = self.action_low.device, self.action_low.dtype
        if x.device != device:
            raise ValueError(
                f"{name} is on {x.device} but the planning model is on {device}; move the "
                f"inputs with .to({str(device)!r}) (or the planner with .to({str(x.device)!r}))."
            )
        if x.dtype != dtype:
            raise ValueError(
                f"{name} has dtype {x.dtype} but the planning model computes in {dtype}; "
                f"pass {name}.to({dtype})."
            )
        check_finite(name, x.detach())

    def check_actions(self, actions: torch.Tensor, observation: torch.Tensor) -> None:
        """Validate candidates ``[*B, K, H, M]`` for ``observation`` ``[*B, N]``: shape, device,
        dtype, finite values."""
        check_features("actions", actions, self.action_dim, min_ndim=3)
        batch = tuple(observation.shape[:-1])
        if tuple(actions.shape[:-3]) != batch:
            raise ValueError(
                f"actions has shape {tuple(actions.shape)}; expected [*B, K, H, {self.action_dim}] "
                f"with observation's batch dims {batch}."
            )
        self.check_placed("actions", actions)

    def forward(
        self,
        context_obs: torch.Tensor,
        context_action: torch.Tensor,
        observation: torch.Tensor,
        actions: torch.Tensor,
        *,
        state: tuple[torch.Tensor, torch.Tensor] | None = None,
        block_rows: int | str | None = None,
    ) -> Prediction:
        """Predict states, cost and u for candidates ``actions`` ``[*B, K, H, M]``.

        Keyword Args:
            state: the world model's state from :meth:`warmup` on this context.
            block_rows: evaluate at most about this many rows (batch elements × candidates)
                at a time (``"auto"``: ``BLOCK_ROWS`` on the CPU, one pass elsewhere; see
                ``resolve_block_rows``): the candidates are split along K into blocks of
                ``max(1, block_rows // B)``, each block one batched pass over all batch
                elements, so a block's rollout state and u windows stay in cache. Each row's
                prediction depends on that row alone, so the result is that of one pass up
                to float rounding. An estimator that draws random numbers per call (MC
                dropout's masks) still scores all rows in one call, so every candidate is
                scored by the same masks. None (default): one pass. Traced into a planner's
                compiled graph (``compile`` with a sampling planner), ``"auto"`` is one pass
                (blocks would be unrolled into the graph), and a number of rows splits the
                candidates by the batch size: one graph per batch size.

        Raises:
            ValueError: unfitted networks, or inputs of the wrong shape, device or dtype, or
                holding NaN or inf (:meth:`check_context`, :meth:`check_actions`; left out
                while compiling and within a planner's ``plan``, which checked them).
        """
        self.check_fitted()
        traced = in_graph()
        if not traced and not _INPUTS_CHECKED.get():
            self.check_context(context_obs, context_action, observation)
            self.check_actions(actions, observation)
        # Traced into a plan's graph, "auto" is one pass: blocks would be unrolled into the
        # graph (its compile time grows with their number) and pin the batch size.
        auto_one_pass = traced and block_rows == "auto"
        block_rows = None if auto_one_pass else resolve_block_rows(block_rows, actions.device)
        context = (context_obs, context_action, observation)
        return self.executor.predict(self, context, actions, state, block_rows)

    def _in_blocks(
        self,
        predict: Callable[..., Prediction],
        context: tuple[torch.Tensor, torch.Tensor, torch.Tensor],
        actions: torch.Tensor,
        state: tuple[torch.Tensor, torch.Tensor] | None,
        block_rows: int | None,
    ) -> Prediction:
        """:meth:`forward`'s candidates ``actions`` in blocks of about ``block_rows`` rows, one
        after another, each one call of ``predict`` (:meth:`_predict`, or the executor's
        compiled copy of it); all in one call when they fit (or ``block_rows`` is None).
        ``context``: the context observations and actions and the current observation."""
        batch_rows = math.prod(context[2].shape[:-1])  # symbolic in a graph of dynamic batch
        k = actions.shape[-3]
        if block_rows is None or batch_rows * k <= block_rows:
            return predict(self, *context, actions, state)
        chunk = max(1, block_rows // batch_rows)
        with_u = self._row_independent_u
        blocks = [
            predict(self, *context, block, state, with_u=with_u)
            for block in actions.split(chunk, dim=-3)
        ]
        return self._scored(Prediction.concat(blocks), context, actions, with_u)

    def _scored(
        self,
        prediction: Prediction,
        context: tuple[torch.Tensor, torch.Tensor, torch.Tensor],
        actions: torch.Tensor,
        with_u: bool,
    ) -> Prediction:
        """``prediction`` of blocks, with u: the blocks' own (``with_u``), else every row's
        scored here in one call (an estimator that draws per call scores all rows with the
        same draws)."""
        if self.uncertainty is not None and not with_u:
            context_obs, context_action, observation = context
            entering = _entering(observation, prediction.states)
            u = self._score_uncertainty(context_obs, context_action, entering, actions)
            prediction.uncertainty = self._until_end(u, entering, actions, prediction.states)
        return prediction

    def _empty_prediction(self, actions: torch.Tensor, with_u: bool) -> Prediction:
        """An uninitialised prediction for ``actions`` ``[*B, K, H, M]`` (u only if scored)."""
        *rows, horizon, _ = actions.shape
        scored = with_u and self.uncertainty is not None
        return Prediction(
            actions.new_empty(*rows, horizon, self.obs_dim),
            actions.new_empty(*rows, horizon),
            actions.new_empty(*rows, horizon) if scored else None,
        )

    @property
    def _row_independent_u(self) -> bool:
        """Whether the estimator's u of a window depends on that window alone (no per-call draws)."""
        return bool(getattr(self.uncertainty, "window_local", False))

    def _predict(
        self,
        context_obs: torch.Tensor,
        context_action: torch.Tensor,
        observation: torch.Tensor,
        actions: torch.Tensor,
        state: tuple[torch.Tensor, torch.Tensor] | None,
        *,
        with_u: bool = True,
    ) -> Prediction:
        """One batched pass of :meth:`forward` (u left out unless ``with_u``)."""
        kwargs = {} if state is None else {"state": state}
        # Members (if any) each imagine every candidate: a leading [R] on every input.
        obs, act = self._per_member(observation), self._per_member(actions)
        context = (self._per_member(context_obs), self._per_member(context_action))
        states = self.world_model.imagine(*context, obs, act, **kwargs)
        entering = _entering(obs, states)  # s_k for k = 0..H-1
        cost = self._until_end(self.cost_fn(entering, act, states), entering, act, states)
        if self.num_members is not None:  # a candidate's cost and states: the members' mean
            cost, states = cost.mean(0), states.mean(0)
            entering = _entering(observation, states)
        uncertainty = None
        if self.uncertainty is not None and with_u:
            u = self._score_uncertainty(context_obs, context_action, entering, actions)
            uncertainty = self._until_end(u, entering, actions, states)
        return Prediction(states=states, cost=cost, uncertainty=uncertainty)

    def _until_end(
        self, x: torch.Tensor, entering: torch.Tensor, actions: torch.Tensor, states: torch.Tensor
    ) -> torch.Tensor:
        """``x`` ``[*B, K, H]`` zeroed after each candidate's first predicted termination (the
        terminating step kept); ``x`` itself without a termination function."""
        if self.termination_fn is None:
            return x
        ended = self.termination_fn(entering, actions, states).cumsum(-1) > 0  # [*B, K, H]
        ended_before = torch.cat([torch.zeros_like(ended[..., :1]), ended[..., :-1]], -1)
        return x.masked_fill(ended_before, 0.0)

    def _score_uncertainty(
        self,
        context_obs: torch.Tensor,
        context_action: torch.Tensor,
        entering: torch.Tensor,
        actions: torch.Tensor,
    ) -> torch.Tensor:
        """u of the H windows ending at each imagined step (the first ones reach into the real context)."""
        est = self.uncertainty
        past = est.window - 1
        *batch, k, horizon, _ = actions.shape
        rows = math.prod(batch) * k  # symbolic in a graph of dynamic batch
        x = entering.new_empty(rows, past + horizon, self.obs_dim + self.action_dim)
        x = x.view(*batch, k, past + horizon, -1)
        if past:
            x[..., :past, : self.obs_dim] = context_obs[..., None, -past:, :]
            x[..., :past, self.obs_dim :] = context_action[..., None, -past:, :]
        x[..., past:, : self.obs_dim] = entering
        x[..., past:, self.obs_dim :] = actions
        x = x.view(rows, past + horizon, -1)
        if torch.is_grad_enabled() and self._row_independent_u:
            # With autograd the estimators score all windows at once; rows in blocks of about
            # GRAD_BLOCK_WINDOWS windows keep each block's forward and backward in cache.
            step = max(1, GRAD_BLOCK_WINDOWS // horizon)
            if rows > step:
                u = torch.cat([checked_scores(est, block) for block in x.split(step)])
                return u.view(*batch, k, horizon)
        return checked_scores(est, x).view(*batch, k, horizon)
