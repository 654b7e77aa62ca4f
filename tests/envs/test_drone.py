"""Tests of the Drone-v0 environment (torchrl_recon.envs.drone)."""

from __future__ import annotations

import math
import warnings

import gymnasium as gym
import numpy as np
import pytest
import torch
from gymnasium.utils.env_checker import check_env

import torchrl_recon  # noqa: F401  (registers the environments)
from torchrl_recon.envs.drone import (
    GRAVITY,
    HOVER_RPM,
    IXX,
    IYY,
    IZZ,
    MASS,
    MAX_RPM,
    DroneEnv,
    cost_from_obs,
    drone_cost,
)

GYM_ID = "torchrl_recon/Drone-v0"
H = 1.0 / 240.0  # physics step


def _rollout(env: DroneEnv, action, steps: int) -> list[np.ndarray]:
    obs = []
    for _ in range(steps):
        o, _, terminated, _, _ = env.step(np.asarray(action, dtype=np.float32))
        assert not terminated
        obs.append(o)
    return obs


def _level_env(**kwargs) -> DroneEnv:
    env = DroneEnv(start_noise=0.0, **kwargs)
    env.reset(seed=0)
    return env


def _energy(env: DroneEnv) -> float:
    """Total mechanical energy: potential + translational + rotational kinetic, J."""
    _, _, pz, vx, vy, vz, _, _, _, _, wx, wy, wz = env._state
    return (
        MASS * GRAVITY * pz
        + 0.5 * MASS * (vx * vx + vy * vy + vz * vz)
        + 0.5 * (IXX * wx * wx + IYY * wy * wy + IZZ * wz * wz)
    )


# ------------------------------------------------------------------------ physics facts
def test_constants_match_spec() -> None:
    assert HOVER_RPM == pytest.approx(14468.43, abs=0.01)
    assert MAX_RPM == pytest.approx(21702.64, abs=0.01)


def test_hover_action_holds_state_for_500_steps() -> None:
    # Tolerance: |dp| < 1e-9 m and every other state entry within 1e-9 over 500 steps (2.08 s).
    env = DroneEnv()
    env.reset(seed=3)
    state0 = np.array(env._state)
    _rollout(env, np.zeros(4), 500)
    assert np.max(np.abs(np.array(env._state) - state0)) < 1e-9


def test_free_flight_conserves_energy() -> None:
    # No drag exists; with the rotors stopped (full map, a = -1) the body flies freely.
    # Semi-implicit Euler loses g^2 h t / 2 per unit mass (0.49 % here), so tolerance 1 % over 0.5 s;
    # the rotational energy (torque-free rigid body) is kept within 1e-3.
    env = DroneEnv(action_map="full", start_noise=0.0)
    env.reset(
        options={
            "position": (0, 0, 2),
            "velocity": (0.5, 0, 1),
            "angular_velocity": (0.3, -0.2, 1.0),
        }
    )
    e0 = _energy(env)
    w0 = np.array(env._state[10:])
    rot0 = 0.5 * float(np.sum(np.array([IXX, IYY, IZZ]) * w0**2))
    _rollout(env, -np.ones(4), 120)
    assert abs(_energy(env) / e0 - 1.0) < 1e-2
    w = np.array(env._state[10:])
    rot = 0.5 * float(np.sum(np.array([IXX, IYY, IZZ]) * w**2))
    assert abs(rot / rot0 - 1.0) < 1e-3


def test_free_fall_matches_integrator_closed_form() -> None:
    env = DroneEnv(action_map="full", start_noise=0.0)
    env.reset(options={"position": (0, 0, 1)})
    n = 60
    obs = _rollout(env, -np.ones(4), n)[-1]
    # Semi-implicit Euler with constant gravity: z_n = z0 - g h^2 n (n + 1) / 2, v_n = -g h n.
    assert obs[2] == pytest.approx(1.0 - GRAVITY * H * H * n * (n + 1) / 2, abs=1e-6)
    assert obs[5] == pytest.approx(-GRAVITY * H * n, abs=1e-6)
    assert np.allclose(obs[[0, 1, 3, 4, 6, 7, 8, 9, 10, 11]], 0.0)


def test_roll_sign_left_rotors_faster() -> None:
    # Rotors 2, 3 (+y side) faster: roll > 0 and the drone accelerates toward -y.
    env = _level_env()
    obs = _rollout(env, [0, 0, 1, 1], 24)[-1]
    assert obs[6] > 0.05 and obs[9] > 0 and obs[4] < 0
    assert abs(obs[7]) < 1e-6 and abs(obs[8]) < 1e-6


def test_pitch_sign_back_rotors_faster() -> None:
    # Rotors 1, 2 (back) faster, 0, 3 slower: pitch > 0 (nose down), accelerates toward +x.
    env = _level_env()
    obs = _rollout(env, [-1, 1, 1, -1], 24)[-1]
    assert obs[7] > 0.2 and obs[10] > 0 and obs[3] > 0
    assert abs(obs[6]) < 1e-6 and abs(obs[8]) < 1e-6


def test_yaw_sign_of_spin_directions() -> None:
    # Rotors 0, 2 (counter-clockwise) faster, 1, 3 slower: yaw < 0; pure yaw keeps x, y, roll, pitch.
    env = _level_env()
    obs = _rollout(env, [1, -1, 1, -1], 24)[-1]
    assert obs[8] < -0.1 and obs[11] < 0
    assert np.allclose(obs[[0, 1, 3, 4, 6, 7, 9, 10]], 0.0, atol=1e-9)
    obs = _rollout(_level_env(), [-1, 1, -1, 1], 24)[-1]
    assert obs[8] > 0.1


# Spec constants, written out here (not imported) so the test is an independent check of the code.
SPEC_MASS, SPEC_IXX, SPEC_IYY, SPEC_IZZ = 0.027, 1.4e-5, 1.4e-5, 2.17e-5  # kg, kg m^2
SPEC_ARM, SPEC_KF, SPEC_KM, SPEC_G = 0.0397, 3.16e-10, 7.94e-12, 9.8  # m, N/RPM^2, N m/RPM^2


@pytest.mark.parametrize(
    "action", [(0, 0, 1, 1), (-1, 1, 1, -1), (1, -1, 1, -1), (0.25, -0.75, 0.125, 0.875)]
)
def test_one_physics_step_matches_a_hand_computation_from_the_spec(action) -> None:
    """From rest, level: one 1/240 s step gives dv = h a and d(omega) = h tau / J (no gyroscopic
    term at omega = 0), with rotors at (+-L/sqrt2, +-L/sqrt2), F = kf w^2 and Q = km w^2."""
    h = 1.0 / 240.0
    hover = math.sqrt(SPEC_MASS * SPEC_G / (4 * SPEC_KF))  # RPM where the 4 thrusts hold the weight
    w2 = [(hover * (1 + 0.05 * a)) ** 2 for a in action]  # default map: hover (1 + 0.05 a)
    force = [SPEC_KF * w for w in w2]
    d = SPEC_ARM / math.sqrt(2.0)
    rotor_y = (-d, -d, +d, +d)  # front-right, back-right, back-left, front-left
    rotor_x = (+d, -d, -d, +d)
    tau_x = sum(y * f for y, f in zip(rotor_y, force, strict=True))  # r x F, F along +z
    tau_y = -sum(x * f for x, f in zip(rotor_x, force, strict=True))
    tau_z = SPEC_KM * (-w2[0] + w2[1] - w2[2] + w2[3])
    expected_rates = (h * tau_x / SPEC_IXX, h * tau_y / SPEC_IYY, h * tau_z / SPEC_IZZ)
    expected_vz = h * (sum(force) / SPEC_MASS - SPEC_G)

    env = DroneEnv(start_noise=0.0)
    env.reset(options={"position": (0, 0, 1)})
    env.step(np.asarray(action, dtype=np.float32))
    rates = env._state[10:13]
    assert rates == pytest.approx(expected_rates, rel=1e-9, abs=1e-12)
    assert env._state[5] == pytest.approx(expected_vz, rel=1e-9, abs=1e-12)
    assert env._state[3:5] == pytest.approx((0.0, 0.0), abs=1e-12)  # level: thrust along z only
    # e.g. rotors 2, 3 at +5 %: tau_x = d 2 (m g / 4)(1.05^2 - 1) = 3.81e-4 N m, 27.19 rad/s^2
    if tuple(action) == (0, 0, 1, 1):
        assert expected_rates[0] / h == pytest.approx(27.19, abs=0.01)


def test_control_frequency_groups_physics_steps() -> None:
    a = np.array([0.3, -0.2, 0.5, 0.1], dtype=np.float32)
    fast, slow = _level_env(), _level_env(control_frequency=30)
    obs_fast = _rollout(fast, a, 8)[-1]
    obs_slow = _rollout(slow, a, 1)[-1]
    assert np.array_equal(obs_fast, obs_slow)
    with pytest.raises(ValueError, match="control_frequency"):
        DroneEnv(control_frequency=7)


def test_angular_velocity_frames() -> None:
    options = {"attitude": (0.3, 0.0, 0.0), "angular_velocity": (0.0, 0.0, 1.0)}
    expected = {"body": (0, 0, 1), "world": (0, -math.sin(0.3), math.cos(0.3))}
    expected["euler_rates"] = expected["world"]  # equal at pitch = 0
    for frame, value in expected.items():
        obs, _ = DroneEnv(angular_velocity_frame=frame).reset(seed=0, options=options)
        assert np.allclose(obs[9:], value, atol=1e-6), frame
        assert obs[6] == pytest.approx(0.3, abs=1e-6)


# --------------------------------------------------------------- termination / truncation
@pytest.mark.parametrize(
    ("options", "kwargs", "reason"),
    [
        ({"position": (0, 0, 0.01), "velocity": (0, 0, -1)}, {}, "crash"),
        ({"position": (2.99, 0, 1), "velocity": (1, 0, 0)}, {}, "out_of_bounds"),
        ({"position": (0, -2.99, 1), "velocity": (0, -1, 0)}, {}, "out_of_bounds"),
        ({"position": (0, 0, 3.99), "velocity": (0, 0, 1)}, {}, "out_of_bounds"),
        ({"attitude": (1.2, 0, 0), "angular_velocity": (10, 0, 0)}, {}, "flipped"),
        ({"angular_velocity": (0, 2, 0)}, {"max_tilt": 0.1}, "tilt"),
    ],
)
def test_termination(options, kwargs, reason) -> None:
    env = DroneEnv(**kwargs)
    env.reset(seed=0, options=options)
    for _ in range(100):
        obs, reward, terminated, truncated, info = env.step(np.zeros(4, dtype=np.float32))
        if terminated:
            break
    assert terminated and not truncated
    assert info["termination"] == reason
    assert reward == pytest.approx(-info["cost"])


def test_termination_on_non_finite_state() -> None:
    env = _level_env()
    env._state = (math.inf,) + env._state[1:]
    _, _, terminated, _, info = env.step(np.zeros(4))
    assert terminated and info["termination"] == "non_finite"


def test_a_start_velocity_beyond_float_range_ends_the_episode_not_the_process() -> None:
    env = DroneEnv(start_noise=0.0)
    env.reset(seed=1, options={"velocity": (1e308, 0.0, 0.0)})
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)  # the float32 observation overflows
        _, reward, terminated, _, info = env.step(np.zeros(4, dtype=np.float32))
    assert terminated and reward == -math.inf and info["cost"] == math.inf


def test_truncation_at_500_steps_via_gymnasium_make() -> None:
    env = gym.make(GYM_ID)
    env.reset(seed=0)
    for t in range(1, 501):
        _, _, terminated, truncated, info = env.step(np.zeros(4, dtype=np.float32))
        assert not terminated
        assert truncated == (t == 500)
        assert "termination" not in info


# ------------------------------------------------------------------- gymnasium API
def test_check_env_passes() -> None:
    env = gym.make(GYM_ID).unwrapped
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        check_env(env)
    other = [w for w in caught if "infinity" not in str(w.message)]
    assert not other, [str(w.message) for w in other]


def test_same_seed_same_trajectory() -> None:
    actions = np.random.default_rng(0).uniform(-1, 1, size=(100, 4)).astype(np.float32)

    def run(seed: int) -> np.ndarray:
        env = gym.make(GYM_ID)
        obs, _ = env.reset(seed=seed)
        traj = [obs]
        for a in actions:
            obs, _, terminated, _, _ = env.step(a)
            traj.append(obs)
            if terminated:
                break
        return np.stack(traj)

    a, b, c = run(7), run(7), run(8)
    assert np.array_equal(a, b)
    assert not np.array_equal(a[0], c[0])
    assert np.all(np.abs(a[0, :3] - (0.0, 0.0, 1.0)) <= 0.1)


def test_reset_rejects_unknown_option() -> None:
    with pytest.raises(ValueError, match="unknown reset option"):
        DroneEnv().reset(options={"pos": (0, 0, 1)})


def test_unknown_keyword_raises_type_error() -> None:
    with pytest.raises(TypeError):
        DroneEnv(drag=True)


# ----------------------------------------------------------------------- torch cost
def test_torch_cost_equals_negative_reward_on_real_transitions() -> None:
    env = gym.make(GYM_ID)
    obs, _ = env.reset(seed=1)
    rng = np.random.default_rng(1)
    o, a, o2, r = [], [], [], []
    for _ in range(200):
        act = rng.uniform(-1, 1, size=4).astype(np.float32)
        nxt, reward, terminated, truncated, info = env.step(act)
        o.append(obs), a.append(act), o2.append(nxt), r.append(reward)
        obs = nxt
        if terminated or truncated:
            obs, _ = env.reset()
    batch = [torch.as_tensor(np.stack(x)).reshape(4, 50, -1) for x in (o, a, o2)]
    cost = drone_cost(*batch)
    assert cost.shape == (4, 50)
    expected = -torch.as_tensor(r, dtype=torch.float64).reshape(4, 50)
    torch.testing.assert_close(cost.double(), expected, atol=1e-5, rtol=0)
    np.testing.assert_allclose(cost_from_obs(np.stack(o2)), -np.array(r), atol=1e-5)


def test_torch_cost_is_differentiable() -> None:
    next_obs = torch.zeros(3, 12, requires_grad=True)
    cost = drone_cost(torch.zeros(3, 12), torch.zeros(3, 4), next_obs)
    cost.sum().backward()
    expected = -torch.ones(3, 3) / math.sqrt(3.0)
    torch.testing.assert_close(next_obs.grad[:, :3], expected)
    assert torch.all(next_obs.grad[:, 3:] == 0)


# ----------------------------------------------------------------------- bad input
@pytest.mark.parametrize(
    ("action", "match"),
    [
        (np.zeros(3), "shape"),
        (np.zeros(5), "shape"),
        (np.array([0.0, np.nan, 0.0, 0.0]), "nan"),
        (np.array([0.0, 0.0, np.inf, 0.0]), "inf"),
        (np.array([-np.inf, 0.0, 0.0, 0.0]), "inf"),
    ],
)
def test_bad_action_raises(action, match) -> None:
    env = _level_env()
    with pytest.raises(ValueError, match=match):
        env.step(action)


def test_out_of_range_action_is_clipped() -> None:
    clipped = _rollout(_level_env(), [1.0, -1.0, 1.0, 0.5], 5)[-1]
    raw = _rollout(_level_env(), [7.0, -3.0, 1.5, 0.5], 5)[-1]
    assert np.array_equal(clipped, raw)
