"""TorchRL world models and the library's planners, both ways round.

* :class:`TorchRLWorldModelAdapter`: a TorchRL :class:`~torchrl.modules.WorldModel` (or the one
  a ``WorldModelEnv`` drives) as a world model of :class:`~torchrl_recon.planners.PlanningModel`:
  all candidates rolled out in one batch, its reward (and done) head scored, the states decoded
  where it has a decoder, so every planner of the library runs on it
  (:meth:`PlanningModel.from_torchrl <torchrl_recon.planners.PlanningModel.from_torchrl>`).
* :class:`LSTMWorldModelModule`: our :class:`~torchrl_recon.modules.LSTMWorldModel` as a TorchRL
  ``WorldModel`` (context encoder, LSTM dynamics, a cost's reward head), its recurrent state and
  real context in the TensorDict, for TorchRL's ``WorldModelEnv``, ``env.rollout`` and planners.
* :class:`BatchedWorldModelEnv`: TorchRL's ``WorldModelEnv`` as TorchRL's planners need it
  (any batch of tensordicts, specs from an unbatched env, the start state kept through a
  ``TransformedEnv``'s reset).
"""

from __future__ import annotations

from collections.abc import Sequence

import torch
from tensordict import NestedKey, TensorDict, TensorDictBase, unravel_key
from tensordict.nn import TensorDictModule, TensorDictModuleBase
from torch import nn
from torchrl.data import Bounded, Categorical, Composite, TensorSpec, Unbounded
from torchrl.envs import EnvBase
from torchrl.envs.model_based import ModelBasedEnvBase, WorldModelEnv
from torchrl.envs.utils import step_mdp
from torchrl.modules import WorldModel

from torchrl_recon.devices import module_device, module_dtype
from torchrl_recon.estimators.uncertainty import UncertaintyEstimator
from torchrl_recon.modules.checks import check_features, check_int
from torchrl_recon.modules.world_model import LSTMWorldModel
from torchrl_recon.planners.bounds import action_bounds, bounds_from_spec
from torchrl_recon.planners.planning_model import CostFn, PlanningModel, TerminationFn

__all__ = [
    "BatchedWorldModelEnv",
    "CONTEXT_ACTION",
    "CONTEXT_OBS",
    "LSTMWorldModelModule",
    "TorchRLWorldModelAdapter",
    "planning_model_from_torchrl",
]

CONTEXT_OBS: tuple[str, str] = ("context", "observation")
"""The real states s_{t-T..t-1} before the current one, ``[*B, T, N]`` (what
:class:`LSTMWorldModelModule`'s encoder warms the LSTM up on)."""
CONTEXT_ACTION: tuple[str, str] = ("context", "action")
"""The real actions a_{t-T..t-1}, ``[*B, T, M]``."""
H_KEY, C_KEY = "wm_h", "wm_c"


def _unbatched(spec: TensorSpec, batch_dims: int) -> TensorSpec:
    """An env's leaf spec without its env batch dims (the first ``batch_dims``)."""
    for _ in range(batch_dims):
        spec = spec[0]
    return spec


def _batched(spec: TensorSpec, batch: torch.Size) -> TensorSpec:
    """A leaf or composite spec with ``batch`` put before its own shape."""
    if not batch:
        return spec.clone()
    return spec.expand(*batch, *spec.shape).clone()


class BatchedWorldModelEnv(WorldModelEnv):
    """TorchRL's :class:`~torchrl.envs.model_based.WorldModelEnv`, as TorchRL's planners need it.

    In torchrl 0.14.1, ``WorldModelEnv`` cannot be planned on by its own ``CEMPlanner`` or
    ``MPPIPlanner``: its ``_step`` returns a tensordict of the env's batch size, so the
    planner's batch of ``[*B, K]`` candidates fails in ``_step_proc_data`` (``shape '[1]' is
    invalid for input of size K``); its constructor expands the reference env's leaf specs
    with the batch size as their whole shape, which raises for an unbatched env
    (``batch_size=[]``, what the planners need) and gives a ``[B]`` action spec for a
    one-dimensional action and ``batch_size=[B]``; and it has no state spec, so a
    ``TransformedEnv`` over it drops the start latent on ``reset`` (its own ``_reset`` then
    raises). This subclass steps any batch, puts the env batch before the reference env's
    unbatched specs and declares the observation spec as its state spec. Everything else is
    ``WorldModelEnv``'s: the world model's ``step_module`` is run, its ``("next", key)``
    outputs of the observation, reward and done specs are the step's.

    Args:
        world_model: the TorchRL ``WorldModel``.
        base_env: a reference env (not stepped) for the action, reward and done specs, and the
            observation spec unless ``observation_spec`` is given; or None with ``action_spec``.

    Keyword Args:
        observation_spec: unbatched ``Composite`` of what the env carries step to step (the
            latent, any recurrent state); default the reference env's.
        action_spec, reward_spec: unbatched specs instead of the reference env's (the reward's
            default ``Unbounded((1,))``).
        batch_size: the env's batch size; default ``[]``, any batch (the planners' case).
        device: default the reference env's, else the world model's.
        latent_key: the entry a start tensordict must hold (``WorldModelEnv``'s).

    Examples:
        >>> from tensordict.nn import TensorDictModule
        >>> from torchrl.envs import GymEnv
        >>> from torchrl.modules import MLP, CEMPlanner, WorldModel
        >>> encoder = TensorDictModule(nn.Linear(3, 4), in_keys=["observation"], out_keys=["latent"])
        >>> dynamics = TensorDictModule(MLP(in_features=5, out_features=4, depth=0),  # cat(latent, action)
        ...                             in_keys=["latent", "action"], out_keys=[("next", "latent")])
        >>> reward = TensorDictModule(nn.Linear(4, 1), in_keys=[("next", "latent")], out_keys=[("next", "reward")])
        >>> world_model = WorldModel(encoder, dynamics, reward)
        >>> env = BatchedWorldModelEnv(world_model, GymEnv("Pendulum-v1"),
        ...                            observation_spec=Composite(latent=Unbounded((4,))))
        >>> start = world_model.encode(TensorDict({"observation": torch.randn(3)}, []))
        >>> CEMPlanner(env, 5, 2, 16, 4)(start)["action"].shape
        torch.Size([1])
    """

    def __init__(
        self,
        world_model: WorldModel,
        base_env: EnvBase | None = None,
        *,
        observation_spec: Composite | None = None,
        action_spec: TensorSpec | None = None,
        reward_spec: TensorSpec | None = None,
        batch_size: int | Sequence[int] | torch.Size | None = None,
        device: torch.device | str | None = None,
        latent_key: NestedKey = "latent",
    ) -> None:
        if base_env is None and action_spec is None:
            raise ValueError(
                "BatchedWorldModelEnv needs a reference env (base_env=) or its specs "
                "(action_spec=, observation_spec=)."
            )
        if batch_size is None:
            batch_size = ()
        batch = torch.Size([batch_size] if isinstance(batch_size, int) else batch_size)
        if device is None:
            device = base_env.device if base_env is not None else None
        if device is None:
            device = (
                module_device(world_model) if any(True for _ in world_model.parameters()) else "cpu"
            )
        ModelBasedEnvBase.__init__(
            self,
            world_model.step_module,
            device=device,
            batch_size=batch,
            allow_done_after_reset=True,
        )
        self._world_model = world_model
        self.latent_key = latent_key
        nb = 0 if base_env is None else len(base_env.batch_size)
        if action_spec is None:
            action_spec = _unbatched(base_env.action_spec, nb)
        if reward_spec is None:
            reward_spec = (
                Unbounded((1,)) if base_env is None else _unbatched(base_env.reward_spec, nb)
            )
        if observation_spec is None:
            if base_env is None:
                raise ValueError("pass observation_spec= (no reference env to read it from).")
            observation_spec = _unbatched(base_env.observation_spec, nb)
        if base_env is None:
            done = Composite(
                {
                    key: Categorical(2, (1,), dtype=torch.bool)
                    for key in ("done", "terminated", "truncated")
                }
            )
        else:
            done = _unbatched(base_env.full_done_spec, nb)
        self.action_spec = _batched(action_spec, batch).to(self.device)
        self.reward_spec = _batched(reward_spec, batch).to(self.device)
        self.full_done_spec = _batched(done, batch).to(self.device)
        self.observation_spec = _batched(observation_spec, batch).to(self.device)
        self.state_spec = self.observation_spec.clone()

    def _step(self, tensordict: TensorDictBase) -> TensorDictBase:
        """``WorldModelEnv._step`` on the tensordict's own batch size."""
        out = self.world_model(tensordict.copy())
        next_td = out.get("next", default=None)
        result = TensorDict(batch_size=tensordict.batch_size, device=self.device)
        if next_td is None:
            return result
        for key in self.observation_spec.keys(include_nested=True, leaves_only=True):
            value = next_td.get(key, default=None)
            if value is not None:
                result.set(key, value)
        for spec in (self.full_reward_spec, self.full_done_spec):
            for key in spec.keys(include_nested=True, leaves_only=True):
                value = next_td.get(key, default=None)
                if value is None:
                    value = spec[key].zero(
                        tensordict.batch_size[: tensordict.batch_dims - self.batch_dims]
                    )
                result.set(key, value)
        return result

    def _reset(self, tensordict: TensorDictBase | None = None, **kwargs) -> TensorDictBase:
        """``WorldModelEnv._reset`` (the start latent from the caller, done flags zero) on the
        tensordict's own batch size."""
        if tensordict is None or self.latent_key not in tensordict.keys(include_nested=True):
            return super()._reset(tensordict, **kwargs)  # its error: no start latent
        out = tensordict.copy()
        lead = tensordict.batch_size[: tensordict.batch_dims - self.batch_dims]
        zero_done = self.full_done_spec.zero(lead)
        for key in zero_done.keys(include_nested=True, leaves_only=True):
            out.set(key, zero_done.get(key))
        return out


# -- item 2: a TorchRL WorldModel as the library's world model ------------------------------


class _Stash:
    """What the last :meth:`TorchRLWorldModelAdapter.imagine` predicted besides the states."""

    def __init__(self, states: torch.Tensor, reward: torch.Tensor, done: torch.Tensor | None):
        self.states, self.reward, self.done = states, reward, done


class _HeadCost:
    """``cost(obs, action, next_obs)`` = −the world model's reward head, as
    :class:`~torchrl_recon.planners.PlanningModel` takes a cost: the head's predictions of the
    rollout that made ``next_obs``, else (other states) the head on re-encoded states."""

    def __init__(self, adapter: TorchRLWorldModelAdapter) -> None:
        self.adapter = adapter

    def __call__(
        self, obs: torch.Tensor, action: torch.Tensor, next_obs: torch.Tensor
    ) -> torch.Tensor:
        stash = self.adapter._stash
        if stash is not None and stash.states is next_obs:
            return -stash.reward
        return -self.adapter.reward(obs, action, next_obs)

    def __repr__(self) -> str:
        return f"reward head of {self.adapter!r}"


class _HeadTermination:
    """``termination(obs, action, next_obs)`` from the world model's done head."""

    def __init__(self, adapter: TorchRLWorldModelAdapter) -> None:
        self.adapter = adapter

    def __call__(
        self, obs: torch.Tensor, action: torch.Tensor, next_obs: torch.Tensor
    ) -> torch.Tensor:
        stash = self.adapter._stash
        if stash is not None and stash.states is next_obs and stash.done is not None:
            return stash.done
        return obs.new_zeros(next_obs.shape[:-1], dtype=torch.bool)

    def __repr__(self) -> str:
        return f"done head of {self.adapter!r}"


class TorchRLWorldModelAdapter(nn.Module):
    """A TorchRL :class:`~torchrl.modules.WorldModel` as the library's planners take a world model.

    :meth:`imagine` encodes the current state s_t once per candidate, then advances all
    ``[*B, K]`` candidates together, one call of the dynamics and reward (and done) heads per
    step (``H`` calls in all, none per candidate), carrying ``("next", ·)`` to the root between
    steps as ``step_mdp`` does; with a decoder, the H predicted latents are decoded in one call
    at the end. The states it returns (what the cost, the estimator and the plan see) are the
    decoded observations, or the latents themselves when there is no decoder (they must then be
    observations: an encoder that copies or normalises them). :attr:`cost` and
    :attr:`termination` read the reward and done heads' predictions of that same rollout, for
    :class:`~torchrl_recon.planners.PlanningModel`'s ``cost_fn`` / ``termination_fn``
    (:meth:`PlanningModel.from_torchrl <torchrl_recon.planners.PlanningModel.from_torchrl>`
    wires them); gradients flow through everything, so the gradient planner works too.

    The model is Markov (the real context only feeds u's windows): ``window`` (default 1) is
    the number of real pairs it asks for. The rollout runs eagerly (no ``compile``/``threads``).

    Args:
        world_model: a TorchRL ``WorldModel``, or a ``WorldModelEnv`` driving one (its latent
            key and action spec are read from it).

    Keyword Args:
        obs_dim: N, the observation size; default from ``env`` or the ``WorldModelEnv``'s
            observation spec at ``observation_key``.
        action_dim: M; default from ``env`` or the ``WorldModelEnv``'s action spec.
        env: a reference env to read N and M from.
        observation_key, action_key: the encoder's input and the dynamics' action.
        latent_key: the encoder's output (default ``"latent"``, or the ``WorldModelEnv``'s).
        reward_key: the reward head's output.
        done_key: the done head's output (default its first out key).
        window: real (s, a) pairs the model asks for before s_t.

    Examples:
        >>> from tensordict.nn import TensorDictModule
        >>> encoder = TensorDictModule(nn.Identity(), in_keys=["observation"], out_keys=["latent"])
        >>> dynamics = TensorDictModule(nn.Bilinear(3, 1, 3), in_keys=["latent", "action"],
        ...                             out_keys=[("next", "latent")])
        >>> reward = TensorDictModule(nn.Linear(3, 1), in_keys=[("next", "latent")],
        ...                           out_keys=[("next", "reward")])
        >>> adapter = TorchRLWorldModelAdapter(WorldModel(encoder, dynamics, reward), obs_dim=3, action_dim=1)
        >>> states = adapter.imagine(torch.zeros(2, 1, 3), torch.zeros(2, 1, 1), torch.randn(2, 3),
        ...                          torch.rand(2, 50, 10, 1))
        >>> states.shape, adapter.cost(None, None, states).shape
        (torch.Size([2, 50, 10, 3]), torch.Size([2, 50, 10]))
    """

    def __init__(
        self,
        world_model: WorldModel | WorldModelEnv,
        *,
        obs_dim: int | None = None,
        action_dim: int | None = None,
        env: EnvBase | None = None,
        observation_key: NestedKey = "observation",
        action_key: NestedKey = "action",
        latent_key: NestedKey | None = None,
        reward_key: NestedKey = ("next", "reward"),
        done_key: NestedKey | None = None,
        window: int = 1,
    ) -> None:
        super().__init__()
        model_env = world_model if isinstance(world_model, WorldModelEnv) else None
        if model_env is not None:
            world_model = model_env._world_model
            latent_key = model_env.latent_key if latent_key is None else latent_key
        if not isinstance(world_model, WorldModel):
            raise TypeError(
                "world_model must be a torchrl.modules.WorldModel or a WorldModelEnv driving one, "
                f"got {type(world_model).__name__}."
            )
        check_int("window", window)
        self.world_model = world_model
        self.observation_key, self.action_key = (
            unravel_key(observation_key),
            unravel_key(action_key),
        )
        self.latent_key = unravel_key("latent" if latent_key is None else latent_key)
        self.reward_key = unravel_key(reward_key)
        heads = world_model.done_head
        self.done_key = None
        if heads is not None:
            self.done_key = unravel_key(done_key if done_key is not None else heads.out_keys[0])
        obs_dim, action_dim = self._sizes(obs_dim, action_dim, env, model_env)
        self.obs_dim, self.action_dim, self.window = obs_dim, action_dim, window
        decoder = world_model.decoder
        if decoder is not None and len(decoder.in_keys) != 1:
            raise ValueError(
                f"the world model's decoder reads {decoder.in_keys}; the adapter decodes latents "
                "alone (a decoder with one in key, the latent)."
            )
        self.cost = _HeadCost(self)
        """``cost_fn`` of the reward head (for :class:`~torchrl_recon.planners.PlanningModel`)."""
        self.termination = None if heads is None else _HeadTermination(self)
        """``termination_fn`` of the done head, or None without one."""
        self._stash: _Stash | None = None
        latent = self._probe()
        if decoder is None and latent != obs_dim:
            raise ValueError(
                f"the world model's latent ({self.latent_key!r}) has {latent} features but the "
                f"observation has {obs_dim}, and it has no decoder: give WorldModel(decoder=...) "
                "so that the planner's states are observations (the cost and the estimator read "
                "them)."
            )

    def _sizes(
        self,
        obs_dim: int | None,
        action_dim: int | None,
        env: EnvBase | None,
        model_env: WorldModelEnv | None,
    ) -> tuple[int, int]:
        for source in (env, model_env):
            if source is None:
                continue
            if action_dim is None:
                action_dim = source.action_spec.shape[-1]
            obs_spec = source.observation_spec.get(self.observation_key, None)
            if obs_dim is None and obs_spec is not None:
                obs_dim = obs_spec.shape[-1]
        if obs_dim is None or action_dim is None:
            raise ValueError(
                f"the adapter needs the observation and action sizes (got obs_dim={obs_dim}, "
                f"action_dim={action_dim}); pass obs_dim= and action_dim=, or env= (a reference "
                "env with both specs)."
            )
        check_int("obs_dim", obs_dim)
        check_int("action_dim", action_dim)
        return int(obs_dim), int(action_dim)

    @torch.no_grad()
    def _probe(self) -> int:
        """The latent's size, from encoding one zero observation."""
        like = next(self.world_model.parameters(), torch.zeros(()))
        obs = torch.zeros(1, self.obs_dim, dtype=like.dtype, device=like.device)
        return self.encode(obs).shape[-1]

    def encode(self, observation: torch.Tensor) -> torch.Tensor:
        """The latent of observations ``[*B, N]`` (the world model's encoder)."""
        td = TensorDict({self.observation_key: observation}, observation.shape[:-1])
        return self.world_model.encode(td).get(self.latent_key)

    def decode(self, latent: torch.Tensor) -> torch.Tensor:
        """The observations of latents ``[*B, L]`` (the decoder; the latents without one)."""
        decoder = self.world_model.decoder
        if decoder is None:
            return latent
        td = TensorDict({decoder.in_keys[0]: latent}, latent.shape[:-1])
        return decoder(td).get(decoder.out_keys[0])

    def reward(
        self, obs: torch.Tensor, action: torch.Tensor, next_obs: torch.Tensor
    ) -> torch.Tensor:
        """The reward head on transitions ``[*B, N]``, ``[*B, M]``, ``[*B, N]`` → ``[*B]``, both
        states encoded (the latent the head reads is then ``encode(next_obs)``: exact for a model
        whose latent is a function of the observation, approximate through a decoder)."""
        batch = next_obs.shape[:-1]
        td = TensorDict(
            {
                self.observation_key: obs.expand(*batch, obs.shape[-1]),
                self.action_key: action.expand(*batch, action.shape[-1]),
            },
            batch,
        )
        td = self.world_model.encode(td)
        td.set(("next", *_as_tuple(self.latent_key)), self.encode(next_obs))
        return self.world_model.reward_head(td).get(self.reward_key).reshape(batch)

    def imagine(
        self,
        context_obs: torch.Tensor,
        context_action: torch.Tensor,
        observation: torch.Tensor,
        actions: torch.Tensor,
        *,
        state: None = None,
    ) -> torch.Tensor:
        """Predict states for candidates ``actions`` ``[*B, K, H, M]`` from s_t ``[*B, N]``.

        The context (``[*B, T', N]``, ``[*B, T', M]``) is not read: the model is Markov.

        Returns:
            s_{t+1..t+H}, ``[*B, K, H, N]``; the reward (and done) heads' predictions of the same
            steps are kept for :attr:`cost` (and :attr:`termination`).
        """
        check_features("observation", observation, self.obs_dim)
        check_features("actions", actions, self.action_dim, min_ndim=3)
        batch = observation.shape[:-1]
        if actions.shape[:-3] != batch:
            raise ValueError(
                f"actions has shape {tuple(actions.shape)}; expected [*B, K, H, {self.action_dim}] "
                f"with *B = {tuple(batch)}, the observation's batch."
            )
        k, horizon = actions.shape[-3], actions.shape[-2]
        rows = batch.numel() * k
        obs = observation.unsqueeze(-2).expand(*batch, k, self.obs_dim).reshape(rows, self.obs_dim)
        flat = actions.reshape(rows, horizon, self.action_dim)
        td = self.world_model.encode(TensorDict({self.observation_key: obs}, [rows]))
        model = self.world_model
        latents, rewards, dones = [], [], []
        for step in range(horizon):
            td.set(self.action_key, flat[:, step])
            td = _run(model.dynamics, td)
            td = _run(model.reward_head, td)
            if model.done_head is not None:
                td = _run(model.done_head, td)
                dones.append(td.get(self.done_key).reshape(rows))
            latents.append(td.get(("next", *_as_tuple(self.latent_key))))
            rewards.append(td.get(self.reward_key).reshape(rows))
            td = step_mdp(td, keep_other=True, exclude_reward=True, exclude_done=True)
        latent = torch.stack(latents, 1)  # [rows, H, L]
        states = self.decode(latent.reshape(rows * horizon, -1)).reshape(
            *batch, k, horizon, self.obs_dim
        )
        done = None if not dones else torch.stack(dones, 1).reshape(*batch, k, horizon).bool()
        self._stash = _Stash(states, torch.stack(rewards, 1).reshape(*batch, k, horizon), done)
        return states

    def extra_repr(self) -> str:
        return (
            f"obs_dim={self.obs_dim}, action_dim={self.action_dim}, latent_key={self.latent_key!r}"
        )


def _as_tuple(key: NestedKey) -> tuple[str, ...]:
    return (key,) if isinstance(key, str) else tuple(key)


def _run(module: nn.Module, td: TensorDictBase) -> TensorDictBase:
    """``module(td)``; for a plain ``TensorDictModule`` (positional in keys, in place, no hooks
    on it) its own steps without the per-call wrapping of each output (``TensorDict.from_any``,
    whose module lookup costs about as much as a small layer: the rollout's hot loop)."""
    plain = (
        type(module) is TensorDictModule
        and module.inplace is True
        and module._kwargs is None
        and not module._get_kwargs
        and not (module._forward_hooks or module._forward_pre_hooks)
    )
    if not plain:
        return module(td)
    out = module._call_module(tuple(td.get(key) for key in module.in_keys))
    out = out if isinstance(out, tuple) else (out,)
    if len(out) != len(module.out_keys_source) or not all(isinstance(x, torch.Tensor) for x in out):
        return module(td)  # not tensors in key order: the module's own way
    for key, value in zip(module.out_keys_source, out, strict=True):
        if key != "_":
            td.set(key, value)
    return td


def planning_model_from_torchrl(
    world_model: WorldModel | WorldModelEnv,
    *,
    env: EnvBase | None = None,
    cost_fn: CostFn | None = None,
    uncertainty: UncertaintyEstimator | None = None,
    termination_fn: TerminationFn | None = None,
    action_low: float | torch.Tensor | None = None,
    action_high: float | torch.Tensor | None = None,
    **adapter_kwargs,
) -> PlanningModel:
    """:meth:`PlanningModel.from_torchrl <torchrl_recon.planners.PlanningModel.from_torchrl>`."""
    adapter = TorchRLWorldModelAdapter(world_model, env=env, **adapter_kwargs)
    spec_source = env if env is not None else world_model
    if action_low is None and action_high is None:
        if not isinstance(spec_source, EnvBase):
            raise ValueError(
                "the action bounds come from an env's action spec: pass env= (or a "
                "WorldModelEnv as world_model), or action_low= and action_high=."
            )
        action_low, action_high = bounds_from_spec(spec_source.action_spec)
    elif action_low is None or action_high is None:
        raise ValueError("pass both action_low= and action_high=, or neither (read from env=).")
    if termination_fn is None:
        termination_fn = adapter.termination
    return PlanningModel(
        adapter,
        adapter.cost if cost_fn is None else cost_fn,
        uncertainty=uncertainty,
        termination_fn=termination_fn,
        action_low=action_low,
        action_high=action_high,
    )


# -- item 3: our LSTM world model inside TorchRL's types ------------------------------------


class _LSTMContextEncoder(TensorDictModuleBase):
    """The LSTM's state after the real context: ``(context, observation)``,
    ``(context, action)`` ``[*B, T, ·]`` → ``wm_h``, ``wm_c`` ``[*B, hidden]``."""

    def __init__(self, world_model: LSTMWorldModel) -> None:
        super().__init__()
        self.world_model = world_model
        self.in_keys, self.out_keys = [CONTEXT_OBS, CONTEXT_ACTION], [H_KEY, C_KEY]

    def forward(self, td: TensorDictBase) -> TensorDictBase:
        h, c = self.world_model.warmup(td.get(CONTEXT_OBS), td.get(CONTEXT_ACTION))
        return td.set(H_KEY, h).set(C_KEY, c)


class _LSTMDynamics(TensorDictModuleBase):
    """One LSTM step: (s, a, h, c) → ``("next", ·)`` of each."""

    def __init__(self, world_model: LSTMWorldModel) -> None:
        super().__init__()
        self.world_model = world_model
        self.in_keys = ["observation", "action", H_KEY, C_KEY]
        self.out_keys = [("next", "observation"), ("next", H_KEY), ("next", C_KEY)]

    def forward(self, td: TensorDictBase) -> TensorDictBase:
        obs = td.get("observation")
        next_obs, (h, c) = self.world_model.step(
            obs, td.get("action").to(obs.dtype), (td.get(H_KEY), td.get(C_KEY))
        )
        td.set(("next", "observation"), next_obs)
        return td.set(("next", H_KEY), h).set(("next", C_KEY), c)


class _CostReward(TensorDictModuleBase):
    """``("next", "reward")`` = −cost(s, a, s')."""

    def __init__(self, cost_fn: CostFn) -> None:
        super().__init__()
        self.cost_fn = cost_fn
        self.in_keys = ["observation", "action", ("next", "observation")]
        self.out_keys = [("next", "reward")]

    def forward(self, td: TensorDictBase) -> TensorDictBase:
        cost = self.cost_fn(
            td.get("observation"), td.get("action"), td.get(("next", "observation"))
        )
        return td.set(("next", "reward"), -cost.unsqueeze(-1))


class _TerminationDone(TensorDictModuleBase):
    """``("next", "terminated")`` and ``("next", "done")`` from a termination function."""

    def __init__(self, termination_fn: TerminationFn) -> None:
        super().__init__()
        self.termination_fn = termination_fn
        self.in_keys = ["observation", "action", ("next", "observation")]
        self.out_keys = [("next", "terminated"), ("next", "done")]

    def forward(self, td: TensorDictBase) -> TensorDictBase:
        ended = self.termination_fn(
            td.get("observation"), td.get("action"), td.get(("next", "observation"))
        ).unsqueeze(-1)
        return td.set(("next", "terminated"), ended).set(("next", "done"), ended)


class LSTMWorldModelModule(WorldModel):
    """Our :class:`~torchrl_recon.modules.LSTMWorldModel` as a TorchRL
    :class:`~torchrl.modules.WorldModel`, for ``WorldModelEnv``, ``env.rollout`` and TorchRL's
    planners.

    Its parts are TensorDict modules over the same weights: the **encoder** warms the LSTM up on
    the real context in the tensordict (:data:`CONTEXT_OBS`, :data:`CONTEXT_ACTION`,
    ``[*B, T, ·]``) and writes its state (``wm_h``, ``wm_c``, ``[*B, hidden]``); the
    **dynamics** is one :meth:`~torchrl_recon.modules.LSTMWorldModel.step` from ``observation``,
    ``action`` and that state to ``("next", ·)`` of each; the **reward head** is
    ``−cost_fn(s, a, s')``; with ``termination_fn``, a **done head** writes
    ``("next", "terminated")`` and ``("next", "done")``. A rollout of :meth:`make_env` from
    :meth:`start` predicts what :meth:`LSTMWorldModel.imagine
    <torchrl_recon.modules.LSTMWorldModel.imagine>` does for the same actions (to float
    rounding: one step at a time through ``nn.LSTM`` instead of the fused rollout).

    Args:
        world_model: the (fitted) LSTM world model, one model (no members).
        cost_fn: batched torch ``cost(obs, action, next_obs)``.

    Keyword Args:
        termination_fn: optional ``termination(obs, action, next_obs) -> bool``.

    Examples:
        >>> from torchrl.modules import CEMPlanner
        >>> lstm = LSTMWorldModel(3, 1, window=4)
        >>> lstm.fit_normalization(torch.randn(64, 3), torch.randn(64, 1), torch.randn(64, 3))
        >>> world_model = LSTMWorldModelModule(lstm, lambda s, a, s1: s1.pow(2).sum(-1))
        >>> env = world_model.make_env(action_low=-2.0, action_high=2.0)
        >>> start = world_model.start(torch.zeros(4, 3), torch.zeros(4, 1), torch.zeros(3))
        >>> env.rollout(5, tensordict=start, auto_reset=False)["next", "observation"].shape
        torch.Size([5, 3])
        >>> CEMPlanner(env, 5, 2, 16, 4)(start)["action"].shape
        torch.Size([1])
    """

    def __init__(
        self,
        world_model: LSTMWorldModel,
        cost_fn: CostFn,
        *,
        termination_fn: TerminationFn | None = None,
    ) -> None:
        if not isinstance(world_model, LSTMWorldModel) or world_model.num_members is not None:
            raise TypeError(
                "LSTMWorldModelModule wraps one LSTMWorldModel (no members), got "
                f"{type(world_model).__name__}"
                + ("" if not isinstance(world_model, LSTMWorldModel) else " with members")
                + "."
            )
        super().__init__(
            _LSTMContextEncoder(world_model),
            _LSTMDynamics(world_model),
            _CostReward(cost_fn),
            done_head=None if termination_fn is None else _TerminationDone(termination_fn),
        )
        self.lstm_world_model = world_model

    def start(
        self, context_obs: torch.Tensor, context_action: torch.Tensor, observation: torch.Tensor
    ) -> TensorDictBase:
        """An imagined rollout's start: the real context ``[*B, T, N]``, ``[*B, T, M]``, the
        state s_t ``[*B, N]`` and the LSTM's state after the context (encoded), batch ``[*B]``."""
        batch = observation.shape[:-1]
        td = TensorDict(
            {"observation": observation, CONTEXT_OBS: context_obs, CONTEXT_ACTION: context_action},
            batch,
            device=observation.device,
        )
        with torch.no_grad():
            return self.encode(td)

    def observation_spec(self) -> Composite:
        """What the env carries step to step (unbatched): s, h, c."""
        wm = self.lstm_world_model
        device, dtype = module_device(wm), module_dtype(wm)
        return Composite(
            {
                "observation": Unbounded((wm.obs_dim,), device=device, dtype=dtype),
                H_KEY: Unbounded((wm.hidden_size,), device=device, dtype=dtype),
                C_KEY: Unbounded((wm.hidden_size,), device=device, dtype=dtype),
            },
            device=device,
        )

    def make_env(
        self,
        base_env: EnvBase | None = None,
        *,
        action_low: float | torch.Tensor | None = None,
        action_high: float | torch.Tensor | None = None,
    ) -> BatchedWorldModelEnv:
        """The ``WorldModelEnv`` (:class:`BatchedWorldModelEnv`) that drives this model: its
        observation spec is :meth:`observation_spec`, its action spec the reference env's, or
        the box ``[action_low, action_high]``; on the LSTM's device."""
        wm = self.lstm_world_model
        device, dtype = module_device(wm), module_dtype(wm)
        action_spec = None
        if base_env is None:
            if action_low is None or action_high is None:
                raise ValueError("pass a reference env, or action_low= and action_high=.")
            low, high = action_bounds(action_low, action_high, wm.action_dim, dtype=dtype)
            action_spec = Bounded(low, high, (wm.action_dim,), dtype=dtype)
        return BatchedWorldModelEnv(
            self,
            base_env,
            observation_spec=self.observation_spec(),
            action_spec=action_spec,
            device=device,
            latent_key=H_KEY,
        )
