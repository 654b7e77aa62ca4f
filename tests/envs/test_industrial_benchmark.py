"""Tests of the Industrial Benchmark environment against the reference specification."""

from __future__ import annotations

import json
import math
from pathlib import Path

import gymnasium
import numpy as np
import pytest
import torch
from gymnasium.utils.env_checker import check_env

import torchrl_recon  # noqa: F401  (registers the gymnasium ids)
from torchrl_recon.envs.industrial_benchmark import (
    IndustrialBenchmarkEnv,
    industrial_benchmark_cost,
)
from torchrl_recon.envs.industrial_benchmark_dynamics import (
    IndustrialBenchmarkDynamics,
    current_operational_cost,
    effective_actions,
    gs_optimum,
    gs_penalty,
    gs_transition,
    operational_cost_convolution,
)

ENV_ID = "torchrl_recon/IndustrialBenchmark-v0"
TOL = 1e-9


# The reference trajectories of industrial_benchmark_python.IDS (see docs/envs/industrial_benchmark.md),
# kept in the repo so the conformance test never depends on files outside it.
REFERENCE = Path(__file__).resolve().parents[1] / "data" / "ib_reference_trajectories.json"


@pytest.fixture(scope="module")
def reference() -> dict:
    with open(REFERENCE) as fh:
        return json.load(fh)


def _close(a: float, b: float, tol: float = TOL) -> bool:
    return abs(a - b) <= tol * max(1.0, abs(b))


def _assert_vec_close(actual, expected, what: str) -> None:
    for i, (a, b) in enumerate(zip(actual, expected, strict=True)):
        assert _close(float(a), float(b)), f"{what}[{i}]: {a!r} != {b!r}"


# --------------------------------------------------------------------------- reference replay


TRAJECTORY_NAMES = [
    "uniform_p10",
    "uniform_p50",
    "uniform_p90",
    "structured_p30",
    "nonstationary_p50",
]
HIDDEN_FLOAT_KEYS = ["coc", "oc", "fb", "ge", "ve", "hg", "hv", "he", "MC", "alpha", "c_mean"]
HIDDEN_INT_KEYS = ["gs_domain", "gs_sys_response", "gs_phi_idx"]


def test_reference_file_has_expected_trajectories(reference: dict) -> None:
    names = [t["name"] for t in reference["trajectories"]]
    assert sorted(names) == sorted(TRAJECTORY_NAMES)


@pytest.mark.parametrize("name", TRAJECTORY_NAMES)
def test_reference_mode_reproduces_trajectory(reference: dict, name: str) -> None:
    traj = next(t for t in reference["trajectories"] if t["name"] == name)
    env = IndustrialBenchmarkEnv(
        setpoint=traj["setpoint"], stationary_setpoint=traj["stationary_p"], reference_rng=True
    )
    obs, info = env.reset(seed=traj["env_seed"])
    assert obs.dtype == np.float64 and obs.shape == (6,)
    _assert_vec_close(obs, traj["reset"]["obs"], f"{name} reset obs")
    assert _close(env.dynamics.reward, traj["reset"]["reward"])
    state = env.dynamics.markov_state()
    _assert_vec_close(state["o"], traj["reset"]["o"], f"{name} reset o")
    for key in HIDDEN_FLOAT_KEYS:
        assert _close(state[key], traj["reset"][key]), f"{name} reset {key}"
    for key in HIDDEN_INT_KEYS:
        assert state[key] == traj["reset"][key], f"{name} reset {key}"

    hidden = traj["hidden"]
    for t, action in enumerate(traj["actions"]):
        obs, reward, terminated, truncated, _ = env.step(np.asarray(action, dtype=np.float64))
        assert terminated is False and truncated is False
        _assert_vec_close(obs, traj["obs"][t], f"{name} obs step {t}")
        assert _close(reward, traj["reward"][t]), (
            f"{name} reward step {t}: {reward} != {traj['reward'][t]}"
        )
        state = env.dynamics.markov_state()
        for key in HIDDEN_FLOAT_KEYS:
            assert _close(state[key], hidden[key][t]), f"{name} {key} step {t}"
        for key in HIDDEN_INT_KEYS:
            assert state[key] == hidden[key][t], f"{name} {key} step {t}"
        if not traj["stationary_p"]:
            sp = hidden["sp_gen"]
            assert (state["p_steps"], state["p_step"]) == (sp["p_steps"][t], sp["p_step"][t])
            assert _close(state["p_ch"], sp["p_ch"][t])


def test_reference_mode_through_gymnasium_make(reference: dict) -> None:
    traj = next(t for t in reference["trajectories"] if t["name"] == "uniform_p50")
    env = gymnasium.make(ENV_ID, setpoint=traj["setpoint"], reference_rng=True)
    obs, _ = env.reset(seed=traj["env_seed"])
    _assert_vec_close(obs, traj["reset"]["obs"], "reset obs")
    for t, action in enumerate(traj["actions"][:20]):
        obs, reward, *_ = env.step(np.asarray(action))
        _assert_vec_close(obs, traj["obs"][t], f"obs step {t}")
        assert _close(reward, traj["reward"][t])
    env.close()


# --------------------------------------------------------------------------- gymnasium API


@pytest.mark.parametrize("kwargs", [{}, {"reference_rng": True}, {"stationary_setpoint": False}])
def test_check_env(kwargs: dict) -> None:
    env = gymnasium.make(ENV_ID, **kwargs).unwrapped
    check_env(env)


def test_spaces_and_registration() -> None:
    env = gymnasium.make(ENV_ID)
    assert env.spec is not None and env.spec.max_episode_steps == 1000
    assert env.observation_space.shape == (6,) and env.observation_space.dtype == np.float64
    assert env.action_space.shape == (3,)
    np.testing.assert_array_equal(env.action_space.low, -1.0)
    np.testing.assert_array_equal(env.action_space.high, 1.0)
    env.close()


def test_truncation_after_1000_steps_never_terminates() -> None:
    env = gymnasium.make(ENV_ID)
    env.reset(seed=3)
    action = np.zeros(3, dtype=np.float32)
    for t in range(1000):
        _, _, terminated, truncated, _ = env.step(action)
        assert terminated is False
        assert truncated is (t == 999)
    env.close()


def _rollout(env: IndustrialBenchmarkEnv, seed: int | None, actions: np.ndarray) -> np.ndarray:
    obs, _ = env.reset(seed=seed)
    rows = [np.append(obs, np.nan)]
    for action in actions:
        obs, reward, *_ = env.step(action)
        rows.append(np.append(obs, reward))
    return np.array(rows)


def test_default_mode_same_seed_same_trajectory_different_seed_differs() -> None:
    actions = np.random.default_rng(0).uniform(-1, 1, (50, 3))
    env = IndustrialBenchmarkEnv()
    a = _rollout(env, 7, actions)
    b = _rollout(IndustrialBenchmarkEnv(), 7, actions)
    c = _rollout(env, 8, actions)
    np.testing.assert_array_equal(a, b)
    assert not np.allclose(a[:, 4:], c[:, 4:])
    # v, g, h are deterministic given the actions, whatever the seed.
    np.testing.assert_array_equal(a[:, :4], c[:, :4])
    # Unseeded resets continue the seeded generator reproducibly.
    env1, env2 = IndustrialBenchmarkEnv(), IndustrialBenchmarkEnv()
    _rollout(env1, 11, actions[:5])
    _rollout(env2, 11, actions[:5])
    np.testing.assert_array_equal(_rollout(env1, None, actions), _rollout(env2, None, actions))


def test_reference_mode_unseeded_reset_is_reproducible_after_seeded_reset() -> None:
    actions = np.zeros((5, 3))
    env1 = IndustrialBenchmarkEnv(reference_rng=True)
    env2 = IndustrialBenchmarkEnv(reference_rng=True)
    _rollout(env1, 5, actions)
    _rollout(env2, 5, actions)
    first = _rollout(env1, None, actions)
    np.testing.assert_array_equal(first, _rollout(env2, None, actions))
    assert not np.array_equal(first, _rollout(env1, None, actions))


def test_default_mode_nonstationary_setpoint_moves_within_bounds() -> None:
    env = IndustrialBenchmarkEnv(stationary_setpoint=False)
    traj = _rollout(env, 0, np.zeros((300, 3)))
    p = traj[:, 0]
    assert np.all((p >= 0.0) & (p <= 100.0))
    assert np.ptp(p) > 1.0


# --------------------------------------------------------------------------- torch cost


def test_torch_cost_equals_minus_reward_on_real_transitions() -> None:
    env = IndustrialBenchmarkEnv(setpoint=30)
    rng = np.random.default_rng(1)
    obs, _ = env.reset(seed=1)
    observations, actions, next_observations, rewards = [], [], [], []
    for _ in range(64):
        action = rng.uniform(-1, 1, 3)
        next_obs, reward, *_ = env.step(action)
        observations.append(obs)
        actions.append(action)
        next_observations.append(next_obs)
        rewards.append(reward)
        obs = next_obs
    o = torch.as_tensor(np.array(observations)).reshape(8, 8, 6)
    a = torch.as_tensor(np.array(actions)).reshape(8, 8, 3)
    n = torch.as_tensor(np.array(next_observations)).reshape(8, 8, 6).requires_grad_(True)
    cost = industrial_benchmark_cost(o, a, n)
    assert cost.shape == (8, 8) and cost.dtype == torch.float64
    torch.testing.assert_close(
        cost.detach(),
        -torch.tensor(rewards, dtype=torch.float64).reshape(8, 8),
        rtol=1e-12,
        atol=0.0,
    )
    cost.sum().backward()
    expected_grad = torch.zeros(6, dtype=torch.float64)
    expected_grad[4], expected_grad[5] = 3.0, 1.0
    torch.testing.assert_close(n.grad, expected_grad.expand(8, 8, 6))
    # Unbatched input gives a scalar.
    assert industrial_benchmark_cost(o[0, 0], a[0, 0], n[0, 0]).shape == ()


def test_torch_cost_rejects_wrong_trailing_dims() -> None:
    with pytest.raises(ValueError, match="action"):
        industrial_benchmark_cost(torch.zeros(2, 6), torch.zeros(2, 2), torch.zeros(2, 6))
    with pytest.raises(ValueError, match="next_observation"):
        industrial_benchmark_cost(torch.zeros(2, 6), torch.zeros(2, 3), torch.zeros(2, 5))


# --------------------------------------------------------------------------- bad input


@pytest.mark.parametrize(
    ("action", "match"),
    [
        (np.zeros(4), r"\(4,\)"),
        (np.zeros((2, 3)), r"\(2, 3\)"),
        (np.array([0.0, np.nan, 0.0]), "nan"),
        (np.array([np.inf, 0.0, 0.0]), "inf"),
        (np.array([0.0, 0.0, -np.inf]), "inf"),
    ],
)
def test_bad_action_raises_value_error_naming_the_value(action: np.ndarray, match: str) -> None:
    env = IndustrialBenchmarkEnv()
    env.reset(seed=0)
    with pytest.raises(ValueError, match=match):
        env.step(action)


def test_out_of_range_action_is_clipped() -> None:
    env1, env2 = IndustrialBenchmarkEnv(), IndustrialBenchmarkEnv()
    env1.reset(seed=4)
    env2.reset(seed=4)
    for raw in ([2.0, -3.0, 1.5], [-7.0, 0.5, -1.2], [0.3, 40.0, -0.2]):
        out1 = env1.step(np.array(raw))
        out2 = env2.step(np.clip(np.array(raw), -1.0, 1.0))
        np.testing.assert_array_equal(out1[0], out2[0])
        assert out1[1] == out2[1]


def test_step_before_reset_raises() -> None:
    with pytest.raises(RuntimeError, match="reset"):
        IndustrialBenchmarkEnv().step(np.zeros(3))


@pytest.mark.parametrize("setpoint", [-0.1, 100.5, float("nan"), float("inf"), -1e9])
def test_bad_setpoint_raises_value_error(setpoint: float) -> None:
    with pytest.raises(ValueError, match="setpoint"):
        IndustrialBenchmarkEnv(setpoint=setpoint)


def test_bad_setpoint_via_make_and_bad_types() -> None:
    with pytest.raises(ValueError, match="150"):
        gymnasium.make(ENV_ID, setpoint=150)
    with pytest.raises(TypeError, match="setpoint"):
        IndustrialBenchmarkEnv(setpoint="50")  # type: ignore[arg-type]
    with pytest.raises(TypeError):
        IndustrialBenchmarkEnv(set_point=50)  # type: ignore[call-arg]
    # Bounds are inclusive.
    for setpoint in (0, 100, 0.0, 100.0):
        IndustrialBenchmarkEnv(setpoint=setpoint).reset(seed=0)


# --------------------------------------------------------------------------- unit checks (§13.3)


@pytest.mark.parametrize(
    ("v", "g", "p", "ve", "ge"),
    [
        (50, 50, 50, 0.2524752475247525, 0.2524752475247525),
        (0, 100, 30, 1.0, 0.0),
        (100, 0, 30, 0.0, 1.0),
        (50, 50, 10, 0.32269503546099293, 0.09016393442622953),
    ],
)
def test_effective_actions_check_values(v: float, g: float, p: float, ve: float, ge: float) -> None:
    got_ve, got_ge = effective_actions(float(v), float(g), float(p))
    assert math.isclose(got_ve, ve, rel_tol=1e-12, abs_tol=1e-15)
    assert math.isclose(got_ge, ge, rel_tol=1e-12, abs_tol=1e-15)


def test_operational_cost_check_values() -> None:
    coc = current_operational_cost(50.0, 50.0, 50.0)
    assert math.isclose(coc, 70.10541234668786, rel_tol=1e-14)
    assert math.isclose(operational_cost_convolution([coc] * 10), 70.10471129256439, rel_tol=1e-14)
    # Delay: a single unit impulse in the history reaches oc with weights on entries 0..4 only.
    for i, w in enumerate([0.11111, 0.22222, 0.33333, 0.22222, 0.11111, 0, 0, 0, 0, 0]):
        history = [0.0] * 10
        history[i] = 1.0
        assert operational_cost_convolution(history) == w


# j: (r_opt, r_min, Pen(r_opt), Pen(-1.5), Pen(-0.5), Pen(0.5), Pen(1.5)) from spec §5.6.
PENALTY_TABLE = {
    -6: (
        -1.0,
        -1.204892996301348,
        -1.0,
        -0.7275986188154854,
        -0.5573803932786541,
        0.20985412370473194,
        1.2303496341671276,
    ),
    -5: (
        -0.9659258262890684,
        -1.1993318723919444,
        -0.9739173274539701,
        -0.6887107921193736,
        -0.5638369114090546,
        0.19985647268567389,
        1.2062029077586973,
    ),
    -4: (
        -0.8660254037844386,
        -1.1826274907236072,
        -0.8981520979821778,
        -0.5770211909165355,
        -0.5856500680925034,
        0.16740653892728574,
        1.129669430871685,
    ),
    -3: (
        -0.7071067811865477,
        -1.1547005383792515,
        -0.7798755098705804,
        -0.40486490949831533,
        -0.6275953442973958,
        0.10767833771700902,
        0.9953129543765683,
    ),
    -2: (
        -0.5000000000000004,
        -1.1153550716504106,
        -0.6301493178701001,
        -0.187663398167426,
        -0.6301493178701001,
        0.08007052097826967,
        0.805805900704893,
    ),
    -1: (
        -0.25881904510252074,
        -1.064138980767423,
        -0.46270496280167156,
        0.058093017770525446,
        -0.461903685425635,
        -0.10335070795217263,
        0.573174029546053,
    ),
    0: (
        0.25881904510252074,
        1.0,
        -0.29245331620146764,
        0.29474761499833924,
        -0.2912165302704312,
        -0.2912165302704312,
        0.29474761499833924,
    ),
    1: (
        0.25881904510252074,
        1.064138980767423,
        -0.4627049628016716,
        0.573174029546053,
        -0.1033507079521726,
        -0.461903685425635,
        0.05809301777052539,
    ),
    2: (
        0.49999999999999994,
        1.1153550716504106,
        -0.6301493178700998,
        0.8058059007048923,
        0.08007052097826983,
        -0.6301493178700998,
        -0.18766339816742544,
    ),
    3: (
        0.7071067811865475,
        1.1547005383792515,
        -0.7798755098705803,
        0.9953129543765671,
        0.10767833771700902,
        -0.6275953442973958,
        -0.4048649094983159,
    ),
    4: (
        0.8660254037844386,
        1.1826274907236072,
        -0.8981520979821778,
        1.129669430871685,
        0.16740653892728574,
        -0.5856500680925034,
        -0.5770211909165355,
    ),
    5: (
        0.9659258262890683,
        1.1993318723919442,
        -0.9739173274539698,
        1.2062029077586973,
        0.1998564726856738,
        -0.5638369114090545,
        -0.6887107921193735,
    ),
    6: (
        1.0,
        1.204892996301348,
        -1.0,
        1.2303496341671276,
        0.20985412370473194,
        -0.5573803932786541,
        -0.7275986188154854,
    ),
}


@pytest.mark.parametrize("j", sorted(PENALTY_TABLE))
def test_penalty_landscape_check_values(j: int) -> None:
    r_opt, r_min, pen_opt, *pen_at = PENALTY_TABLE[j]
    got_opt, got_min = gs_optimum(j)
    assert math.isclose(got_opt, r_opt, rel_tol=1e-12)
    assert math.isclose(got_min, r_min, rel_tol=1e-12)
    assert math.isclose(gs_penalty(j, r_opt), pen_opt, rel_tol=1e-12)
    for x, expected in zip((-1.5, -0.5, 0.5, 1.5), pen_at, strict=True):
        assert math.isclose(gs_penalty(j, x), expected, rel_tol=1e-12, abs_tol=1e-15)
    assert gs_penalty(j, 0.0) == 0.0
    assert math.isclose(gs_penalty(-j, 0.37), gs_penalty(j, -0.37), rel_tol=1e-9, abs_tol=1e-12)


def test_mis_calibration_worked_behaviour() -> None:
    state = (1, 1, 0)
    phis, responses = [], []
    for _ in range(20):
        state = gs_transition(*state, 1.0)  # held above the safe zone
        phis.append(state[2])
        responses.append(state[1])
    assert phis == [1, 2, 3, 4, 5, 6, 5, 4, 3, 2, 1, 0, -1, -2, -3, -4, -5, -6, -6, -6]
    assert responses[:5] == [1] * 5 and all(r == -1 for r in responses[5:])
    for expected_phi in (-5, -4, -3, -2, -1):  # cool-down in the safe zone
        state = gs_transition(*state, 0.0)
        assert state[2] == expected_phi and state[1] == -1
    assert gs_transition(*state, 0.0) == (1, 1, 0)  # reset at phi == 0
    # A domain change makes the response advantageous again.
    assert gs_transition(1, -1, 3, -1.0) == (-1, 1, 2)


def test_reset_check_values_p50_seed_1002() -> None:
    env = IndustrialBenchmarkEnv(setpoint=50, reference_rng=True)
    obs, _ = env.reset(seed=1002)
    s = env.dynamics.markov_state()
    expected = {
        "coc": 70.10541234668786,
        "oc": 70.10471129256439,
        "fb": 60.71428571428571,
        "ge": 0.2524752475247525,
        "ve": 0.2524752475247525,
        "he": 0.0,
        "MC": 0.0,
        "f": 22.10499805256681,
        "c": 95.66220102521062,
        "reward": -161.97719518291103,
    }
    for key, value in expected.items():
        assert _close(s[key], value, 1e-12), key
    assert s["o"] == [s["coc"]] * 10  # the internal zero step fills the whole buffer
    np.testing.assert_array_equal(obs[:4], [50.0, 50.0, 50.0, 50.0])


@pytest.mark.parametrize(
    ("p", "he", "gs"), [(10, 0.8, (1, 1, 1)), (50, 0.0, (1, 1, 0)), (90, -0.8, (-1, 1, -1))]
)
def test_initial_mis_calibration(p: float, he: float, gs: tuple[int, int, int]) -> None:
    env = IndustrialBenchmarkEnv(setpoint=p)
    env.reset(seed=0)
    s = env.dynamics.markov_state()
    assert math.isclose(s["he"], he, abs_tol=1e-12)
    assert (s["gs_domain"], s["gs_sys_response"], s["gs_phi_idx"]) == gs


def test_dynamics_rejects_unknown_rng() -> None:
    with pytest.raises(TypeError, match="rng"):
        IndustrialBenchmarkDynamics(50.0, rng=np.random)  # type: ignore[arg-type]


# --------------------------------------------------------------------------- value ranges (§9)


def test_value_ranges_default_mode() -> None:
    rng = np.random.default_rng(123)
    pen_max = 1.2303496341671276
    for setpoint, stationary in ((10, True), (90, True), (50, False)):
        env = IndustrialBenchmarkEnv(setpoint=setpoint, stationary_setpoint=stationary)
        obs, _ = env.reset(seed=setpoint)
        # Persistent pushes so the bounds and the fatigue saturation are reached.
        actions = np.repeat(rng.uniform(-1, 1, (40, 3)), 25, axis=0)
        for action in actions:
            obs, reward, *_ = env.step(action)
            s = env.dynamics.markov_state()
            assert obs in env.observation_space
            for key in ("p", "v", "g", "h"):
                assert 0.0 <= s[key] <= 100.0
            assert -1.5 <= s["he"] <= 1.5
            assert 0.0 <= s["ve"] <= 1.0 and 0.0 <= s["ge"] <= 1.0
            assert 0.0 <= s["hv"] <= 5.0 and 0.0 <= s["hg"] <= 5.0
            assert 0.0 <= s["alpha"] < 1.0
            assert 0.0 <= s["fb"] <= 300.0
            assert s["fb"] / 3.0 - 1e-12 <= s["f"] <= s["fb"] + 1e-12
            if s["fb"] == 0.0:
                assert s["f"] == 0.0
            assert 1.0 <= s["coc"] <= math.exp(8.5)
            assert s["gs_phi_idx"] in range(-6, 7)
            assert s["gs_domain"] in (-1, 1) and s["gs_sys_response"] in (-1, 1)
            assert -pen_max - 1e-9 <= s["MC"] <= 1.0 + 1e-12
            assert s["oc"] - 1e-9 <= s["c_mean"] <= s["oc"] + 25.0 * (1.0 + pen_max) + 1e-9
            assert reward == -(3.0 * s["f"] + s["c"])


def test_statistics_of_own_rng_match_reference(reference: dict) -> None:
    """§13.2 check 4: consumption noise ~ N(0, 1); fatigue saturation close to the reference."""
    traj = next(t for t in reference["trajectories"] if t["name"] == "structured_p30")
    ref_saturated = np.mean([d is not None for d in traj["hidden"]["draws"]["normal_alpha"]])
    z, saturated = [], []
    for seed in range(10):
        env = IndustrialBenchmarkEnv(setpoint=traj["setpoint"])
        env.reset(seed=seed)
        for action in traj["actions"]:
            env.step(np.asarray(action))
            s = env.dynamics.markov_state()
            z.append((s["c_mean"] - s["c"]) / (1.0 + 0.005 * s["c_mean"]))
            saturated.append(max(s["hv"], s["hg"]) == 5.0)
    assert abs(np.mean(z)) < 0.1 and abs(np.std(z) - 1.0) < 0.1
    assert abs(np.mean(saturated) - ref_saturated) < 0.15
