"""MPC as a TensorDict policy: plan, execute open loop, re-plan when uncertainty says so."""

from __future__ import annotations

import warnings
from typing import Literal

import torch
from tensordict import TensorDictBase
from tensordict.nn import TensorDictModuleBase
from torchrl.data import Bounded, Composite, Unbounded
from torchrl.envs import EnvBase

from torchrl_recon.modules.checks import (
    check_features,
    check_finite,
    check_flag,
    check_int,
    check_real,
    check_type,
    is_key,
)
from torchrl_recon.modules.fitted import ESTIMATOR, WORLD_MODEL, unfitted_before_data
from torchrl_recon.planners.base import InfeasiblePlanWarning, PlannerBase
from torchrl_recon.policies.env_checks import (
    IS_INIT,
    MISSING_INIT_TRACKER,
    PlannerStatePrimer,
    check_policy_env,
)

ReplanMode = Literal["every_step", "every_n", "uncertainty"]
WarmupMode = Literal["random", "zeros", "plan"]
WARMUP_MODES = ("random", "zeros", "plan")

# State keys carried step to step (primed by make_tensordict_primer, reset where is_init is set).
OBS_HISTORY, ACTION_HISTORY = "mpc_obs_history", "mpc_action_history"
PLAN, PLAN_STATES, PLAN_COST, PLAN_U, PLAN_STEP, SEEN = (
    "mpc_plan",
    "mpc_plan_states",
    "mpc_plan_cost",
    "mpc_plan_u",
    "mpc_plan_step",
    "mpc_steps_seen",
)
STATE_KEYS = (OBS_HISTORY, ACTION_HISTORY, PLAN, PLAN_STATES, PLAN_COST, PLAN_U, PLAN_STEP, SEEN)
# TorchRL's partial-step mask: rollout(break_when_all_done=True) sets it False for the envs
# of a batch that are done and wait for the others.
PARTIAL_STEP = "_step"
# Per-step outputs, for plotting predicted vs real.
REPLANNED, FEASIBLE = "mpc_replanned", "mpc_feasible"
PRED_NEXT, PRED_U, PRED_COST = (
    "mpc_predicted_next_observation",
    "mpc_predicted_uncertainty",
    "mpc_predicted_cost",
)


class MPCPolicy(TensorDictModuleBase):
    """Model-predictive control with a :class:`~torchrl_recon.planners.PlannerBase`, usable by
    ``env.rollout`` and every TorchRL collector.

    Its state (the last ``C`` real (s, a) pairs and the remaining plan with its predictions)
    travels in the TensorDict under ``mpc_*`` keys: add :meth:`make_tensordict_primer` to the
    env (as with TorchRL's ``LSTMModule``) and keep an ``InitTracker``. Where ``is_init`` is
    set the state is cleared; without ``is_init`` the policy raises (it could not tell a new
    episode from an old one).

    The planner's action bounds must be the env's: the primer refuses, when appended, an env
    whose action spec has another range, and :meth:`check_env` checks a finished env (bounds,
    ``InitTracker``, primer). Build the planning model with
    :meth:`~torchrl_recon.planners.PlanningModel.from_env` to take the bounds from the env. By
    default the first ``warmup_steps`` (default ``C``) steps of an episode take uniform random
    actions to fill the context (the paper's "10 random actions after reset"): on a task those
    steps can end or spoil (a balanced pole, episodes shorter than the context) pass
    ``warmup="plan"``, which plans from the first step (TorchRL's ``Collector`` at its
    defaults reads the policy's :attr:`spec` and does not call it before the models are fitted).

    Re-planning (``replan``):

    * ``"every_step"``: classic MPC, re-plan at every step, execute the first action;
    * ``"every_n"``: re-plan every ``replan_every`` steps;
    * ``"uncertainty"``: the paper's mode. Execute the plan open loop while the predicted
      u of the next action (``threshold_on="step"``) or the predicted Σu since the plan was
      made (``threshold_on="cumulative"``) is at most ``threshold``; re-plan when it crosses
      it or the plan runs out. A fresh plan always executes at least one action.

    With ``error_threshold`` (not in the paper), any mode also re-plans when the observed state
    has left the plan's prediction of it: when the root mean square over the state's dimensions
    of (observed − predicted), in units of the world model's ``obs_norm`` standard deviations,
    exceeds it. Predicted u only sees the predicted states, so a plan kept where u is low can
    otherwise run open loop to its end while the real states drift away.

    In a batch of envs every row keeps its own state and re-plan trigger; the rows whose
    trigger fired are planned together in one planner call. Rows that TorchRL's partial-step
    mask (``"_step"``, set by ``rollout(break_when_all_done=True)`` for envs that are done
    and wait for the others) leaves out are not planned.

    Per step it writes ``action``, ``mpc_replanned``, ``mpc_feasible`` (False when no
    candidate met the planner's constraints; the planner's warning is not repeated) and the predicted next
    observation, u and cost of the action taken, so predicted and real trajectories can be
    compared.

    It computes on the planning model's device (move the planner with ``.to(device)``) and
    writes its outputs on the device of the observation it was given. With a collector, keep
    the env on the CPU and pass ``env_device="cpu"``, ``policy_device=<the model's device>`` and
    ``storing_device="cpu"``; the primer's specs are on the model's device until it is appended
    to an env, then on the env's.

    Args:
        planner: the planner (its model's ``obs_dim``/``action_dim`` and horizon are used).

    Keyword Args:
        replan: ``"every_step"``, ``"every_n"`` or ``"uncertainty"``.
        replan_every: n for ``"every_n"``.
        threshold: u threshold for ``"uncertainty"``.
        threshold_on: ``"step"`` or ``"cumulative"``.
        error_threshold: also re-plan when the observed state is further than this from the
            plan's prediction (RMS in normalised units); ``None`` (default) never.
        warm_start: pass the unexecuted rest of the previous plan to the planner as ``init``.
        warmup_steps: steps after each reset before the first plan (at least the context
            length ``C``; 0 with ``warmup="plan"``).
        warmup: what those steps do: ``"random"`` (uniform random actions, the paper's),
            ``"zeros"`` (the zero action, clamped into the bounds: a task that must not be
            shaken at its start, e.g. a balanced pole), or ``"plan"`` (no warm-up: plan from
            the first step, the context before the episode's start filled with its first
            observation and the zero action, as if the system had been at rest).
        obs_key, action_key: TensorDict keys.

    Examples:
        >>> from torchrl_recon.envs import make_env
        >>> from torchrl_recon.envs.drone import drone_cost
        >>> from torchrl_recon.modules import LSTMWorldModel
        >>> from torchrl_recon.planners import CEMPlanner, Objective, PlanningModel
        >>> world_model = LSTMWorldModel(12, 4, window=3)
        >>> world_model.fit_normalization(torch.randn(50, 12), torch.rand(50, 4), torch.randn(50, 12))
        >>> planner = CEMPlanner(PlanningModel(world_model, drone_cost), Objective(),
        ...                      horizon=10, num_candidates=32, num_elites=4, iterations=2)
        >>> policy = MPCPolicy(planner, replan="every_n", replan_every=5)
        >>> env = make_env("drone", seed=0).append_transform(policy.make_tensordict_primer())
        >>> td = env.rollout(8, policy)
        >>> td["mpc_replanned"].squeeze(-1).tolist()
        [False, False, False, True, False, False, False, False]
    """

    def __init__(
        self,
        planner: PlannerBase,
        *,
        replan: ReplanMode = "every_step",
        replan_every: int = 1,
        threshold: float | None = None,
        threshold_on: Literal["step", "cumulative"] = "step",
        error_threshold: float | None = None,
        warm_start: bool = True,
        warmup_steps: int | None = None,
        warmup: WarmupMode = "random",
        obs_key: str = "observation",
        action_key: str = "action",
    ) -> None:
        super().__init__()
        _check_wiring(planner, warm_start, obs_key, action_key)
        _check_replan(planner, replan, replan_every, threshold, threshold_on, error_threshold)
        # replan settings
        self.error_threshold = error_threshold
        self.planner, self.replan, self.replan_every = planner, replan, replan_every
        self.threshold, self.threshold_on, self.warm_start = threshold, threshold_on, warm_start
        # the planner's shapes
        model = planner.model
        self.obs_dim, self.action_dim = model.obs_dim, model.action_dim
        self.horizon, self.context = planner.horizon, model.context_length
        # warm-up
        self.warmup_steps = _warmup_steps(warmup, warmup_steps, self.context)
        self.warmup = warmup
        # TensorDict wiring
        self.obs_key, self.action_key = obs_key, action_key
        self.in_keys = [obs_key, IS_INIT, *STATE_KEYS]
        self.out_keys = [
            action_key,
            REPLANNED,
            FEASIBLE,
            PRED_NEXT,
            PRED_U,
            PRED_COST,
            *[("next", k) for k in STATE_KEYS],
        ]

    @property
    def device(self) -> torch.device:
        """The planning model's device, where the policy computes."""
        return self.planner.model.action_low.device

    def state_spec(self) -> Composite:
        """Specs of the carried state (unbatched), on the planning model's device and dtype."""
        c, h, n, m = self.context, self.horizon, self.obs_dim, self.action_dim
        like = self.planner.model.action_low

        def spec(*shape: int, dtype: torch.dtype = like.dtype) -> Unbounded:
            return Unbounded(shape, dtype=dtype, device=like.device)

        return Composite(
            {
                OBS_HISTORY: spec(c, n),
                ACTION_HISTORY: spec(c, m),
                PLAN: spec(h, m),
                PLAN_STATES: spec(h, n),
                PLAN_COST: spec(h),
                PLAN_U: spec(h),
                PLAN_STEP: spec(1, dtype=torch.int64),
                SEEN: spec(1, dtype=torch.int64),
            },
            device=like.device,
        )

    @property
    def spec(self) -> Composite | None:
        """With ``warmup="plan"``: the specs of everything the policy writes (unbatched), on its
        device. TorchRL's ``Collector`` reads them at construction instead of calling the policy
        on a reset tensordict, a call that would plan with models not fitted yet.

        With ``warmup="random"``: None, so the Collector calls the policy once (a random step,
        no plan) to learn its outputs, as for any policy without a spec. TorchRL 0.14's
        Collector reads a spec only correctly when the env and the policy share a device: with
        ``env_device="cpu", policy_device="cuda"`` and a spec, its first batch stops in
        ``TensorDict.update`` (the keys it takes back are a set). So with ``warmup="plan"`` and
        an env on another device, cast the env's data to the policy's device
        (``DeviceCastTransform``, as the experiments do) or build the Collector with
        ``use_buffers=False``.

        Examples:
            >>> from torchrl_recon.modules import LSTMWorldModel
            >>> from torchrl_recon.planners import CEMPlanner, Objective, PlanningModel
            >>> model = PlanningModel(LSTMWorldModel(3, 1, window=2), lambda s, a, s1: s1[..., 0])
            >>> planner = CEMPlanner(model, Objective(), horizon=4, num_candidates=8, num_elites=2)
            >>> MPCPolicy(planner).spec is None
            True
            >>> policy = MPCPolicy(planner, warmup="plan")
            >>> policy.spec["action"].shape, sorted(policy.out_keys, key=str) == sorted(policy.spec.keys(True, True), key=str)
            (torch.Size([1]), True)
        """
        if self.warmup != "plan":
            return None
        model = self.planner.model
        like = model.action_low
        n = self.obs_dim

        def spec(*shape: int, dtype: torch.dtype = like.dtype) -> Unbounded:
            return Unbounded(shape, dtype=dtype, device=like.device)

        state = self.state_spec()
        return Composite(
            {
                self.action_key: Bounded(
                    model.action_low, model.action_high, (self.action_dim,), device=like.device
                ),
                REPLANNED: spec(1, dtype=torch.bool),
                FEASIBLE: spec(1, dtype=torch.bool),
                PRED_NEXT: spec(n),
                PRED_U: spec(1),
                PRED_COST: spec(1),
                "next": Composite({k: state[k] for k in STATE_KEYS}, device=like.device),
            },
            device=like.device,
        )

    def make_tensordict_primer(self) -> PlannerStatePrimer:
        """The transform that adds and resets this policy's state in the env (append it to the env).

        Appended to an env, it checks that the env's action spec has the planner's bounds
        (``ValueError`` naming both ranges otherwise).
        """
        model = self.planner.model
        return PlannerStatePrimer(
            self.state_spec(),
            action_low=model.action_low,
            action_high=model.action_high,
            action_key=self.action_key,
            owner=f"{type(self).__name__}'s planner",
            default_value=0,
            expand_specs=True,
        )

    def check_env(self, env: EnvBase) -> None:
        """Check that ``env`` fits this policy: the planner's action bounds are the env's action
        spec, the env has an ``InitTracker`` and this policy's primer.

        Raises:
            ValueError: the bounds differ (both ranges are named).
            KeyError: the ``InitTracker`` or the primer is missing (the message says what to add).

        Examples:
            >>> from torchrl_recon.envs import make_env
            >>> from torchrl_recon.envs.drone import drone_cost
            >>> from torchrl_recon.modules import LSTMWorldModel
            >>> from torchrl_recon.planners import Objective, PlanningModel, RandomShootingPlanner
            >>> planner = RandomShootingPlanner(PlanningModel(LSTMWorldModel(12, 4), drone_cost),
            ...                                 Objective(), horizon=5, num_candidates=8)
            >>> policy = MPCPolicy(planner)
            >>> policy.check_env(make_env("drone", seed=0).append_transform(policy.make_tensordict_primer()))
        """
        model = self.planner.model
        check_policy_env(
            env,
            model.action_low,
            model.action_high,
            action_key=self.action_key,
            state_key=PLAN,
            owner=f"{type(self).__name__}'s planner",
        )

    def _check_fitted_before_data(self) -> None:
        """Refuse unfitted models as the planning model does, but say what works for a policy
        that plans at an episode's first step, which TorchRL's ``Collector`` may call before any
        data (:func:`~torchrl_recon.modules.fitted.unfitted_before_data`)."""
        model = self.planner.model
        try:
            model.check_fitted()
        except ValueError:
            modules = [(model.world_model, WORLD_MODEL), (model.uncertainty, ESTIMATOR)]
            err = unfitted_before_data(modules, type(self).__name__)
            if err is None:
                raise
            raise err from None

    def _needs_plan(self, step: torch.Tensor, plan_u: torch.Tensor) -> torch.Tensor:
        exhausted = step >= self.horizon
        if self.replan == "every_step":
            return torch.ones_like(exhausted)
        if self.replan == "every_n":
            return exhausted | (step >= self.replan_every)
        idx = step.clamp(max=self.horizon - 1)
        if self.threshold_on == "step":
            upcoming = plan_u.gather(-1, idx[:, None]).squeeze(-1)
        else:
            upcoming = (plan_u.cumsum(-1)).gather(-1, idx[:, None]).squeeze(-1)
        return exhausted | (upcoming > self.threshold)

    def _drifted(
        self, obs: torch.Tensor, plan_states: torch.Tensor, step: torch.Tensor
    ) -> torch.Tensor:
        """Rows whose observation is further than ``error_threshold`` from the plan's prediction
        of it (``plan_states[step - 1]``, the state predicted after the last planned action)."""
        if self.error_threshold is None:
            return torch.zeros_like(step, dtype=torch.bool)
        on_plan = (step >= 1) & (step <= self.horizon)
        predicted = _at_step(plan_states, (step - 1).clamp(0, self.horizon - 1))
        norm = getattr(self.planner.model.world_model, "obs_norm", None)
        scale = norm.scale if norm is not None else obs.new_ones(self.obs_dim)
        rms = ((obs - predicted) / scale).pow(2).mean(-1).sqrt()
        return on_plan & (rms > self.error_threshold)

    def forward(self, tensordict: TensorDictBase) -> TensorDictBase:
        """One step of every row: read the observation and the carried state, re-plan the rows
        whose trigger fired, take each row's next action from its kept plan (or the warm-up's),
        and write the action, the predictions and the next state into ``tensordict``."""
        flat, given = self._read_observation(tensordict)
        obs = given.to(self.device)
        state, step, seen = self._read_state(flat, obs.device)
        ready = seen >= self.warmup_steps
        replanned = self._rows_to_replan(flat, obs, state, step, ready)
        feasible = self._replan(state, obs, step, seen, replanned)
        action, predicted = self._next_action(state, step, ready)
        outputs = {
            self.action_key: action,
            REPLANNED: replanned[:, None],
            FEASIBLE: feasible[:, None],
            **predicted,
        }
        self._advance(state, obs, action, step, seen, ready)
        self._write(tensordict, outputs, state, given.device)
        return tensordict

    def _read_observation(self, tensordict: TensorDictBase) -> tuple[TensorDictBase, torch.Tensor]:
        """The tensordict flattened to ``[R]`` rows and its observation ``[R, N]`` (checked, on
        the device it was given on); refuses a tensordict without the policy's state."""
        check_type("tensordict", tensordict, TensorDictBase, "a TensorDict (an env's step)")
        if PLAN not in tensordict.keys():
            raise KeyError(
                f"MPCPolicy state {PLAN!r} is missing from the tensordict; append "
                "policy.make_tensordict_primer() to the env (and an InitTracker)."
            )
        flat = tensordict.reshape(-1)
        given = flat.get(self.obs_key, None)
        if given is None:
            raise KeyError(
                f"MPCPolicy reads the observation {self.obs_key!r}, which the tensordict lacks "
                f"(it has {sorted(map(str, tensordict.keys(True, True)))}); pass obs_key=."
            )
        check_features(f"{self.obs_key!r} given to MPCPolicy", given, self.obs_dim)
        check_finite(f"{self.obs_key!r} given to MPCPolicy", given)
        return flat, given

    def _read_state(
        self, flat: TensorDictBase, device: torch.device
    ) -> tuple[TensorDictBase, torch.Tensor, torch.Tensor]:
        """A copy of the carried state on ``device``, cleared where ``is_init`` is set, with
        views of its plan step and steps seen, ``[R]`` each (updating them updates the state)."""
        state = flat.select(*STATE_KEYS).to(device).clone()
        step, seen = state[PLAN_STEP].squeeze(-1), state[SEEN].squeeze(-1)
        is_init = flat.get(IS_INIT, None)
        if is_init is None:
            raise KeyError(MISSING_INIT_TRACKER)
        is_init = is_init.to(device).reshape(flat.shape[0])
        step.masked_fill_(is_init, self.horizon)  # a plan that ran out: re-plan when ready
        seen.masked_fill_(is_init, 0)
        return state, step, seen

    def _rows_to_replan(
        self,
        flat: TensorDictBase,
        obs: torch.Tensor,
        state: TensorDictBase,
        step: torch.Tensor,
        ready: torch.Tensor,
    ) -> torch.Tensor:
        """Rows past their warm-up whose trigger fired (the re-plan rule or the drift from the
        plan), except those the partial-step mask leaves out, ``[R]`` bool."""
        drifted = self._drifted(obs, state[PLAN_STATES], step)
        replanned = ready & (self._needs_plan(step, state[PLAN_U]) | drifted)
        stepped = flat.get(PARTIAL_STEP, None)  # rows an env batch will not step: never planned
        if stepped is not None:
            replanned &= stepped.to(obs.device).reshape(flat.shape[0])
        return replanned

    def _replan(
        self,
        state: TensorDictBase,
        obs: torch.Tensor,
        step: torch.Tensor,
        seen: torch.Tensor,
        replanned: torch.Tensor,
    ) -> torch.Tensor:
        """Plan the ``replanned`` rows in one planner call and keep their plans in ``state``
        (their plan step back to 0); returns which rows' plans are feasible, ``[R]`` bool."""
        feasible = torch.ones(len(replanned), dtype=torch.bool, device=obs.device)
        if not replanned.any():
            return feasible
        if self.warmup == "plan":
            self._check_fitted_before_data()
        idx = replanned.nonzero().squeeze(-1)
        with warnings.catch_warnings():  # recorded per step in mpc_feasible instead
            warnings.simplefilter("ignore", InfeasiblePlanWarning)
            context_obs, context_action = self._context(state, obs, seen)
            result = self.planner.plan(
                context_obs[idx],
                context_action[idx],
                obs[idx],
                init=self._warm_start(state[PLAN][idx], step[idx]),
            )
        self._check_plan(result.actions, len(idx))
        state[PLAN][idx], state[PLAN_STATES][idx], state[PLAN_COST][idx] = (
            result.actions,
            result.states,
            result.cost,
        )
        if result.uncertainty is not None:
            state[PLAN_U][idx] = result.uncertainty
        step[idx] = 0
        feasible[idx] = result.feasible
        return feasible

    def _next_action(
        self, state: TensorDictBase, step: torch.Tensor, ready: torch.Tensor
    ) -> tuple[torch.Tensor, dict[str, torch.Tensor]]:
        """The action of each row, ``[R, M]``: its kept plan's current step once past the
        warm-up, the warm-up action before; with the plan's predictions for it (NaN in the
        warm-up)."""
        warmup_action = self._warmup_action(len(step))
        at = step.clamp(max=self.horizon - 1)
        planned = ready[:, None]
        action = torch.where(planned, _at_step(state[PLAN], at), warmup_action)
        predicted = {
            PRED_NEXT: torch.where(planned, _at_step(state[PLAN_STATES], at), float("nan")),
            PRED_U: torch.where(planned, _at_step(state[PLAN_U], at)[:, None], float("nan")),
            PRED_COST: torch.where(planned, _at_step(state[PLAN_COST], at)[:, None], float("nan")),
        }
        return action, predicted

    def _warmup_action(self, rows: int) -> torch.Tensor:
        """The warm-up's action for ``rows`` rows, ``[R, M]``: uniform random in the bounds with
        ``warmup="random"``, the rest action otherwise."""
        low, high = self.planner.model.action_low, self.planner.model.action_high
        if self.warmup == "random":
            return low + (high - low) * torch.rand(
                rows, self.action_dim, dtype=low.dtype, device=low.device
            )
        return self._rest_action().expand(rows, -1)

    def _advance(
        self,
        state: TensorDictBase,
        obs: torch.Tensor,
        action: torch.Tensor,
        step: torch.Tensor,
        seen: torch.Tensor,
        ready: torch.Tensor,
    ) -> None:
        """The state after this step: one more step of the plan (past the warm-up), one more
        step seen, and the context with its oldest pair dropped and (s_t, a_t) appended."""
        step += ready.long()
        seen += 1
        state[OBS_HISTORY] = torch.cat([state[OBS_HISTORY][:, 1:], obs[:, None]], 1)
        state[ACTION_HISTORY] = torch.cat([state[ACTION_HISTORY][:, 1:], action[:, None]], 1)

    def _write(
        self,
        tensordict: TensorDictBase,
        outputs: dict[str, torch.Tensor],
        state: TensorDictBase,
        device: torch.device,
    ) -> None:
        """Write the step's outputs and the next state (under ``"next"``) into ``tensordict``,
        reshaped from ``[R]`` rows to its batch shape, on ``device``."""
        batch = tensordict.batch_size
        for key, value in outputs.items():
            tensordict.set(key, value.reshape(*batch, *value.shape[1:]).to(device))
        for key in STATE_KEYS:
            value = state[key].reshape(*batch, *state[key].shape[1:])
            tensordict.set(("next", key), value.to(device))

    def _check_plan(self, actions: torch.Tensor, rows: int) -> None:
        """Refuse a plan the env must not be given (a plug-in planner's bug): not ``[rows, H,
        M]``, NaN or inf, or outside the action bounds (by more than float rounding)."""
        name = type(self.planner).__name__
        expected = (rows, self.horizon, self.action_dim)
        if tuple(actions.shape) != expected:
            raise ValueError(
                f"{name}.plan returned actions of shape {tuple(actions.shape)}; expected {expected}."
            )
        check_finite(f"the actions {name}.plan returned", actions)
        low, high = self.planner.model.action_low, self.planner.model.action_high
        slack = 1e-5 * (high - low)
        outside = (actions < low - slack) | (actions > high + slack)
        if outside.any():
            bad = outside.nonzero()[0].tolist()
            raise ValueError(
                f"{name}.plan returned an action outside the bounds [{low.tolist()}, "
                f"{high.tolist()}] (first at index {bad}: {actions[tuple(bad)].item():.6g}); a "
                "planner keeps its candidates within the planning model's action bounds."
            )

    def _rest_action(self) -> torch.Tensor:
        """The zero action, clamped into the planner's bounds, ``[M]``."""
        low, high = self.planner.model.action_low, self.planner.model.action_high
        return torch.zeros_like(low).clamp(low, high)

    def _context(
        self, state: TensorDictBase, obs: torch.Tensor, seen: torch.Tensor
    ) -> tuple[torch.Tensor, torch.Tensor]:
        """The real context to plan from, ``[R, C, N]``, ``[R, C, M]``; with ``warmup="plan"``
        the slots before the episode's start hold its first observation and the rest action."""
        obs_h, act_h = state[OBS_HISTORY], state[ACTION_HISTORY]
        if self.warmup != "plan":
            return obs_h, act_h
        c = obs_h.shape[1]
        missing = c - seen.clamp(max=c)  # slots before the episode's start, [R]
        before = torch.arange(c, device=obs.device) < missing[:, None]  # [R, C]
        first_index = missing.clamp(max=c - 1)[:, None, None].expand(-1, 1, obs_h.shape[-1])
        first = torch.where((seen > 0)[:, None], obs_h.gather(1, first_index).squeeze(1), obs)
        obs_h = torch.where(before[..., None], first[:, None], obs_h)
        act_h = torch.where(before[..., None], self._rest_action(), act_h)
        return obs_h, act_h

    def _warm_start(self, plan: torch.Tensor, step: torch.Tensor) -> torch.Tensor | None:
        """The unexecuted rest of each plan, padded with its last action; zeros when a plan ran out."""
        if not self.warm_start:
            return None
        offsets = torch.arange(self.horizon, device=step.device)
        shift = (step[:, None] + offsets).clamp(max=self.horizon - 1)
        init = plan.gather(-2, shift[..., None].expand(-1, -1, self.action_dim))
        return torch.where((step >= self.horizon)[:, None, None], torch.zeros_like(init), init)


def _at_step(x: torch.Tensor, step: torch.Tensor) -> torch.Tensor:
    """``x[i, step[i]]`` for ``x`` ``[R, H, ...]``."""
    index = step.view(-1, 1, *([1] * (x.ndim - 2))).expand(-1, 1, *x.shape[2:])
    return x.gather(1, index).squeeze(1)


def _check_wiring(
    planner: PlannerBase, warm_start: bool, obs_key: object, action_key: object
) -> None:
    """Refuse a planner that is not a ``PlannerBase``, a non-bool ``warm_start`` or a key that
    is not a TensorDict key."""
    check_type("planner", planner, PlannerBase, "a planner (a PlannerBase, e.g. CEMPlanner)")
    check_flag("warm_start", warm_start)
    for name, key in (("obs_key", obs_key), ("action_key", action_key)):
        if not is_key(key):
            raise TypeError(
                f"{name} must be a TensorDict key (a str or tuple of str), got {key!r}."
            )


def _check_replan(
    planner: PlannerBase,
    replan: str,
    replan_every: int,
    threshold: float | None,
    threshold_on: str,
    error_threshold: float | None,
) -> None:
    """Refuse a re-plan setting that is unknown, incomplete or out of range for ``replan``."""
    if replan not in ("every_step", "every_n", "uncertainty"):
        raise ValueError(
            f"replan must be 'every_step', 'every_n' or 'uncertainty', got {replan!r}."
        )
    if replan == "every_n":
        check_int("replan_every", replan_every)
    if replan == "uncertainty":
        if threshold is None:
            raise ValueError("replan='uncertainty' needs a threshold.")
        check_real("threshold", threshold)
        if planner.model.uncertainty is None:
            raise ValueError(
                "replan='uncertainty' needs a planning model with an uncertainty estimator."
            )
    if threshold_on not in ("step", "cumulative"):
        raise ValueError(f"threshold_on must be 'step' or 'cumulative', got {threshold_on!r}.")
    if error_threshold is not None and not (0 < error_threshold < float("inf")):
        raise ValueError(
            f"error_threshold must be a positive finite number or None, got {error_threshold!r}."
        )


def _warmup_steps(warmup: str, warmup_steps: int | None, context: int) -> int:
    """The number of warm-up steps after each reset: 0 for ``warmup="plan"``, else
    ``warmup_steps`` (at least the context length ``context``, which is the default)."""
    if warmup not in WARMUP_MODES:
        raise ValueError(f"warmup must be one of {list(WARMUP_MODES)}, got {warmup!r}.")
    if warmup == "plan":
        if warmup_steps not in (None, 0):
            raise ValueError(
                f"warmup='plan' plans from the first step: warmup_steps must be 0 or None, "
                f"got {warmup_steps}."
            )
        return 0
    if warmup_steps is not None and warmup_steps < context:
        raise ValueError(
            f"warmup_steps={warmup_steps} is shorter than the context the planner needs ({context})."
        )
    return context if warmup_steps is None else warmup_steps
