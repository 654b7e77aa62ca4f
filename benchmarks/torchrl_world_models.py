"""ms per plan on a TorchRL world model: TorchRL's CEMPlanner over a WorldModelEnv with the
UncertaintyPenalty transform, against the library's CEMPlanner on the same model (one batched
rollout per iteration), same K, H, iterations and elites, u in both (reconstruction, T = 4).

Two models at Pendulum-v1's sizes (N = 3, M = 1): a TorchRL ``WorldModel`` (MLP dynamics and
reward head, 64 units) through ``PlanningModel.from_torchrl``, and our LSTM world model (32
units) as ``LSTMWorldModelModule`` against ``PlanningModel`` over the LSTM itself.

Run: python benchmarks/torchrl_world_models.py [--candidates 100 1000] [--horizon 15]
     [--iterations 3] [--elites 10] [--repeats 5] [--threads 1]
Prints one row per model and K, then ``speed-up (<model>, K=<K>): X.Xx`` lines.
"""

from __future__ import annotations

import argparse

import torch
from _common import parse_args, setup_done
from tensordict import TensorDict
from tensordict.nn import TensorDictModule
from torch import nn
from torchrl.data import Composite, Unbounded
from torchrl.envs import GymEnv, TransformedEnv
from torchrl.modules import MLP, WorldModel
from torchrl.modules import CEMPlanner as TorchRLCEMPlanner

from torchrl_recon.envs.gym_costs import pendulum
from torchrl_recon.estimators import ReconstructionUncertainty
from torchrl_recon.modules import LSTMWorldModel
from torchrl_recon.planners import CEMPlanner, Objective, PlanningModel
from torchrl_recon.planners.torchrl_models import BatchedWorldModelEnv, LSTMWorldModelModule
from torchrl_recon.runs.timing import interleaved_median_ms
from torchrl_recon.transforms import UncertaintyPenalty

BETA, WINDOW = 0.5, 4


class Residual(nn.Module):
    """``z + MLP(z, a)``."""

    def __init__(self) -> None:
        super().__init__()
        self.net = MLP(in_features=4, out_features=3, num_cells=[64, 64])

    def forward(self, z: torch.Tensor, action: torch.Tensor) -> torch.Tensor:
        return z + self.net(z, action)


def mlp_world_model() -> WorldModel:
    """TorchRL's WorldModel as its docs build one: MLP dynamics and reward head."""
    encoder = TensorDictModule(nn.Identity(), in_keys=["observation"], out_keys=["latent"])
    dynamics = TensorDictModule(
        Residual(), in_keys=["latent", "action"], out_keys=[("next", "latent")]
    )
    reward = TensorDictModule(
        MLP(in_features=4, out_features=1, num_cells=[64]),
        in_keys=["latent", "action"],
        out_keys=[("next", "reward")],
    )
    return WorldModel(encoder, dynamics, reward)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--candidates", type=int, nargs="+", default=[100, 1000])
    parser.add_argument("--horizon", type=int, default=15)
    parser.add_argument("--iterations", type=int, default=3)
    parser.add_argument("--elites", type=int, default=10)
    parser.add_argument("--repeats", type=int, default=5)
    parser.add_argument("--threads", type=int, default=1)
    args = parse_args(parser)
    setup_done()
    torch.manual_seed(0)
    base = GymEnv("Pendulum-v1")
    obs, act = torch.randn(256, 3), torch.rand(256, 1) * 4 - 2
    estimator = ReconstructionUncertainty(3, 1, window=WINDOW)
    estimator.fit_normalization(obs, act)
    lstm = LSTMWorldModel(3, 1, window=WINDOW)
    lstm.fit_normalization(obs, act, obs + 0.1 * torch.randn(256, 3))
    mlp = mlp_world_model()
    for module in (estimator, lstm, mlp):
        module.requires_grad_(False)
    g = torch.Generator().manual_seed(1)
    ctx = torch.randn(WINDOW, 3, generator=g), torch.rand(WINDOW, 1, generator=g) * 4 - 2
    now = torch.randn(3, generator=g)

    def penalised(env: BatchedWorldModelEnv, obs_key: str) -> tuple[TransformedEnv, TensorDict]:
        penalty = UncertaintyPenalty(estimator, beta=BETA, obs_key=obs_key)
        return TransformedEnv(env, penalty), penalty.history(*ctx)

    # the MLP WorldModel: TorchRL's route and the library's, on the same modules
    mlp_env, history = penalised(
        BatchedWorldModelEnv(mlp, base, observation_spec=Composite(latent=Unbounded((3,)))),
        "latent",
    )
    mlp_start = TensorDict({"latent": now, "uncertainty_history": history}, [])
    mlp_model = PlanningModel.from_torchrl(mlp, env=base, uncertainty=estimator)
    # our LSTM: as LSTMWorldModelModule under WorldModelEnv, and under PlanningModel
    module = LSTMWorldModelModule(lstm, pendulum)
    lstm_env, history = penalised(module.make_env(base), "observation")
    lstm_start = module.start(*ctx, now).set("uncertainty_history", history)
    lstm_model = PlanningModel.from_env(lstm, pendulum, base, uncertainty=estimator)
    cases = {
        "TorchRL MLP WorldModel": (mlp_env, mlp_start, mlp_model),
        "LSTMWorldModel": (lstm_env, lstm_start, lstm_model),
    }
    h, iters, elites = args.horizon, args.iterations, args.elites
    print(
        f"H={h}, {iters} iterations, {elites} elites, u (reconstruction, T={WINDOW}, "
        f"beta={BETA}), median of {args.repeats} round-robin calls, ms per plan"
    )
    speedups = []
    for name, (env, start, model) in cases.items():
        for k in args.candidates:
            theirs = TorchRLCEMPlanner(env, h, iters, k, elites)
            ours = CEMPlanner(
                model,
                Objective(beta=BETA),
                horizon=h,
                num_candidates=k,
                iterations=iters,
                num_elites=elites,
            )

            def torchrl_plan(planner=theirs, td=start):
                with torch.no_grad():
                    planner(td.clone())

            def library_plan(planner=ours):
                planner.plan(*ctx, now)

            ms = interleaved_median_ms(
                {"torchrl": torchrl_plan, "library": library_plan}, args.repeats
            )
            speedups.append((name, k, ms["torchrl"] / ms["library"]))
            print(
                f"{name:24s} K={k:5d}  TorchRL CEMPlanner over WorldModelEnv {ms['torchrl']:8.1f} ms"
                f"   library CEMPlanner {ms['library']:8.1f} ms"
            )
    for name, k, ratio in speedups:
        print(f"speed-up ({name}, K={k}): {ratio:.1f}x")


if __name__ == "__main__":
    main()
