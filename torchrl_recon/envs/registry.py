"""The one table of environments: names, gymnasium ids, classes and torch cost functions."""

from __future__ import annotations

import functools
import importlib
import inspect
from collections.abc import Callable, Mapping
from dataclasses import dataclass
from typing import Any

import gymnasium as gym
import torch

from torchrl_recon.plugins import import_object

CostFn = Callable[[torch.Tensor, torch.Tensor, torch.Tensor], torch.Tensor]


LEARNED = "learned"
"""A recipe's ``env.cost`` / ``env.termination`` that is learned from the data's rewards and
ends (:class:`~torchrl_recon.modules.RewardModel`) instead of imported."""


def import_cost(path: str, *, what: str = "cost") -> CostFn:
    """Import the cost function ``"module:function"`` (this runs ``module``'s code, as any import).

    The function must take ``(obs, action, next_obs)`` (batched torch tensors) and return the
    per-step cost of the same batch shape. ``what`` names it in messages: a termination
    function (``termination(obs, action, next_obs) -> bool``) is imported the same way.

    Raises:
        ValueError: one line: ``path`` is not ``module:function``, the module cannot be
            imported (or fails while importing), it has no such attribute, or the attribute
            is not a function of three positional arguments.

    Examples:
        >>> import_cost("torchrl_recon.envs.drone:drone_cost").__name__
        'drone_cost'
        >>> try:
        ...     import_cost("torchrl_recon.envs.drone:no_such_cost")
        ... except ValueError as e:
        ...     print(str(e).split(";")[0])
        cost 'torchrl_recon.envs.drone:no_such_cost': module 'torchrl_recon.envs.drone' has no attribute 'no_such_cost'
    """
    module, _, attr = str(path).partition(":")
    if not module or not attr or ":" in attr:
        raise ValueError(
            f"{what} must be 'module:function' (a batched torch {what}(obs, action, next_obs) "
            f"-> [...] in an importable module), got {path!r}."
        )
    where = f"{what} {path!r}"
    fn = import_object(path, what)
    if not callable(fn):
        raise ValueError(f"{where}: {module}.{attr} is a {type(fn).__name__}, not a function.")
    try:
        signature = inspect.signature(fn)
    except ValueError:  # no signature (a builtin): trust it
        return fn
    keywords = {
        n: None
        for n, p in signature.parameters.items()
        if p.kind is inspect.Parameter.KEYWORD_ONLY and p.default is inspect.Parameter.empty
    }
    try:  # keyword-only parameters may come from the env's keywords (EnvEntry.cost_fn_with)
        signature.bind(None, None, None, **keywords)
    except TypeError:
        raise ValueError(
            f"{where}: {module}.{attr}{signature} cannot be called as {what}(obs, action, next_obs)."
        ) from None
    return fn


@dataclass(frozen=True)
class EnvEntry:
    """One environment: short name, gymnasium id, class path, cost function path, episode limit, state names."""

    name: str
    gym_id: str
    entry_point: str
    cost_fn_path: str
    max_episode_steps: int
    state_names: tuple[str, ...] = ()

    def cost_fn(self) -> CostFn:
        """Import and return the batched torch cost ``cost(obs, action, next_obs) -> [...]``."""
        return import_cost(self.cost_fn_path)

    def cost_fn_with(self, env_kwargs: Mapping[str, Any]) -> CostFn:
        """The cost with the env keywords (a recipe's ``env.kwargs``) that the cost also takes.

        Examples:
            >>> get_entry("minitaur").cost_fn_with({"cost": "forward", "motor_kp": 1.0}).keywords
            {'cost': 'forward'}
        """
        fn = self.cost_fn()
        params = inspect.signature(fn).parameters
        shared = {
            k: v
            for k, v in env_kwargs.items()
            if k in params and params[k].kind is inspect.Parameter.KEYWORD_ONLY
        }
        return functools.partial(fn, **shared) if shared else fn

    def env_class(self) -> type:
        """Import and return the gymnasium environment class."""
        module, attr = self.entry_point.split(":")
        return getattr(importlib.import_module(module), attr)

    def keywords(self) -> dict[str, Any] | None:
        """The constructor keywords of the environment class and their defaults.

        Read from the class's ``__init__`` signature; a keyword without a default maps to
        ``inspect.Parameter.empty``. None when the constructor takes ``**kwargs`` (any keyword).

        Examples:
            >>> sorted(get_entry("industrial_benchmark").keywords())
            ['reference_rng', 'setpoint', 'stationary_setpoint']
        """
        params = inspect.signature(self.env_class().__init__).parameters
        if any(p.kind is inspect.Parameter.VAR_KEYWORD for p in params.values()):
            return None
        return {
            name: p.default
            for name, p in params.items()
            if name != "self" and p.kind is not inspect.Parameter.VAR_POSITIONAL
        }

    def check_kwargs(self, kwargs: Mapping[str, Any]) -> None:
        """Refuse constructor keywords the environment class does not take.

        Raises:
            TypeError: naming the environment, the unknown keywords and the accepted ones.

        Examples:
            >>> get_entry("drone").check_kwargs({"delta": 0.1})
            >>> try:
            ...     get_entry("drone").check_kwargs({"action_mode": "leg"})
            ... except TypeError as e:
            ...     print(str(e).split(";")[0])
            environment 'drone' (DroneEnv) has no keyword(s) ['action_mode']
        """
        allowed = self.keywords()
        if allowed is None:
            return
        unknown = sorted(set(kwargs) - set(allowed))
        if unknown:
            raise TypeError(
                f"environment {self.name!r} ({self.env_class().__name__}) has no keyword(s) "
                f"{unknown}; it accepts {sorted(allowed)}."
            )


ENVS: dict[str, EnvEntry] = {
    e.name: e
    for e in (
        EnvEntry(
            "industrial_benchmark",
            "torchrl_recon/IndustrialBenchmark-v0",
            "torchrl_recon.envs.industrial_benchmark:IndustrialBenchmarkEnv",
            "torchrl_recon.envs.industrial_benchmark:industrial_benchmark_cost",
            1000,
            ("p", "v", "g", "h", "f", "c"),
        ),
        EnvEntry(
            "drone",
            "torchrl_recon/Drone-v0",
            "torchrl_recon.envs.drone:DroneEnv",
            "torchrl_recon.envs.drone:drone_cost",
            500,
            ("x", "y", "z", "vx", "vy", "vz", "roll", "pitch", "yaw", "p", "q", "r"),
        ),
        EnvEntry(
            "minitaur",
            "torchrl_recon/Minitaur-v0",
            "torchrl_recon.envs.minitaur:MinitaurEnv",
            "torchrl_recon.envs.minitaur:minitaur_cost",
            500,
            tuple(
                [f"motor_angle_{i}" for i in range(8)]
                + [f"motor_velocity_{i}" for i in range(8)]
                + [f"motor_torque_{i}" for i in range(8)]
                + ["qx", "qy", "qz", "qw", "x - x0", "y - y0", "z", "vx", "vy", "vz"]
            ),
        ),
    )
}
"""The paper's three environments by short name (:func:`register_env` adds others beside them)."""


def get_entry(name: str) -> EnvEntry:
    """Look an environment up by short name (``"drone"``) or gymnasium id.

    A shipped env or one added with :func:`register_env` comes back as registered; a DeepMind
    Control task ``"dmc:<domain>/<task>"`` (the ``dmc`` extra) as a
    :class:`~torchrl_recon.envs.dmc.DMCEntry`; any other gymnasium id (``"Pendulum-v1"``, or
    ``"my_module:MyEnv-v0"``, which imports ``my_module`` first) as a generic :class:`GymEntry`
    without a torch cost (see :func:`gym_entry`).

    Raises:
        ValueError: ``name`` is neither registered here nor a gymnasium id nor a DeepMind
            Control task (or is one and dm_control is not installed).

    Examples:
        >>> get_entry("torchrl_recon/Drone-v0").name
        'drone'
        >>> get_entry("Pendulum-v1").env_class().__name__
        'PendulumEnv'
    """
    for entry in (*ENVS.values(), *USER_ENVS.values()):
        if name in (entry.name, entry.gym_id):
            return entry
    from torchrl_recon.envs.dmc import dmc_entry, is_dmc_id  # dm_control only for a dmc: id

    if is_dmc_id(name):
        return dmc_entry(name)
    return gym_entry(name)


def register_envs() -> None:
    """Register every environment with gymnasium (idempotent)."""
    for entry in ENVS.values():
        if entry.gym_id not in gym.registry:
            gym.register(
                id=entry.gym_id,
                entry_point=entry.entry_point,
                max_episode_steps=entry.max_episode_steps,
            )


# ----------------------------------------------------------------------------------------------
# Any gymnasium environment: a generic entry, and user registrations with a torch cost


USER_ENVS: dict[str, EnvEntry] = {}


@dataclass(frozen=True)
class GymEntry(EnvEntry):
    """An environment known to gymnasium but not shipped here: no torch cost unless one is given.

    ``gym_id`` is what ``gymnasium.make`` is called with (``"Pendulum-v1"`` or
    ``"my_module:MyEnv-v0"``); ``cost_fn_path`` is ``"module:function"`` or ``""`` for none;
    ``max_episode_steps`` is gymnasium's (None for no limit).
    """

    def cost_fn(self) -> CostFn:
        """The registered torch cost; a clear error when the env has none."""
        if not self.cost_fn_path:
            raise ValueError(
                f"environment {self.name!r} has no torch cost; write one, cost(obs, action, "
                "next_obs) -> [...] (batched, in torch), and register it with "
                f"torchrl_recon.envs.register_env({self.gym_id!r}, cost='my_module:my_cost'), "
                "or pass it to PlanningModel directly."
            )
        return super().cost_fn()

    def env_class(self) -> type:
        """The class (or factory function) gymnasium builds the environment with."""
        entry_point = _gym_spec(self.gym_id).entry_point
        if isinstance(entry_point, str):
            module, attr = entry_point.split(":")
            return getattr(importlib.import_module(module), attr)
        return entry_point

    def keywords(self) -> dict[str, Any] | None:
        """The constructor keywords of the environment and their defaults (None: any keyword)."""
        target = self.env_class()
        params = inspect.signature(target.__init__ if isinstance(target, type) else target)
        params = params.parameters
        if any(p.kind is inspect.Parameter.VAR_KEYWORD for p in params.values()):
            return None
        return {
            name: p.default
            for name, p in params.items()
            if name != "self" and p.kind is not inspect.Parameter.VAR_POSITIONAL
        }


def _gym_spec(gym_id: str) -> gym.envs.registration.EnvSpec:
    """gymnasium's spec of ``gym_id``, importing ``module`` first for ``"module:EnvId"``."""
    module, _, env_id = gym_id.rpartition(":")
    how = (
        f"register it with gymnasium.register(id={env_id!r}, entry_point='my_module:MyEnv') in "
        f"a module and pass 'my_module:{env_id}' (gymnasium imports my_module first)"
    )
    if module:
        try:
            importlib.import_module(module)
        except ImportError as e:
            raise ValueError(
                f"Unknown environment {gym_id!r}: cannot import module {module!r} ({e}); "
                f"put it on sys.path, or {how}."
            ) from None
        except Exception as e:  # the user's module fails while importing
            raise ValueError(
                f"Environment {gym_id!r}: importing module {module!r} failed: "
                f"{type(e).__name__}: {e}"
            ) from None
    register_envs()
    try:
        return gym.spec(env_id)
    except gym.error.Error as err:
        known = sorted(list(ENVS) + [e.gym_id for e in ENVS.values()] + list(USER_ENVS))
        raise ValueError(
            f"Unknown environment {gym_id!r}: not one of {known} nor a registered gymnasium id "
            f"({err}); {how}."
        ) from None


def gym_entry(
    gym_id: str,
    *,
    name: str | None = None,
    cost: str | None = None,
    state_names: tuple[str, ...] = (),
) -> GymEntry:
    """A :class:`GymEntry` for any gymnasium id (checked with gymnasium, not registered here).

    Args:
        gym_id: a gymnasium id, ``"module:EnvId"`` to import ``module`` (which registers the
            env) first.

    Keyword Args:
        name: short name (default: ``gym_id``).
        cost: ``"module:function"`` of a batched torch cost ``cost(obs, action, next_obs)``.
        state_names: names of the observation's dims (optional).

    Raises:
        ValueError: gymnasium does not know ``gym_id`` (the message says how to register it).

    Examples:
        >>> entry = gym_entry("Pendulum-v1")
        >>> entry.name, entry.max_episode_steps, entry.cost_fn_path
        ('Pendulum-v1', 200, '')
    """
    spec = _gym_spec(gym_id)
    entry_point = spec.entry_point
    if not isinstance(entry_point, str):
        entry_point = f"{entry_point.__module__}:{entry_point.__qualname__}"
    if cost is not None and (cost.count(":") != 1 or not all(cost.split(":"))):
        raise ValueError(f"cost must be 'module:function', got {cost!r}.")
    return GymEntry(
        name or gym_id,
        gym_id,
        entry_point,
        cost or "",
        spec.max_episode_steps,
        tuple(state_names),
    )


def register_env(
    gym_id: str,
    *,
    name: str | None = None,
    cost: str | None = None,
    state_names: tuple[str, ...] = (),
) -> GymEntry:
    """Make a gymnasium environment known by ``name`` (default ``gym_id``), with a torch cost.

    Afterwards ``get_entry(name)`` / ``make_env(name, ...)`` find it and
    ``get_entry(name).cost_fn()`` imports the cost. Registering the same entry again is a no-op.

    Raises:
        ValueError: ``name`` is a shipped env or already registered differently, or gymnasium
            does not know ``gym_id``.

    Examples:
        >>> entry = register_env("Pendulum-v1", name="pendulum_doc", state_names=("cos", "sin", "omega"))
        >>> get_entry("pendulum_doc").state_names
        ('cos', 'sin', 'omega')
        >>> _ = USER_ENVS.pop("pendulum_doc")  # leave the registry as it was
    """
    entry = gym_entry(gym_id, name=name, cost=cost, state_names=state_names)
    if entry.name in ENVS:
        raise ValueError(f"{entry.name!r} is a shipped environment; pick another name.")
    if USER_ENVS.get(entry.name, entry) != entry:
        raise ValueError(
            f"{entry.name!r} is already registered as {USER_ENVS[entry.name]}; pick another name."
        )
    USER_ENVS[entry.name] = entry
    return entry
