"""Simplified quadcopter (Crazyflie 2.x, "X" layout) without aerodynamic effects.

The environment of the paper's Sec. 3 ("a simulated and simplified drone/quadcopter, which
doesn't include aerodynamics effects"): 4 actions drive the speeds of the 4 rotors, 12
observations give the world-frame position and velocity, the Z-Y-X Euler angles and the
angular velocity, and the cost is the Euclidean distance between the drone and the goal
``(1, 1, 1)``. The rigid-body dynamics are plain Python floats (no physics engine); the
constants are those of gym-pybullet-drones' ``cf2x`` model. See ``docs/envs/drone.md``.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from typing import Any

import gymnasium as gym
import numpy as np
import torch

from torchrl_recon.envs._validation import validate_action

__all__ = [
    "DroneEnv",
    "drone_cost",
    "cost_from_obs",
    "GOAL",
    "MASS",
    "GRAVITY",
    "KF",
    "KM",
    "ARM",
    "HOVER_RPM",
    "MAX_RPM",
    "PHYSICS_FREQUENCY",
]

# --- Physical constants (Crazyflie 2.x, gym-pybullet-drones ``assets/cf2x.urdf``) -----------
MASS = 0.027  # kg
IXX = 1.4e-5  # kg m^2
IYY = 1.4e-5  # kg m^2
IZZ = 2.17e-5  # kg m^2
ARM = 0.0397  # m, centre to rotor axis
ROTOR_OFFSET = ARM / math.sqrt(2.0)  # m, |x| = |y| of each rotor ("X" layout)
KF = 3.16e-10  # N / RPM^2, thrust per rotor F = KF w^2
KM = 7.94e-12  # N m / RPM^2, drag torque per rotor Q = KM w^2
THRUST_TO_WEIGHT = 2.25
GRAVITY = 9.8  # m / s^2
WEIGHT = MASS * GRAVITY  # N
HOVER_RPM = math.sqrt(WEIGHT / (4.0 * KF))  # ~14468.43 RPM
MAX_RPM = math.sqrt(THRUST_TO_WEIGHT * WEIGHT / (4.0 * KF))  # ~21702.64 RPM
PHYSICS_FREQUENCY = 240  # Hz, one semi-implicit Euler step every 1/240 s

GOAL: tuple[float, float, float] = (1.0, 1.0, 1.0)

_ENV_NAME = "Drone-v0"
_ANGULAR_VELOCITY_FRAMES = ("body", "world", "euler_rates")
_ACTION_MAPS = ("hover", "full")
_RESET_OPTION_KEYS = ("position", "velocity", "attitude", "angular_velocity")


def _as_vector3(value: Any, name: str) -> tuple[float, float, float]:
    """Return ``value`` as a tuple of 3 finite floats or raise ``ValueError`` naming it."""
    arr = np.asarray(value, dtype=np.float64)
    if arr.shape != (3,) or not np.all(np.isfinite(arr)):
        raise ValueError(f"{_ENV_NAME}: {name} must be 3 finite numbers, got {value!r}.")
    x, y, z = arr.tolist()
    return (x, y, z)


def _quaternion_from_euler(
    roll: float, pitch: float, yaw: float
) -> tuple[float, float, float, float]:
    """Quaternion ``(x, y, z, w)`` of ``R = Rz(yaw) Ry(pitch) Rx(roll)`` (pybullet convention)."""
    cr, sr = math.cos(0.5 * roll), math.sin(0.5 * roll)
    cp, sp = math.cos(0.5 * pitch), math.sin(0.5 * pitch)
    cy, sy = math.cos(0.5 * yaw), math.sin(0.5 * yaw)
    return (
        sr * cp * cy - cr * sp * sy,
        cr * sp * cy + sr * cp * sy,
        cr * cp * sy - sr * sp * cy,
        cr * cp * cy + sr * sp * sy,
    )


def cost_from_obs(obs: Any, goal: Sequence[float] = GOAL) -> Any:
    """Euclidean distance between the position ``obs[..., 0:3]`` and ``goal``.

    Works on numpy arrays (returns a numpy array / float64 scalar) and on torch tensors
    (returns a tensor, differentiable) of any leading batch shape.

    Args:
        obs: Observations of shape ``[..., 12]`` (only the first 3 entries are used).
        goal: Goal position ``(x, y, z)`` in metres.

    Returns:
        The cost, shape ``[...]``.

    Examples:
        >>> import numpy as np
        >>> float(cost_from_obs(np.zeros(12)))  # sqrt(3)
        1.7320508075688772
    """
    if isinstance(obs, torch.Tensor):
        target = torch.as_tensor(goal, dtype=obs.dtype, device=obs.device)
        return torch.linalg.vector_norm(obs[..., 0:3] - target, dim=-1)
    arr = np.asarray(obs, dtype=np.float64)
    return np.linalg.norm(arr[..., 0:3] - np.asarray(goal, dtype=np.float64), axis=-1)


def drone_cost(
    observation: torch.Tensor,
    action: torch.Tensor,
    next_observation: torch.Tensor,
    *,
    goal: Sequence[float] = GOAL,
) -> torch.Tensor:
    """Batched torch cost of Drone-v0 transitions: distance of the next position to the goal.

    Equal to ``-reward`` of :class:`DroneEnv` on real transitions (the env evaluates the
    cost on the state after the step). Pure and differentiable, so a planner can score
    imagined trajectories with it.

    Args:
        observation: Observations before the step, shape ``[..., 12]`` (unused).
        action: Actions, shape ``[..., 4]`` (unused; the cost depends on position only).
        next_observation: Observations after the step, shape ``[..., 12]``.
        goal: Goal position ``(x, y, z)`` in metres; keep the default ``(1, 1, 1)`` to match
            the environment's default goal.

    Returns:
        The cost ``||next_observation[..., 0:3] - goal||_2``, shape ``[...]``.

    Raises:
        ValueError: If ``next_observation`` does not end in 12 entries.

    Examples:
        >>> import torch
        >>> obs = torch.zeros(2, 5, 12)
        >>> next_obs = torch.zeros(2, 5, 12)
        >>> next_obs[..., 0:3] = 1.0
        >>> next_obs[0, 0, 2] = 0.0
        >>> cost = drone_cost(obs, torch.zeros(2, 5, 4), next_obs)
        >>> cost.shape
        torch.Size([2, 5])
        >>> cost[0, 0].item(), cost[1, 0].item()
        (1.0, 0.0)
    """
    if next_observation.shape[-1] != 12:
        raise ValueError(
            f"{_ENV_NAME}: next_observation must have shape [..., 12], got {tuple(next_observation.shape)}."
        )
    return cost_from_obs(next_observation, goal)


class DroneEnv(gym.Env):
    """Simplified Crazyflie 2.x quadcopter: rigid body, 4 rotors, no aerodynamics.

    Dynamics (Newton-Euler, world z up, body x forward / y left / z up, ``R = Rz Ry Rx``):
    ``m dv/dt = R (0, 0, T) - (0, 0, m g)``, ``dR/dt = R [omega]x`` and
    ``J domega/dt = tau - omega x J omega``, integrated at 240 Hz with semi-implicit Euler
    (velocity then position; body rates then an exact rotation of the attitude quaternion).
    No drag, ground effect, downwash, motor lag or noise. Rotor ``i`` sits at body
    ``(+d, -d)``, ``(-d, -d)``, ``(-d, +d)``, ``(+d, +d)`` for ``i = 0..3`` (front-right,
    back-right, back-left, front-left) with ``d = L / sqrt(2)``; thrust ``F_i = kf w_i^2``,
    drag torque ``Q_i = km w_i^2``, yaw torque ``-Q0 + Q1 - Q2 + Q3``.

    Action: ``Box(-1, 1, (4,), float32)``; entry ``i`` sets rotor ``i``'s speed in RPM,
    ``w_i = HOVER_RPM (1 + delta a_i)`` (``action_map="hover"``, default ``delta = 0.05``,
    ``a = 0`` is exact hover) or piecewise linearly ``-1 -> 0``, ``0 -> HOVER_RPM``,
    ``+1 -> MAX_RPM`` (``action_map="full"``). Finite out-of-range values are clipped; wrong
    shapes, NaN and inf raise ``ValueError``.

    Observation: ``Box(-inf, inf, (12,), float32)``, in the paper's order: position
    ``x, y, z`` (m, world), velocity ``vx, vy, vz`` (m/s, world), ``roll, pitch, yaw``
    (rad, Z-Y-X Euler angles), angular velocity (rad/s; body rates ``p, q, r`` by default,
    see ``angular_velocity_frame``).

    Reward: ``-cost`` with ``cost = ||(x, y, z) - goal||_2`` after the step (also in
    ``info["cost"]``); see :func:`drone_cost`.

    Episode: starts level and at rest at ``start_position + U(-start_noise, start_noise)^3``
    (drawn from ``self.np_random``). Terminates when ``z <= 0`` ("crash"), ``|x| > 3`` or
    ``|y| > 3`` or ``z > 4`` ("out_of_bounds"), the drone is upside down
    (``cos(roll) cos(pitch) <= 0``, "flipped"), ``|roll|`` or ``|pitch|`` exceeds the optional
    ``max_tilt`` ("tilt"), or the state is not finite ("non_finite"); the reason is in
    ``info["termination"]``. ``gymnasium.make("torchrl_recon/Drone-v0")`` truncates at 500
    steps.

    Args:
        delta: Relative rotor-speed range of ``action_map="hover"``.
        action_map: ``"hover"`` (``HOVER_RPM (1 + delta a)``) or ``"full"`` (0 to ``MAX_RPM``).
        control_frequency: Env steps per simulated second; must divide 240 (240 physics steps
            per second), e.g. 240 (default, one physics step per env step), 120, 60, 30.
        goal: Goal position of the cost, metres.
        start_position: Nominal start position, metres.
        start_noise: Half-width of the uniform noise added to each start coordinate, metres.
        angular_velocity_frame: Frame of observation entries 9-11: ``"body"`` (default, body
            rates ``p, q, r``), ``"world"`` (``R omega``) or ``"euler_rates"``
            (``d(roll, pitch, yaw)/dt``, singular at ``pitch = +-pi/2``).
        max_tilt: Optional stricter tilt limit in rad on ``|roll|`` and ``|pitch|``
            (``None``: only the upside-down rule).
        arena_half_width: Terminate when ``|x|`` or ``|y|`` exceeds this, metres.
        arena_height: Terminate when ``z`` exceeds this, metres.
        render_mode: Only ``None`` is supported (no rendering).

    Examples:
        >>> import gymnasium as gym
        >>> import numpy as np
        >>> import torchrl_recon  # registers the environments
        >>> env = gym.make("torchrl_recon/Drone-v0")
        >>> obs, info = env.reset(seed=0)
        >>> obs.shape, obs.dtype
        ((12,), dtype('float32'))
        >>> obs2, reward, terminated, truncated, info = env.step(np.zeros(4, dtype=np.float32))
        >>> bool(np.allclose(obs2, obs, atol=1e-6)), terminated, truncated  # a = 0 hovers
        (True, False, False)
        >>> bool(abs(reward + info["cost"]) < 1e-12)
        True
    """

    metadata: dict[str, Any] = {"render_modes": [], "render_fps": PHYSICS_FREQUENCY}

    def __init__(
        self,
        *,
        delta: float = 0.05,
        action_map: str = "hover",
        control_frequency: int = PHYSICS_FREQUENCY,
        goal: Sequence[float] = GOAL,
        start_position: Sequence[float] = (0.0, 0.0, 1.0),
        start_noise: float = 0.1,
        angular_velocity_frame: str = "body",
        max_tilt: float | None = None,
        arena_half_width: float = 3.0,
        arena_height: float = 4.0,
        render_mode: str | None = None,
    ) -> None:
        super().__init__()
        if render_mode is not None:
            raise ValueError(
                f"{_ENV_NAME}: render_mode {render_mode!r} is not supported; use None."
            )
        if action_map not in _ACTION_MAPS:
            raise ValueError(f"{_ENV_NAME}: action_map {action_map!r} not in {_ACTION_MAPS}.")
        if angular_velocity_frame not in _ANGULAR_VELOCITY_FRAMES:
            raise ValueError(
                f"{_ENV_NAME}: angular_velocity_frame {angular_velocity_frame!r} not in "
                f"{_ANGULAR_VELOCITY_FRAMES}."
            )
        if (
            isinstance(control_frequency, bool)
            or not isinstance(control_frequency, (int, np.integer))
            or control_frequency <= 0
            or PHYSICS_FREQUENCY % int(control_frequency) != 0
        ):
            raise ValueError(
                f"{_ENV_NAME}: control_frequency {control_frequency!r} must be a positive divisor of {PHYSICS_FREQUENCY}."
            )
        if not (math.isfinite(delta) and 0.0 <= delta <= 1.0):
            raise ValueError(f"{_ENV_NAME}: delta {delta!r} must be in [0, 1].")
        if not (math.isfinite(start_noise) and start_noise >= 0.0):
            raise ValueError(f"{_ENV_NAME}: start_noise {start_noise!r} must be finite and >= 0.")
        if max_tilt is not None and not (0.0 < max_tilt):
            raise ValueError(f"{_ENV_NAME}: max_tilt {max_tilt!r} must be positive or None.")
        if not (arena_half_width > 0.0 and arena_height > 0.0):
            raise ValueError(
                f"{_ENV_NAME}: arena_half_width {arena_half_width!r} and arena_height {arena_height!r} must be positive."
            )

        self.render_mode = render_mode
        self.delta = float(delta)
        self.action_map = action_map
        self.control_frequency = int(control_frequency)
        self.goal = _as_vector3(goal, "goal")
        self.start_position = _as_vector3(start_position, "start_position")
        self.start_noise = float(start_noise)
        self.angular_velocity_frame = angular_velocity_frame
        self.max_tilt = None if max_tilt is None else float(max_tilt)
        self.arena_half_width = float(arena_half_width)
        self.arena_height = float(arena_height)
        self.physics_steps = PHYSICS_FREQUENCY // self.control_frequency
        self.dt = 1.0 / self.control_frequency
        self.metadata = {**self.metadata, "render_fps": self.control_frequency}

        self.action_space = gym.spaces.Box(-1.0, 1.0, shape=(4,), dtype=np.float32)
        self.observation_space = gym.spaces.Box(-np.inf, np.inf, shape=(12,), dtype=np.float32)

        # State: position, velocity (world), quaternion (x, y, z, w), body rates.
        self._state: tuple[float, ...] = self._make_state(
            self.start_position, (0.0,) * 3, (0.0,) * 3, (0.0,) * 3
        )

    # ------------------------------------------------------------------ helpers
    @staticmethod
    def _make_state(
        position: Sequence[float],
        velocity: Sequence[float],
        attitude: Sequence[float],
        angular_velocity: Sequence[float],
    ) -> tuple[float, ...]:
        qx, qy, qz, qw = _quaternion_from_euler(*attitude)
        return (*position, *velocity, qx, qy, qz, qw, *angular_velocity)

    def _rotor_rpm(self, a0: float, a1: float, a2: float, a3: float) -> tuple[float, ...]:
        if self.action_map == "hover":
            k = HOVER_RPM * self.delta
            return (HOVER_RPM + k * a0, HOVER_RPM + k * a1, HOVER_RPM + k * a2, HOVER_RPM + k * a3)
        up = MAX_RPM - HOVER_RPM
        return tuple(
            HOVER_RPM * (1.0 + a) if a <= 0.0 else HOVER_RPM + up * a for a in (a0, a1, a2, a3)
        )

    def _observe(self) -> tuple[np.ndarray, float, float, float]:
        """Return (observation, R33, roll, pitch) of the current state."""
        px, py, pz, vx, vy, vz, qx, qy, qz, qw, wx, wy, wz = self._state
        r11 = 1.0 - 2.0 * (qy * qy + qz * qz)
        r21 = 2.0 * (qx * qy + qw * qz)
        r31 = 2.0 * (qx * qz - qw * qy)
        r32 = 2.0 * (qy * qz + qw * qx)
        r33 = 1.0 - 2.0 * (qx * qx + qy * qy)
        roll = math.atan2(r32, r33)
        pitch = -math.asin(-1.0 if r31 < -1.0 else (1.0 if r31 > 1.0 else r31))
        yaw = math.atan2(r21, r11)
        frame = self.angular_velocity_frame
        if frame == "body":
            o0, o1, o2 = wx, wy, wz
        elif frame == "world":
            r12 = 2.0 * (qx * qy - qw * qz)
            r13 = 2.0 * (qx * qz + qw * qy)
            r22 = 1.0 - 2.0 * (qx * qx + qz * qz)
            r23 = 2.0 * (qy * qz - qw * qx)
            o0 = r11 * wx + r12 * wy + r13 * wz
            o1 = r21 * wx + r22 * wy + r23 * wz
            o2 = r31 * wx + r32 * wy + r33 * wz
        else:  # euler_rates
            sph, cph = math.sin(roll), math.cos(roll)
            cth = math.cos(pitch)
            tth = math.tan(pitch)
            o0 = wx + (sph * wy + cph * wz) * tth
            o1 = cph * wy - sph * wz
            o2 = (sph * wy + cph * wz) / cth
        obs = np.array((px, py, pz, vx, vy, vz, roll, pitch, yaw, o0, o1, o2), dtype=np.float32)
        return obs, r33, roll, pitch

    def _cost(self) -> float:
        """The distance to the goal (inf, not an OverflowError, for a state beyond float range:
        the step then ends, out of bounds or non-finite)."""
        gx, gy, gz = self.goal
        px, py, pz = self._state[0:3]
        try:
            return math.sqrt((px - gx) ** 2 + (py - gy) ** 2 + (pz - gz) ** 2)
        except OverflowError:  # float ** raises where * would give inf
            return math.inf

    def _accelerations(
        self, a0: float, a1: float, a2: float, a3: float
    ) -> tuple[float, float, float, float]:
        """Return the thrust acceleration and the 3 body torques over the inertias of an action."""
        w0, w1, w2, w3 = self._rotor_rpm(a0, a1, a2, a3)
        w0, w1, w2, w3 = w0 * w0, w1 * w1, w2 * w2, w3 * w3
        thrust_acc = KF * (w0 + w1 + w2 + w3) / MASS
        # Body torques divided by the inertias (angular accelerations without gyroscopic term).
        ax_t = ROTOR_OFFSET * KF * (w2 + w3 - w0 - w1) / IXX
        ay_t = ROTOR_OFFSET * KF * (w1 + w2 - w0 - w3) / IYY
        az_t = KM * (w1 + w3 - w0 - w2) / IZZ
        return thrust_acc, ax_t, ay_t, az_t

    def _integrate(self, thrust_acc: float, ax_t: float, ay_t: float, az_t: float) -> None:
        """Advance ``self._state`` by ``physics_steps`` semi-implicit Euler steps of 1/240 s."""
        cx, cy, cz = (IZZ - IYY) / IXX, (IXX - IZZ) / IYY, (IYY - IXX) / IZZ
        h = 1.0 / PHYSICS_FREQUENCY
        px, py, pz, vx, vy, vz, qx, qy, qz, qw, wx, wy, wz = self._state
        for _ in range(self.physics_steps):
            # Translation: v += a h, then p += v h (semi-implicit Euler).
            vx += 2.0 * (qx * qz + qw * qy) * thrust_acc * h
            vy += 2.0 * (qy * qz - qw * qx) * thrust_acc * h
            vz += ((1.0 - 2.0 * (qx * qx + qy * qy)) * thrust_acc - GRAVITY) * h
            px += vx * h
            py += vy * h
            pz += vz * h
            # Rotation: J domega/dt = tau - omega x (J omega).
            dwx = ax_t - cx * wy * wz
            dwy = ay_t - cy * wz * wx
            dwz = az_t - cz * wx * wy
            wx += dwx * h
            wy += dwy * h
            wz += dwz * h
            # Attitude: q <- q (x) (sin(a/2) axis, cos(a/2)), a = |omega| h, then renormalise.
            n = math.sqrt(wx * wx + wy * wy + wz * wz)
            if n > 0.0:
                half = 0.5 * n * h
                s = math.sin(half) / n
                dx, dy, dz, dw = wx * s, wy * s, wz * s, math.cos(half)
                qx, qy, qz, qw = (
                    qw * dx + qx * dw + qy * dz - qz * dy,
                    qw * dy + qy * dw + qz * dx - qx * dz,
                    qw * dz + qz * dw + qx * dy - qy * dx,
                    qw * dw - qx * dx - qy * dy - qz * dz,
                )
                inv = 1.0 / math.sqrt(qx * qx + qy * qy + qz * qz + qw * qw)
                qx, qy, qz, qw = qx * inv, qy * inv, qz * inv, qw * inv
        self._state = (px, py, pz, vx, vy, vz, qx, qy, qz, qw, wx, wy, wz)

    def _termination_reason(self, r33: float, roll: float, pitch: float) -> str | None:
        """Name why the current state ends the episode, or ``None`` while it goes on."""
        px, py, pz, vx, vy, vz, qx, qy, qz, qw, wx, wy, wz = self._state
        if not math.isfinite(px + py + pz + vx + vy + vz + qx + qy + qz + qw + wx + wy + wz):
            return "non_finite"
        if pz <= 0.0:
            return "crash"
        if (
            abs(px) > self.arena_half_width
            or abs(py) > self.arena_half_width
            or pz > self.arena_height
        ):
            return "out_of_bounds"
        if r33 <= 0.0:
            return "flipped"
        if self.max_tilt is not None and (abs(roll) > self.max_tilt or abs(pitch) > self.max_tilt):
            return "tilt"
        return None

    # ---------------------------------------------------------------------- API
    def reset(
        self, *, seed: int | None = None, options: dict[str, Any] | None = None
    ) -> tuple[np.ndarray, dict[str, Any]]:
        """Start a new episode: level, at rest, near ``start_position``.

        Args:
            seed: Seed of ``self.np_random`` (start-position noise).
            options: Optional exact start state overriding the random one, with any of the
                keys ``"position"`` (m), ``"velocity"`` (m/s, world), ``"attitude"`` (roll,
                pitch, yaw in rad) and ``"angular_velocity"`` (body rates, rad/s), each 3
                numbers. Missing keys keep the default (random position, zero otherwise).

        Returns:
            The first observation and ``info`` with ``"cost"``.

        Raises:
            ValueError: On an unknown option key or a non-finite / wrongly shaped value.

        Examples:
            >>> env = DroneEnv(start_noise=0.0)
            >>> obs, info = env.reset(seed=1, options={"velocity": (0.0, 0.0, 0.5)})
            >>> obs[:6].tolist()
            [0.0, 0.0, 1.0, 0.0, 0.0, 0.5]
        """
        super().reset(seed=seed)
        options = dict(options or {})
        unknown = sorted(set(options) - set(_RESET_OPTION_KEYS))
        if unknown:
            raise ValueError(
                f"{_ENV_NAME}: unknown reset option(s) {unknown}; expected {_RESET_OPTION_KEYS}."
            )
        noise = self.np_random.uniform(-self.start_noise, self.start_noise, size=3)
        position = tuple(p + n for p, n in zip(self.start_position, noise.tolist(), strict=True))
        if "position" in options:
            position = _as_vector3(options["position"], "options['position']")
        zero = (0.0, 0.0, 0.0)
        velocity = _as_vector3(options.get("velocity", zero), "options['velocity']")
        attitude = _as_vector3(options.get("attitude", zero), "options['attitude']")
        rates = _as_vector3(options.get("angular_velocity", zero), "options['angular_velocity']")
        self._state = self._make_state(position, velocity, attitude, rates)
        obs, _, _, _ = self._observe()
        return obs, {"cost": self._cost()}

    def step(self, action: Any) -> tuple[np.ndarray, float, bool, bool, dict[str, Any]]:
        """Apply the rotor speeds of ``action`` for ``1 / control_frequency`` seconds.

        Args:
            action: 4 numbers in ``[-1, 1]`` (finite out-of-range values are clipped).

        Returns:
            ``(observation, reward, terminated, truncated, info)``; ``reward = -info["cost"]``,
            ``info["termination"]`` names the reason when ``terminated``. ``truncated`` is
            always ``False`` here (the TimeLimit wrapper of ``gymnasium.make`` truncates).

        Raises:
            ValueError: If ``action`` has the wrong shape or contains NaN or inf.
        """
        a0, a1, a2, a3 = validate_action(action, shape=(4,), env_name=_ENV_NAME).tolist()
        thrust_acc, ax_t, ay_t, az_t = self._accelerations(a0, a1, a2, a3)
        self._integrate(thrust_acc, ax_t, ay_t, az_t)
        obs, r33, roll, pitch = self._observe()
        cost = self._cost()
        info: dict[str, Any] = {"cost": cost}
        reason = self._termination_reason(r33, roll, pitch)
        if reason is not None:
            info["termination"] = reason
        return obs, -cost, reason is not None, False, info
