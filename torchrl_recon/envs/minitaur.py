"""Minitaur quadruped on pybullet (gymnasium 1.x), with the paper's forward-distance cost.

Built directly on ``pybullet`` in DIRECT mode with ``pybullet_data``'s Minitaur URDF, following
the reference ``MinitaurBulletEnv`` as described in ``docs/envs/minitaur.md`` (the old-``gym`` ``pybullet_envs`` package is never imported).
Each :class:`MinitaurEnv` owns one physics client and frees it in :meth:`MinitaurEnv.close`.

Observation (34 float32 dims): motor angles (0-7), motor velocities (8-15), observed motor
torques (16-23), base orientation quaternion x, y, z, w (24-27), base displacement ``x - x0``,
``y - y0`` since reset (28, 29), base height ``z`` (30) and base linear velocity in the world
frame (31-33). The torch cost :func:`minitaur_cost` reads the displacement ``obs[..., 28]``.
"""

from __future__ import annotations

import math
import os
from typing import Any

import gymnasium as gym
import numpy as np
import pybullet
import pybullet_data
import torch
from gymnasium import spaces

from torchrl_recon.envs._validation import validate_action
from torchrl_recon.envs.minitaur_motor import (
    LEG_POSITIONS,
    MOTOR_DIRECTIONS,
    MOTOR_NAMES,
    MOTOR_SPEED_LIMIT,
    NUM_MOTORS,
    OBSERVED_TORQUE_LIMIT,
    OVERHEAT_SHUTDOWN_TIME,
    OVERHEAT_SHUTDOWN_TORQUE,
    MotorModel,
    leg_to_motor_angles,
)

__all__ = ["MinitaurEnv", "minitaur_cost", "OBS_DIM", "ACT_DIM", "X_DISPLACEMENT_INDEX"]

OBS_DIM = 34
ACT_DIM = 8
#: Index of ``x - x0`` (forward displacement since reset) in the observation.
X_DISPLACEMENT_INDEX = 28

ACTION_MODES = ("leg", "pwm")
COST_FORMS = ("signed", "squared")

TIME_STEP = 0.002  # s per physics step (0.01 / 5)
ACTION_REPEAT = 5  # physics steps per env step -> 100 Hz control
NUM_SOLVER_ITERATIONS = 60  # 300 / 5
SETTLE_STEPS = 100
INIT_POSITION = (0.0, 0.0, 0.2)
INIT_ORIENTATION = (0.0, 0.0, 0.0, 1.0)
KNEE_ANGLE = -2.1834
KNEE_CONSTRAINT_POINT_RIGHT = (0.0, 0.005, 0.2)
KNEE_CONSTRAINT_POINT_LEFT = (0.0, 0.01, 0.2)
FALL_UP_Z = 0.85  # world-z component of the base's up axis below which the robot has fallen
FALL_HEIGHT = 0.13  # m, base height below which the robot has fallen ("leg" mode only)
ENERGY_WEIGHT = 0.005  # reference reward: forward - 0.005 * |tau . dq| * dt
OBSERVATION_EPS = 0.01
_F32_MAX = float(np.finfo(np.float32).max)
_OVERHEAT_STEPS = round(OVERHEAT_SHUTDOWN_TIME / TIME_STEP)


def _check_cost(cost: str) -> str:
    if cost not in COST_FORMS:
        raise ValueError(f"Minitaur: cost={cost!r} is not supported; expected one of {COST_FORMS}.")
    return cost


def minitaur_cost(
    observation: torch.Tensor,
    action: torch.Tensor,
    next_observation: torch.Tensor,
    *,
    cost: str = "signed",
) -> torch.Tensor:
    """Per-step Minitaur cost from (predicted) observations; equals ``-reward`` of the env.

    With ``d = next_observation[..., 28]`` (forward displacement ``x - x0`` since reset) the
    cost is ``-d * |d|`` (``cost="signed"``, default: only forward travel lowers it) or the
    paper-literal ``-d ** 2`` (``cost="squared"``: travel in either direction lowers it).
    ``observation`` and ``action`` are accepted for the common cost signature and not used.

    Args:
        observation: Observations before the step, shape ``[..., 34]``.
        action: Actions, shape ``[..., 8]``.
        next_observation: Observations after the step, shape ``[..., 34]``.
        cost: ``"signed"`` or ``"squared"``.

    Returns:
        The cost, shape ``[...]`` (differentiable with respect to ``next_observation``).

    Raises:
        ValueError: If ``cost`` is unknown or ``next_observation`` has no 34-dim last axis.

    Examples:
        >>> import torch
        >>> next_obs = torch.zeros(2, 34)
        >>> next_obs[:, 28] = torch.tensor([0.5, -0.5])
        >>> minitaur_cost(torch.zeros(2, 34), torch.zeros(2, 8), next_obs)
        tensor([-0.2500,  0.2500])
        >>> minitaur_cost(torch.zeros(2, 34), torch.zeros(2, 8), next_obs, cost="squared")
        tensor([-0.2500, -0.2500])
    """
    _check_cost(cost)
    if next_observation.shape[-1:] != (OBS_DIM,):
        raise ValueError(
            f"Minitaur: next_observation has shape {tuple(next_observation.shape)}, "
            f"expected [..., {OBS_DIM}]."
        )
    d = next_observation[..., X_DISPLACEMENT_INDEX]
    if cost == "signed":
        return -d * d.abs()
    return -d * d


def _observation_bounds() -> tuple[np.ndarray, np.ndarray]:
    # Motor angles are not wrapped and leave the reference's +-pi: a sustained extreme leg
    # command tracks q* = 3.53 rad (measured up to 3.99 rad) and PWM mode winds motors through
    # whole turns (measured -20 to 14 rad in 500 random steps), so dims 0-7 are unbounded.
    high = np.concatenate(
        [
            np.full(NUM_MOTORS, _F32_MAX),
            np.full(NUM_MOTORS, MOTOR_SPEED_LIMIT + OBSERVATION_EPS),
            np.full(NUM_MOTORS, OBSERVED_TORQUE_LIMIT + OBSERVATION_EPS),
            np.full(4, 1.0 + OBSERVATION_EPS),
            np.full(OBS_DIM - 28, _F32_MAX),
        ]
    ).astype(np.float32)
    return -high, high


class MinitaurEnv(gym.Env[np.ndarray, np.ndarray]):
    """Ghost Robotics Minitaur quadruped walking forward on a plane (pybullet, DIRECT mode).

    Physics as the reference ``MinitaurBulletEnv``: dt = 2 ms, 60 solver iterations, gravity
    -10, accurate DC-motor model with overheat protection, 5 physics steps per env step
    (100 Hz), hard reset with a 100-step settle at motor angle pi/2. Reset is deterministic
    (no noise, randomiser off unless ``randomize_dynamics=True``), so the same actions give a
    bit-identical trajectory. The episode ends (``terminated``) when the robot falls; the
    500-step time limit comes from gymnasium's ``TimeLimit`` (registered id
    ``torchrl_recon/Minitaur-v0``).

    Args:
        action_mode: ``"leg"`` (default): 4 leg extensions + 4 leg swings in ``[-1, 1]``,
            mapped to desired motor angles tracked by the motor model's PD law. ``"pwm"``:
            the 8 motor duty cycles (raw torque commands) in ``[-1, 1]``.
        cost: ``"signed"`` (default) ``-(x - x0)|x - x0|`` or ``"squared"`` ``-(x - x0)^2``;
            the reward is ``-cost``.
        self_collision: Enable self-collision of the robot's links (reference default; turning
            it off is about 1.4-1.9x faster).
        motor_kp: Proportional gain of the position-mode duty-cycle law (1/rad).
        motor_kd: Derivative gain of the position-mode duty-cycle law (s/rad).
        motor_overheat_protection: Disable a motor for the rest of the episode after more than
            1 s of consecutive applied torque above 2.45 N m.
        distance_limit: Terminate when the planar distance from the origin exceeds this (m).
        randomize_dynamics: Randomise masses, battery voltage, motor damping and foot friction
            at every reset (reference randomiser ranges, drawn from ``self.np_random``).
        render_mode: ``None`` or ``"rgb_array"`` (software renderer).
        render_size: ``(width, height)`` of rendered frames.

    Raises:
        ValueError: On an unknown ``action_mode``, ``cost`` or ``render_mode``.

    Examples:
        >>> import numpy as np
        >>> env = MinitaurEnv(self_collision=False)
        >>> obs, info = env.reset(seed=0)
        >>> obs.shape, obs.dtype
        ((34,), dtype('float32'))
        >>> obs, reward, terminated, truncated, info = env.step(np.zeros(8, dtype=np.float32))
        >>> bool(terminated), sorted(info)
        (False, ['forward_progress', 'reference_reward'])
        >>> env.close()
    """

    metadata = {"render_modes": ["rgb_array"], "render_fps": int(1.0 / (TIME_STEP * ACTION_REPEAT))}

    def __init__(
        self,
        *,
        action_mode: str = "leg",
        cost: str = "signed",
        self_collision: bool = True,
        motor_kp: float = 1.0,
        motor_kd: float = 0.02,
        motor_overheat_protection: bool = True,
        distance_limit: float = math.inf,
        randomize_dynamics: bool = False,
        render_mode: str | None = None,
        render_size: tuple[int, int] = (320, 240),
    ) -> None:
        if action_mode not in ACTION_MODES:
            raise ValueError(
                f"Minitaur: action_mode={action_mode!r} is not supported; expected one of {ACTION_MODES}."
            )
        if render_mode is not None and render_mode not in self.metadata["render_modes"]:
            raise ValueError(
                f"Minitaur: render_mode={render_mode!r} is not supported; expected None or 'rgb_array'."
            )
        self.action_mode = action_mode
        self.cost = _check_cost(cost)
        self.self_collision = bool(self_collision)
        self.motor_overheat_protection = bool(motor_overheat_protection)
        self.distance_limit = float(distance_limit)
        self.randomize_dynamics = bool(randomize_dynamics)
        self.render_mode = render_mode
        self.render_size = (int(render_size[0]), int(render_size[1]))
        self._kp = float(motor_kp)
        self._kd = float(motor_kd)
        self._motor = MotorModel(kp=self._kp, kd=self._kd)

        self.action_space = spaces.Box(-1.0, 1.0, (ACT_DIM,), dtype=np.float32)
        low, high = _observation_bounds()
        self.observation_space = spaces.Box(low, high, dtype=np.float32)

        self._data_path = pybullet_data.getDataPath()
        self._robot: int | None = None
        self._client: int | None = pybullet.connect(pybullet.DIRECT)
        if self._client < 0:
            self._client = None
            raise RuntimeError("Minitaur: could not connect a pybullet DIRECT client.")
        self._link_groups: dict[str, list[int]] = {"motor": [], "leg": [], "foot": []}
        self._motor_ids: list[int] = []
        self._origin = np.zeros(3)
        self._last_position = np.zeros(3)
        self._observed_torque = np.zeros(NUM_MOTORS)
        self._overheat_counter = np.zeros(NUM_MOTORS, dtype=np.int64)
        self._motor_enabled = np.ones(NUM_MOTORS, dtype=bool)
        self._velocities = np.zeros(NUM_MOTORS)

    # ------------------------------------------------------------------ test / debug hooks
    @property
    def client_id(self) -> int:
        """The pybullet physics client id owned by this env (for ``physicsClientId=``)."""
        return self._require_client()

    @property
    def robot_id(self) -> int:
        """The pybullet body id of the robot (valid after :meth:`reset`)."""
        if self._robot is None:
            raise RuntimeError("Minitaur: call reset() before using the robot.")
        return self._robot

    @property
    def motor_enabled(self) -> np.ndarray:
        """Which of the 8 motors are still enabled (overheat protection), a copy."""
        return self._motor_enabled.copy()

    def _require_client(self) -> int:
        if self._client is None:
            raise RuntimeError("Minitaur: the environment is closed.")
        return self._client

    # ------------------------------------------------------------------ gymnasium API
    def reset(
        self, *, seed: int | None = None, options: dict[str, Any] | None = None
    ) -> tuple[np.ndarray, dict[str, Any]]:
        """Hard-reset the world: reload plane and robot, set the start pose and settle.

        Args:
            seed: Seeds ``self.np_random`` (used only by ``randomize_dynamics``).
            options: Unused.

        Returns:
            The first observation and an info dict with zero ``forward_progress`` and
            ``reference_reward``.
        """
        super().reset(seed=seed)
        cid = self._require_client()
        pybullet.resetSimulation(physicsClientId=cid)
        pybullet.setPhysicsEngineParameter(
            numSolverIterations=NUM_SOLVER_ITERATIONS, physicsClientId=cid
        )
        pybullet.setTimeStep(TIME_STEP, physicsClientId=cid)
        pybullet.loadURDF(os.path.join(self._data_path, "plane.urdf"), physicsClientId=cid)
        pybullet.setGravity(0, 0, -10, physicsClientId=cid)
        flags = pybullet.URDF_USE_SELF_COLLISION if self.self_collision else 0
        self._robot = pybullet.loadURDF(
            os.path.join(self._data_path, "quadruped", "minitaur.urdf"),
            INIT_POSITION,
            INIT_ORIENTATION,
            flags=flags,
            physicsClientId=cid,
        )
        self._setup_robot(cid)
        self._motor = MotorModel(kp=self._kp, kd=self._kd)
        if self.randomize_dynamics:
            self._randomize(cid)
        self._overheat_counter[:] = 0
        self._motor_enabled[:] = True
        settle_command = np.full(NUM_MOTORS, math.pi / 2.0)
        for _ in range(SETTLE_STEPS):
            self._apply(settle_command, pwm=False)
            pybullet.stepSimulation(physicsClientId=cid)
        position, _ = pybullet.getBasePositionAndOrientation(self._robot, physicsClientId=cid)
        self._origin = np.array(position)
        self._last_position = self._origin.copy()
        obs, _ = self._observe()
        return obs, {"forward_progress": 0.0, "reference_reward": 0.0}

    def step(self, action: np.ndarray) -> tuple[np.ndarray, float, bool, bool, dict[str, Any]]:
        """Apply one action for 0.01 s (5 physics steps).

        Args:
            action: Shape ``[8]`` in ``[-1, 1]``; finite out-of-range values are clipped.

        Returns:
            ``(observation, reward, terminated, truncated, info)``; ``reward = -cost``,
            ``truncated`` is always False (the TimeLimit wrapper truncates), ``info`` holds
            ``forward_progress`` (``x_t - x_(t-1)``) and ``reference_reward`` (the reference
            env's ``forward - 0.005 |tau . dq| dt``).

        Raises:
            ValueError: On a wrong action shape or a NaN/inf entry.
        """
        cid = self._require_client()
        if self._robot is None:
            raise RuntimeError("Minitaur: call reset() before step().")
        a = validate_action(action, shape=(ACT_DIM,), env_name="Minitaur")
        pwm = self.action_mode == "pwm"
        command = a if pwm else leg_to_motor_angles(a)
        for _ in range(ACTION_REPEAT):
            self._apply(command, pwm=pwm)
            pybullet.stepSimulation(physicsClientId=cid)
        obs, (position, up_z) = self._observe()

        finite = bool(np.all(np.isfinite(obs)) and np.all(np.isfinite(position)))
        if not finite:
            obs = np.nan_to_num(obs, nan=0.0, posinf=_F32_MAX, neginf=-_F32_MAX)
            position = np.nan_to_num(position)
        forward = float(position[0] - self._last_position[0])
        self._last_position = position
        energy = abs(float(np.dot(self._observed_torque, self._velocities))) * TIME_STEP
        info = {
            "forward_progress": forward,
            "reference_reward": forward - ENERGY_WEIGHT * energy,
        }
        d = obs[X_DISPLACEMENT_INDEX]  # float32, same arithmetic as minitaur_cost on float32
        reward = float(d * abs(d)) if self.cost == "signed" else float(d * d)

        fallen = up_z < FALL_UP_Z or (self.action_mode == "leg" and position[2] < FALL_HEIGHT)
        too_far = math.hypot(position[0], position[1]) > self.distance_limit
        terminated = bool(fallen or too_far or not finite)
        return obs, reward, terminated, False, info

    def render(self) -> np.ndarray | None:
        """Return an RGB frame ``[height, width, 3]`` (uint8) when ``render_mode="rgb_array"``."""
        if self.render_mode != "rgb_array":
            return None
        cid = self._require_client()
        target = [0.0, 0.0, 0.0]
        if self._robot is not None:
            target = list(
                pybullet.getBasePositionAndOrientation(self._robot, physicsClientId=cid)[0]
            )
        width, height = self.render_size
        view = pybullet.computeViewMatrixFromYawPitchRoll(
            cameraTargetPosition=target,
            distance=1.0,
            yaw=0,
            pitch=-30,
            roll=0,
            upAxisIndex=2,
            physicsClientId=cid,
        )
        proj = pybullet.computeProjectionMatrixFOV(
            fov=60, aspect=width / height, nearVal=0.1, farVal=100.0, physicsClientId=cid
        )
        _, _, pixels, _, _ = pybullet.getCameraImage(
            width,
            height,
            viewMatrix=view,
            projectionMatrix=proj,
            renderer=pybullet.ER_TINY_RENDERER,
            physicsClientId=cid,
        )
        return np.asarray(pixels, dtype=np.uint8).reshape(height, width, 4)[:, :, :3].copy()

    def close(self) -> None:
        """Disconnect this env's physics client (idempotent)."""
        client = getattr(self, "_client", None)
        self._client, self._robot = None, None
        if client is not None and pybullet.isConnected(physicsClientId=client):
            pybullet.disconnect(physicsClientId=client)
        super().close()

    def __del__(self) -> None:
        try:
            self.close()
        except Exception:  # e.g. during interpreter shutdown; nothing to report to
            pass

    # ------------------------------------------------------------------ internals
    def _setup_robot(self, cid: int) -> None:
        """Name map, closed-chain constraints, start pose and free knees (spec sections 3-4)."""
        robot = self._robot
        joint_ids: dict[str, int] = {}
        self._link_groups = {"motor": [], "leg": [], "foot": []}
        for i in range(pybullet.getNumJoints(robot, physicsClientId=cid)):
            info = pybullet.getJointInfo(robot, i, physicsClientId=cid)
            joint_ids[info[1].decode("utf-8")] = i
            link_name = info[12].decode("utf-8")
            if link_name.startswith("motor_"):
                self._link_groups["motor"].append(i)
            elif "_leg_" in link_name:
                self._link_groups["leg"].append(i)
                if link_name.startswith("lower_leg_"):
                    self._link_groups["foot"].append(i)
        self._motor_ids = [joint_ids[name] for name in MOTOR_NAMES]
        for leg, position in enumerate(LEG_POSITIONS):
            for side, k in (("L", 2 * leg), ("R", 2 * leg + 1)):
                direction = MOTOR_DIRECTIONS[k]
                pybullet.resetJointState(
                    robot,
                    joint_ids[f"motor_{position}{side}_joint"],
                    direction * math.pi / 2.0,
                    targetVelocity=0,
                    physicsClientId=cid,
                )
                pybullet.resetJointState(
                    robot,
                    joint_ids[f"knee_{position}{side}_link"],
                    direction * KNEE_ANGLE,
                    targetVelocity=0,
                    physicsClientId=cid,
                )
            pybullet.createConstraint(
                robot,
                joint_ids[f"knee_{position}R_link"],
                robot,
                joint_ids[f"knee_{position}L_link"],
                pybullet.JOINT_POINT2POINT,
                [0, 0, 0],
                KNEE_CONSTRAINT_POINT_RIGHT,
                KNEE_CONSTRAINT_POINT_LEFT,
                physicsClientId=cid,
            )
            # Disable pybullet's built-in velocity motors: motors get explicit torques, knees are free.
            free = [
                joint_ids[f"{kind}_{position}{side}_{suffix}"]
                for kind, suffix in (("motor", "joint"), ("knee", "link"))
                for side in ("L", "R")
            ]
            pybullet.setJointMotorControlArray(
                robot,
                free,
                pybullet.VELOCITY_CONTROL,
                targetVelocities=[0.0] * 4,
                forces=[0.0] * 4,
                physicsClientId=cid,
            )

    def _randomize(self, cid: int) -> None:
        """Reference randomiser ranges, drawn from ``self.np_random``."""
        rng, robot = self.np_random, self._robot
        base_mass = pybullet.getDynamicsInfo(robot, -1, physicsClientId=cid)[0]
        leg_mass = pybullet.getDynamicsInfo(
            robot, self._link_groups["leg"][0], physicsClientId=cid
        )[0]
        motor_mass = pybullet.getDynamicsInfo(
            robot, self._link_groups["motor"][0], physicsClientId=cid
        )[0]
        pybullet.changeDynamics(
            robot, -1, mass=base_mass * rng.uniform(0.8, 1.2), physicsClientId=cid
        )
        new_leg_mass = leg_mass * rng.uniform(0.8, 1.2)
        new_motor_mass = motor_mass * rng.uniform(0.8, 1.2)
        for link in self._link_groups["leg"]:
            pybullet.changeDynamics(robot, link, mass=new_leg_mass, physicsClientId=cid)
        for link in self._link_groups["motor"]:
            pybullet.changeDynamics(robot, link, mass=new_motor_mass, physicsClientId=cid)
        self._motor.voltage = float(rng.uniform(14.8, 16.8))
        self._motor.viscous_damping = float(rng.uniform(0.0, 0.01))
        friction = float(rng.uniform(0.8, 1.5))
        for link in self._link_groups["foot"]:
            pybullet.changeDynamics(robot, link, lateralFriction=friction, physicsClientId=cid)

    def _motor_state(self) -> tuple[np.ndarray, np.ndarray]:
        states = pybullet.getJointStates(self._robot, self._motor_ids, physicsClientId=self._client)
        angles = np.array([s[0] for s in states]) * MOTOR_DIRECTIONS
        velocities = np.array([s[1] for s in states]) * MOTOR_DIRECTIONS
        return angles, velocities

    def _apply(self, command: np.ndarray, *, pwm: bool) -> None:
        """One pass of the motor model: desired angles (or duty cycles) -> joint torques."""
        angles, velocities = self._motor_state()
        if pwm:
            applied, observed = self._motor.pwm_to_torque(command, velocities)
        else:
            applied, observed = self._motor.position_to_torque(command, angles, velocities)
        if self.motor_overheat_protection:
            hot = np.abs(applied) > OVERHEAT_SHUTDOWN_TORQUE
            self._overheat_counter = np.where(hot, self._overheat_counter + 1, 0)
            self._motor_enabled &= self._overheat_counter <= _OVERHEAT_STEPS
        self._observed_torque = observed
        torques = np.where(self._motor_enabled, applied * MOTOR_DIRECTIONS, 0.0)
        pybullet.setJointMotorControlArray(
            self._robot,
            self._motor_ids,
            pybullet.TORQUE_CONTROL,
            forces=torques.tolist(),
            physicsClientId=self._client,
        )

    def _observe(self) -> tuple[np.ndarray, tuple[np.ndarray, float]]:
        """Build the 34-dim observation; also return the base position and up-axis z."""
        cid = self._client
        angles, velocities = self._motor_state()
        self._velocities = velocities
        position, orientation = pybullet.getBasePositionAndOrientation(
            self._robot, physicsClientId=cid
        )
        linear_velocity, _ = pybullet.getBaseVelocity(self._robot, physicsClientId=cid)
        position = np.array(position)
        qx, qy = orientation[0], orientation[1]
        up_z = 1.0 - 2.0 * (qx * qx + qy * qy)  # R33 of the base rotation matrix
        obs = np.concatenate(
            [
                angles,
                velocities,
                self._observed_torque,
                orientation,
                [position[0] - self._origin[0], position[1] - self._origin[1], position[2]],
                linear_velocity,
            ]
        ).astype(np.float32)
        return obs, (position, up_z)
