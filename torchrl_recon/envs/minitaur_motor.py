"""Minitaur motor and leg models: the DC-motor model and the leg-space action mapping.

Re-implemented from the reference motor model described in ``docs/envs/minitaur.md``,
which documents the reference ``pybullet_envs/bullet/{motor,minitaur}.py``. Only numpy is used;
the pybullet calls live in :mod:`torchrl_recon.envs.minitaur`.
"""

from __future__ import annotations

import math

import numpy as np

NUM_MOTORS = 8
NUM_LEGS = 4

#: Motor joint names in action/observation order (front-left, back-left, front-right, back-right).
MOTOR_NAMES: tuple[str, ...] = (
    "motor_front_leftL_joint",
    "motor_front_leftR_joint",
    "motor_back_leftL_joint",
    "motor_back_leftR_joint",
    "motor_front_rightL_joint",
    "motor_front_rightR_joint",
    "motor_back_rightL_joint",
    "motor_back_rightR_joint",
)
#: Leg names, leg ``j`` owns motors ``2j`` (L) and ``2j + 1`` (R).
LEG_POSITIONS: tuple[str, ...] = ("front_left", "back_left", "front_right", "back_right")
#: Motor space value = direction x joint value (and back, by the same product).
MOTOR_DIRECTIONS = np.array([-1.0, -1.0, -1.0, -1.0, 1.0, 1.0, 1.0, 1.0])

MOTOR_VOLTAGE = 16.0  # V
MOTOR_RESISTANCE = 0.186  # ohm
MOTOR_TORQUE_CONSTANT = 0.0954  # N m / A
MOTOR_VISCOUS_DAMPING = 0.0  # N m s / rad
VOLTAGE_CLIPPING = 50.0  # V
OBSERVED_TORQUE_LIMIT = 5.7  # N m
MOTOR_SPEED_LIMIT = MOTOR_VOLTAGE / (MOTOR_VISCOUS_DAMPING + MOTOR_TORQUE_CONSTANT)  # rad/s
CURRENT_TABLE = np.array([0.0, 10.0, 20.0, 30.0, 40.0, 50.0, 60.0])  # A
TORQUE_TABLE = np.array([0.0, 1.0, 1.9, 2.45, 3.0, 3.25, 3.5])  # N m

OVERHEAT_SHUTDOWN_TORQUE = 2.45  # N m
OVERHEAT_SHUTDOWN_TIME = 1.0  # s


class MotorModel:
    """Accurate DC-motor model of the Minitaur's eight motors (vectorised over motors).

    Position mode turns a desired motor angle into a duty cycle with a PD law,
    ``pwm = kp (q* - q) - kd dq``; torque (PWM) mode takes the duty cycle directly. The duty
    cycle is clipped to ``[-1, 1]`` and converted to the torque the sensor reports and the
    (smaller, back-EMF and current-saturated) torque actually applied.

    Args:
        kp: Proportional gain of the position-mode duty-cycle law (1/rad).
        kd: Derivative gain of the position-mode duty-cycle law (s/rad).
        voltage: Supply voltage in volts.
        viscous_damping: Motor viscous damping in N m s/rad.

    Examples:
        >>> import numpy as np
        >>> model = MotorModel()
        >>> applied, observed = model.pwm_to_torque(np.ones(8), np.zeros(8))
        >>> float(applied[0]), float(observed[0])
        (3.5, 5.7)
    """

    def __init__(
        self,
        kp: float = 1.0,
        kd: float = 0.02,
        voltage: float = MOTOR_VOLTAGE,
        viscous_damping: float = MOTOR_VISCOUS_DAMPING,
    ) -> None:
        self.kp = float(kp)
        self.kd = float(kd)
        self.voltage = float(voltage)
        self.viscous_damping = float(viscous_damping)

    def position_to_torque(
        self, desired_angle: np.ndarray, angle: np.ndarray, velocity: np.ndarray
    ) -> tuple[np.ndarray, np.ndarray]:
        """Convert desired motor angles (motor space) to ``(applied, observed)`` torques.

        Args:
            desired_angle: Target motor angles in rad, shape ``[8]``.
            angle: Current motor angles in rad, shape ``[8]``.
            velocity: Current motor velocities in rad/s, shape ``[8]``.

        Returns:
            The torque to apply and the torque the sensor reports, both ``[8]`` in N m.

        Examples:
            >>> import numpy as np
            >>> applied, _ = MotorModel().position_to_torque(np.ones(8), np.ones(8), np.zeros(8))
            >>> float(np.abs(applied).max())
            0.0
        """
        pwm = self.kp * (desired_angle - angle) - self.kd * velocity
        return self.pwm_to_torque(pwm, velocity)

    def pwm_to_torque(self, pwm: np.ndarray, velocity: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Convert duty cycles (clipped to ``[-1, 1]``) to ``(applied, observed)`` torques.

        Args:
            pwm: Duty cycles, shape ``[8]``.
            velocity: Current motor velocities in rad/s, shape ``[8]``.

        Returns:
            The torque to apply and the torque the sensor reports, both ``[8]`` in N m.

        Examples:
            >>> import numpy as np
            >>> _, observed = MotorModel().pwm_to_torque(np.full(8, 0.1), np.zeros(8))
            >>> round(float(observed[0]), 4)
            0.8206
        """
        pwm = np.clip(pwm, -1.0, 1.0)
        observed = np.clip(
            MOTOR_TORQUE_CONSTANT * pwm * self.voltage / MOTOR_RESISTANCE,
            -OBSERVED_TORQUE_LIMIT,
            OBSERVED_TORQUE_LIMIT,
        )
        voltage_net = np.clip(
            pwm * self.voltage - (MOTOR_TORQUE_CONSTANT + self.viscous_damping) * velocity,
            -VOLTAGE_CLIPPING,
            VOLTAGE_CLIPPING,
        )
        current = voltage_net / MOTOR_RESISTANCE
        applied = np.sign(current) * np.interp(np.abs(current), CURRENT_TABLE, TORQUE_TABLE)
        return applied, observed


def leg_to_motor_angles(action: np.ndarray) -> np.ndarray:
    """Map a leg-model action (4 extensions, 4 swings in ``[-1, 1]``) to 8 desired motor angles.

    For motor ``k`` of leg ``j = k // 2``: ``q*_k = pi - (pi/4)(a[4 + j] + 1.5) + e_k`` with
    ``e_k = (-1)^k (pi/4) a[j]``, sign flipped again for ``k >= 4``.

    Args:
        action: Leg-model action, shape ``[8]``.

    Returns:
        Desired motor angles in rad (motor space), shape ``[8]``.

    Examples:
        >>> import numpy as np
        >>> leg_to_motor_angles(np.zeros(8)).round(4).tolist()[:2]
        [1.9635, 1.9635]
    """
    action = np.asarray(action, dtype=np.float64)
    k = np.arange(NUM_MOTORS)
    leg = k // 2
    swing = -(math.pi / 4.0) * (action[leg + NUM_LEGS] + 1.5)
    extension = np.where(k % 2 == 0, 1.0, -1.0) * (math.pi / 4.0) * action[leg]
    extension = np.where(k >= NUM_LEGS, -extension, extension)
    return math.pi + swing + extension
