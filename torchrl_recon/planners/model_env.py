"""Expose our world model (+ cost, + optional uncertainty penalty) as a TorchRL ``ModelBasedEnvBase``."""

from __future__ import annotations

import torch
from tensordict import TensorDict, TensorDictBase
from tensordict.nn import TensorDictModuleBase, TensorDictSequential
from torchrl.data import Bounded, Categorical, Composite, Unbounded
from torchrl.envs.model_based import ModelBasedEnvBase
from torchrl.modules import LSTMModule

from torchrl_recon.devices import module_device, module_dtype
from torchrl_recon.estimators.uncertainty import UncertaintyEstimator
from torchrl_recon.modules.activations import ACTIVATIONS
from torchrl_recon.modules.checks import check_real, check_type
from torchrl_recon.modules.fitted import ESTIMATOR, WORLD_MODEL, FittedCheck
from torchrl_recon.modules.world_model import LSTMWorldModel
from torchrl_recon.planners.bounds import action_bounds
from torchrl_recon.planners.planning_model import CostFn, TerminationFn, check_step_fn

__all__ = ["WorldModelPlanningEnv"]

H_KEY, C_KEY, U_HISTORY, ENDED = "wm_h", "wm_c", "u_history", "wm_ended"


class _InputModule(TensorDictModuleBase):
    """(s, a) → the world model's standardised LSTM input."""

    def __init__(self, world_model: LSTMWorldModel) -> None:
        super().__init__()
        self.world_model = world_model
        self.in_keys, self.out_keys = ["observation", "action"], ["wm_input"]

    def forward(self, td: TensorDictBase) -> TensorDictBase:
        wm_input = self.world_model.normalize_inputs(td.get("observation"), td.get("action"))
        return td.set("wm_input", wm_input)


class _StepModule(TensorDictModuleBase):
    """LSTM features → next observation, reward = −cost − β·u, and the rolled uncertainty history."""

    def __init__(
        self,
        world_model: LSTMWorldModel,
        cost_fn: CostFn,
        estimator: UncertaintyEstimator | None,
        beta: float,
        termination_fn: TerminationFn | None = None,
    ):
        super().__init__()
        self.world_model, self.cost_fn, self.estimator, self.beta = (
            world_model,
            cost_fn,
            estimator,
            beta,
        )
        self.termination_fn = termination_fn
        state = ([U_HISTORY] if estimator is not None else []) + (
            [ENDED] if termination_fn is not None else []
        )
        self.in_keys = ["wm_features", "observation", "action", *state]
        self.out_keys = ["observation", "reward", "is_init", *state]

    def forward(self, td: TensorDictBase) -> TensorDictBase:
        wm = self.world_model
        obs, action = td.get("observation"), td.get("action")
        z = ACTIVATIONS[wm.activation](wm.dense(td.get("wm_features")))
        next_obs = obs + wm.delta_norm.denormalize(wm.head(z))
        reward = -self.cost_fn(obs, action, next_obs)
        if self.estimator is not None:
            window = torch.cat([td.get(U_HISTORY), torch.cat([obs, action], -1).unsqueeze(-2)], -2)
            reward = reward - self.beta * self.estimator.score_windows(window)
            td.set(U_HISTORY, window[..., 1:, :])
        if self.termination_fn is not None:  # nothing accrues after a predicted end
            ended = td.get(ENDED).squeeze(-1)
            reward = reward.masked_fill(ended, 0.0)
            td.set(ENDED, (ended | self.termination_fn(obs, action, next_obs)).unsqueeze(-1))
        td.set("observation", next_obs)
        td.set("reward", reward.unsqueeze(-1))
        return td.set("is_init", torch.zeros_like(reward, dtype=torch.bool).unsqueeze(-1))


class WorldModelPlanningEnv(ModelBasedEnvBase):
    """Our :class:`~torchrl_recon.modules.LSTMWorldModel` as a TorchRL model-based env.

    Lets TorchRL's own ``CEMPlanner`` and ``MPPIPlanner`` plan on our models. The LSTM is
    TorchRL's ``LSTMModule`` sharing the world model's ``nn.LSTM`` weights; its state
    (``wm_h``, ``wm_c``), ``is_init`` and, with an estimator, the last ``T − 1`` (s, a) pairs
    (``u_history``) are part of the observation spec, so they are carried through rollouts.
    The reward is ``−cost − beta·u`` of each imagined transition, and 0 after the first
    transition ``termination_fn`` says ends the episode (its flag ``wm_ended`` is carried
    like the LSTM state). Start a rollout from
    :meth:`initial_state`, which warms the LSTM up on a real context. The env's device is the
    world model's (it is not moved). As :class:`~torchrl_recon.planners.PlanningModel`, it
    refuses a world model or estimator whose normalisation was never fitted, at the first
    :meth:`initial_state`, reset or step (a ``ValueError`` saying how to fit it).

    Args:
        world_model: the world model.
        cost_fn: batched torch cost ``cost(obs, action, next_obs)``.

    Keyword Args:
        uncertainty: optional estimator; with it the reward is penalised by ``beta·u``.
        beta: uncertainty weight.
        termination_fn: optional ``termination(obs, action, next_obs) -> bool [...]``.
        action_low, action_high: action bounds (floats or ``[M]`` tensors); finite, low < high.

    Examples:
        >>> from torchrl.modules import CEMPlanner as TorchRLCEMPlanner
        >>> from torchrl_recon.envs.drone import drone_cost
        >>> world_model = LSTMWorldModel(12, 4, window=3)
        >>> world_model.fit_normalization(torch.randn(50, 12), torch.rand(50, 4), torch.randn(50, 12))
        >>> env = WorldModelPlanningEnv(world_model, drone_cost)
        >>> planner = TorchRLCEMPlanner(env, planning_horizon=5, optim_steps=2, num_candidates=16, top_k=4)
        >>> td = env.initial_state(torch.zeros(3, 12), torch.zeros(3, 4), torch.zeros(12))
        >>> planner(td)["action"].shape
        torch.Size([4])
    """

    def __init__(
        self,
        world_model: LSTMWorldModel,
        cost_fn: CostFn,
        *,
        uncertainty: UncertaintyEstimator | None = None,
        beta: float = 0.0,
        termination_fn: TerminationFn | None = None,
        action_low: float | torch.Tensor = -1.0,
        action_high: float | torch.Tensor = 1.0,
    ) -> None:
        check_type("world_model", world_model, LSTMWorldModel, "an LSTMWorldModel")
        if uncertainty is not None:
            check_type("uncertainty", uncertainty, UncertaintyEstimator, "an UncertaintyEstimator")
        check_real("beta", beta)
        n, m = world_model.obs_dim, world_model.action_dim
        low, high = action_bounds(action_low, action_high, m, dtype=module_dtype(world_model))
        check_step_fn("cost_fn", cost_fn, n, m, device=module_device(world_model))
        if termination_fn is not None:
            check_step_fn(
                "termination_fn",
                termination_fn,
                n,
                m,
                device=module_device(world_model),
                boolean=True,
            )
        lstm = LSTMModule(
            lstm=world_model.lstm,
            in_keys=["wm_input", H_KEY, C_KEY],
            out_keys=["wm_features", H_KEY, C_KEY],
        )
        module = TensorDictSequential(
            _InputModule(world_model),
            lstm,
            _StepModule(world_model, cost_fn, uncertainty, beta, termination_fn),
        )
        device = module_device(world_model)
        super().__init__(module, device=device)
        self.lstm_world_model, self.estimator = world_model, uncertainty
        self.termination_fn = termination_fn
        self._world_model_fitted = FittedCheck(WORLD_MODEL)
        self._estimator_fitted = FittedCheck(ESTIMATOR)
        hid = world_model.hidden_size
        observation = {
            "observation": Unbounded((n,), device=device),
            H_KEY: Unbounded((1, hid), device=device),
            C_KEY: Unbounded((1, hid), device=device),
            "is_init": Categorical(2, (1,), dtype=torch.bool, device=device),
        }
        if uncertainty is not None:
            observation[U_HISTORY] = Unbounded((uncertainty.window - 1, n + m), device=device)
        if termination_fn is not None:
            observation[ENDED] = Categorical(2, (1,), dtype=torch.bool, device=device)
        self.observation_spec = Composite(observation, device=device)
        self.state_spec = self.observation_spec.clone()
        self.action_spec = Bounded(low.to(device), high.to(device), (m,), device=device)
        self.reward_spec = Unbounded((1,), device=device)

    def initial_state(
        self, context_obs: torch.Tensor, context_action: torch.Tensor, observation: torch.Tensor
    ) -> TensorDictBase:
        """A start tensordict from a real context ``[*B, T, N]``, ``[*B, T, M]`` and state ``[*B, N]``."""
        self.check_fitted()
        wm = self.lstm_world_model
        with torch.no_grad():
            h, c = wm.warmup(context_obs, context_action)
        batch = observation.shape[:-1]
        td = TensorDict(
            {
                "observation": observation,
                H_KEY: h.unsqueeze(-2),
                C_KEY: c.unsqueeze(-2),
                "is_init": torch.zeros(*batch, 1, dtype=torch.bool, device=observation.device),
            },
            batch,
            device=observation.device,  # TorchRL's planners allocate on the tensordict's device
        )
        if self.termination_fn is not None:
            td.set(ENDED, torch.zeros(*batch, 1, dtype=torch.bool, device=observation.device))
        if self.estimator is not None:
            past = self.estimator.window - 1
            td.set(
                U_HISTORY,
                torch.cat([context_obs, context_action], -1)[
                    ..., context_obs.shape[-2] - past :, :
                ],
            )
        return td

    def check_fitted(self) -> None:
        """Refuse a world model or estimator whose normalisation was never fitted (checked once,
        then only re-checked after their ``fitted`` buffers changed; see
        :class:`~torchrl_recon.modules.fitted.FittedCheck`)."""
        self._world_model_fitted(self.lstm_world_model)
        if self.estimator is not None:
            self._estimator_fitted(self.estimator)

    def _step(self, tensordict: TensorDictBase) -> TensorDictBase:
        self.check_fitted()
        return super()._step(tensordict)

    def _reset(self, tensordict: TensorDictBase | None = None, **kwargs) -> TensorDictBase:
        """Keep a given start state; fill missing entries with zeros (``is_init`` False)."""
        self.check_fitted()
        batch = tensordict.batch_size if tensordict is not None else self.batch_size
        out = self.observation_spec.zero(batch)
        if tensordict is not None:
            out.update(tensordict.select(*self.observation_spec.keys(), strict=False))
        return out
