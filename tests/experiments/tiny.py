"""Overrides that shrink any experiment recipe to a few seconds: tiny networks, two fit steps;
and a gymnasium env whose episodes end after 3 steps, shorter than any training window."""

import uuid

TINY = [
    "models.window=3",
    "models.world_model.hidden_size=4",
    "models.world_model.dense_size=4",
    "models.uncertainty.hidden_size=4",
    "training.slice_len=6",
    "training.num_slices=2",
    "training.world_model.steps=2",
    "training.world_model.eval_every=1",
    "training.uncertainty.steps=2",
    "training.uncertainty.eval_every=1",
    "logger.backend=none",
]

SHORT_ENV = '''
import gymnasium as gym
import numpy as np
import torch


class Short(gym.Env):
    """Ends after 3 steps, like InvertedPendulum's random episodes."""

    observation_space = gym.spaces.Box(-10, 10, (2,), np.float32)
    action_space = gym.spaces.Box(-1, 1, (1,), np.float32)

    def __init__(self, **kwargs):  # TorchRL's GymEnv may pass frameskip
        super().__init__()

    def reset(self, *, seed=None, options=None):
        super().reset(seed=seed)
        self.t, self.s = 0, np.zeros(2, np.float32)
        return self.s.copy(), {}

    def step(self, action):
        self.t += 1
        self.s = (self.s + np.asarray(action, np.float32)[0]).clip(-10, 10)
        return self.s.copy(), -float(self.s[0] ** 2), self.t >= 3, False, {}


def cost(obs, action, next_obs):
    return next_obs[..., 0].pow(2)


def never(obs, action, next_obs):  # a termination rule: the env ends by its step count only
    return torch.zeros(next_obs.shape[:-1], dtype=torch.bool, device=next_obs.device)


gym.register(id="{env_id}", entry_point="{module}:Short", max_episode_steps=50)
'''


def short_env(tmp_path, monkeypatch, termination: bool = False) -> list[str]:
    """The ``env.id`` and ``env.cost`` overrides of :data:`SHORT_ENV` (and ``env.termination``
    with ``termination``), written as a fresh module under ``tmp_path`` (put on ``sys.path`` by
    pytest's ``monkeypatch``)."""
    module, env_id = f"short_env_{uuid.uuid4().hex[:8]}", f"Short{uuid.uuid4().hex[:6]}-v0"
    source = SHORT_ENV.replace("{env_id}", env_id).replace("{module}", module)
    (tmp_path / f"{module}.py").write_text(source)
    monkeypatch.syspath_prepend(str(tmp_path))
    overrides = [f"env.id={module}:{env_id}", f"env.cost={module}:cost"]
    return overrides + ([f"env.termination={module}:never"] if termination else [])
