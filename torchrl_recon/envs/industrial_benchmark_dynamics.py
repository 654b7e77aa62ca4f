"""Pure dynamics of the Industrial Benchmark (Hein et al., 2017), reference Python semantics.

This module holds the simulator core without any gymnasium machinery: the constants, the
deterministic sub-models (effective actions, operational cost, mis-calibration / "Goldstone"
landscape) and :class:`IndustrialBenchmarkDynamics`, which advances the full state one step at a
time. It follows the reference Python implementation (the behaviour of
``industrial_benchmark_python.IDS`` at commit ``afeed69``), including the order of every random
draw, so that driving it with ``numpy.random.RandomState(seed)`` reproduces the reference
bit for bit.

The per-step hot path deliberately uses Python floats and the :mod:`math` module: numpy calls on
scalars cost about a microsecond each, which would dominate a step.
"""

from __future__ import annotations

import math
from collections import deque
from typing import Any

import numpy as np

__all__ = [
    "ACTION_TOLERANCE",
    "CONV_WEIGHTS",
    "CRC",
    "CRF",
    "CRGS",
    "GAIN_STEP",
    "GS_BOUND",
    "GS_SAFE_ZONE",
    "GS_SCALE",
    "GS_SETPOINT_DEPENDENCY",
    "GS_STEPS_PER_TURN",
    "GS_STRONGEST_PENALTY_INDEX",
    "MAX_REQUIRED_STEP",
    "SHIFT_STEP",
    "VELOCITY_STEP",
    "IndustrialBenchmarkDynamics",
    "RandomSource",
    "current_operational_cost",
    "effective_actions",
    "fatigue_base",
    "gs_penalty",
    "gs_transition",
    "operational_cost_convolution",
]

RandomSource = np.random.RandomState | np.random.Generator

# --- constants (spec §2) -------------------------------------------------------------------
MAX_REQUIRED_STEP: float = math.sin(15.0 / 180.0 * math.pi)  # m = sin(15 deg)
GS_BOUND: float = 1.5
GS_SETPOINT_DEPENDENCY: float = 0.02
GS_SCALE: float = 2.0 * GS_BOUND + 100.0 * GS_SETPOINT_DEPENDENCY  # = 5.0
VELOCITY_STEP: float = 1.0
GAIN_STEP: float = 10.0
SHIFT_STEP: float = (MAX_REQUIRED_STEP / 0.9) * 100.0 / GS_SCALE  # ~5.7515
CRF: float = 3.0  # fatigue weight in the cost
CRC: float = 1.0  # consumption weight in the cost
CRGS: float = 25.0  # mis-calibration weight in the consumption

EXP_SCALE: float = 0.1  # numpy ``exponential(0.1)``: scale = mean
ACTION_TOLERANCE: float = 0.05
FATIGUE_AMPLIFICATION: float = 1.1
FATIGUE_AMPLIFICATION_MAX: float = 5.0
FATIGUE_AMPLIFICATION_START: float = 1.2

CONV_WEIGHTS: tuple[float, ...] = (
    0.11111,
    0.22222,
    0.33333,
    0.22222,
    0.11111,
    0.0,
    0.0,
    0.0,
    0.0,
    0.0,
)
_W0, _W1, _W2, _W3, _W4 = CONV_WEIGHTS[:5]
HISTORY_LENGTH: int = 10

GS_STEPS_PER_TURN: int = 24
GS_STRONGEST_PENALTY_INDEX: int = GS_STEPS_PER_TURN // 4  # k = 6
GS_SAFE_ZONE: float = MAX_REQUIRED_STEP / 2.0  # z = m / 2

# --- normalised, linearly biased Goldstone potential (spec §2, [NLGP]) ---------------------
_U0 = math.cbrt(1.0 + math.sqrt(2.0)) / math.sqrt(3.0)
_R0 = _U0 + 1.0 / (3.0 * _U0)
_LAMBDA = 2.0 * _R0**2 - _R0**4 + 8.0 * math.sqrt(2.0 / 27.0) * _R0
NLGP_A: float = 2.0 / _LAMBDA
NLGP_B: float = 1.0 / _LAMBDA
NLGP_KAPPA: float = -8.0 * math.sqrt(2.0 / 27.0) / _LAMBDA
NLGP_QB: float = -math.sqrt(1.0 / 27.0)


def _global_minimum_radius(theta: float) -> float:
    """Radius minimising the NLGP along the ray ``theta`` (signed, spec §5.6)."""
    sin_t = math.sin(theta)
    q = NLGP_KAPPA * abs(sin_t) / (8.0 * NLGP_B)
    s = 1.0 if sin_t >= 0.0 else -1.0  # sign(sin) with sign(0) := 1
    if q <= NLGP_QB:
        u = math.cbrt(-s * q + math.sqrt(max(0.0, q * q - 1.0 / 27.0)))
        return u + 1.0 / (3.0 * u)
    return s * math.sqrt(4.0 / 3.0) * math.cos(1.0 / 3.0 * math.acos(-q * math.sqrt(27.0)))


def _penalty_parameters(j: int) -> tuple[float, float, float, float, float, float]:
    """Per-angle constants ``(ksin, |r_opt|, |r_min|, exponent, scaling, theta)`` of ``Pen_j``."""
    theta = (2 * j) * math.pi / GS_STEPS_PER_TURN
    theta = theta % (2.0 * math.pi)  # reduced to [0, 2 pi) like the reference
    r_opt = max(abs(math.sin(theta)), MAX_REQUIRED_STEP)
    if theta >= math.pi:
        r_opt = -r_opt
    r_min = _global_minimum_radius(theta)
    abs_opt, abs_min = abs(r_opt), abs(r_min)
    exponent = (2.0 - abs_opt) / (2.0 - abs_min)
    scaling = (2.0 - abs_min) / (2.0 - abs_opt) ** exponent
    return NLGP_KAPPA * math.sin(theta), abs_opt, abs_min, exponent, scaling, theta


# Index ``j + 6`` for ``j`` in -6..6.
_PENALTY_TABLE: tuple[tuple[float, float, float, float, float, float], ...] = tuple(
    _penalty_parameters(j)
    for j in range(-GS_STRONGEST_PENALTY_INDEX, GS_STRONGEST_PENALTY_INDEX + 1)
)


def gs_penalty(phi_idx: int, x: float) -> float:
    """Evaluate the mis-calibration penalty landscape ``Pen_j(x)`` (spec §5.6).

    Args:
        phi_idx: Angle index ``j`` in ``-6..6``.
        x: Effective shift ``he`` in ``[-1.5, 1.5]``.

    Returns:
        The penalty ``N(T(x), theta_j)``; the mis-calibration value is its negation ``MC = -Pen``.

    Examples:
        >>> round(gs_penalty(6, 1.0), 12)
        -1.0
        >>> gs_penalty(0, 0.0) == 0.0
        True
    """
    ksin, abs_opt, abs_min, exponent, scaling, _ = _PENALTY_TABLE[
        phi_idx + GS_STRONGEST_PENALTY_INDEX
    ]
    ax = abs(x)
    if ax <= abs_opt:
        r = x * abs_min / abs_opt
    else:
        r = (1.0 if x > 0.0 else -1.0) * (abs_min + scaling * (ax - abs_opt) ** exponent)
    rsq = r * r
    return -NLGP_A * rsq + NLGP_B * (rsq * rsq) + ksin * r


def gs_optimum(phi_idx: int) -> tuple[float, float]:
    """Return the signed ``(r_opt, r_min)`` radii of ``Pen_j`` (spec §5.6 check table).

    Args:
        phi_idx: Angle index ``j`` in ``-6..6``.

    Returns:
        The desired optimum position ``r_opt`` and the NLGP minimising radius ``r_min``.

    Examples:
        >>> r_opt, r_min = gs_optimum(6)
        >>> r_opt, round(r_min, 12)
        (1.0, 1.204892996301)
    """
    _, abs_opt, _, _, _, theta = _PENALTY_TABLE[phi_idx + GS_STRONGEST_PENALTY_INDEX]
    r_opt = -abs_opt if theta >= math.pi else abs_opt
    return r_opt, _global_minimum_radius(theta)


def gs_transition(domain: int, response: int, phi_idx: int, x: float) -> tuple[int, int, int]:
    """Advance the mis-calibration state machine by one step (spec §5.6, "Transition").

    Args:
        domain: Current domain ``delta`` (+1 / -1).
        response: Current system response ``psi`` (+1 advantageous / -1 disadvantageous).
        phi_idx: Current angle index ``phi`` in ``-6..6``.
        x: Effective shift ``he`` of this step.

    Returns:
        The new ``(domain, response, phi_idx)``.

    Examples:
        >>> gs_transition(1, 1, 5, 1.0)  # reaching |phi| = 6 turns the response disadvantageous
        (1, -1, 6)
        >>> gs_transition(1, -1, 1, 0.0)  # cool-down to 0 inside the safe zone resets the state
        (1, 1, 0)
    """
    k = GS_STRONGEST_PENALTY_INDEX
    old_domain = domain
    in_safe_zone = abs(x) <= GS_SAFE_ZONE
    sign_x = 1 if x > 0.0 else (-1 if x < 0.0 else 0)
    if not in_safe_zone:
        domain = sign_x
    if domain != old_domain:
        response = 1
    if in_safe_zone:
        phi_idx -= 1 if phi_idx > 0 else (-1 if phi_idx < 0 else 0)
    elif phi_idx != -domain * k:
        phi_idx += response * sign_x
    if abs(phi_idx) >= k:
        response = -1
        phi_idx = 2 * k - ((phi_idx + 4 * k) % (4 * k))
    if phi_idx == 0 and in_safe_zone:
        domain = 1
        response = 1
    return domain, response, phi_idx


def effective_actions(v: float, g: float, p: float) -> tuple[float, float]:
    """Effective velocity ``ve`` ("alpha") and effective gain ``ge`` ("beta") (spec §5.3).

    Args:
        v: Velocity steering in ``[0, 100]``.
        g: Gain steering in ``[0, 100]``.
        p: Setpoint in ``[0, 100]``.

    Returns:
        ``(ve, ge)``, both in ``[0, 1]``.

    Examples:
        >>> effective_actions(50.0, 50.0, 50.0)
        (0.2524752475247525, 0.2524752475247525)
    """
    a_max = 100.0 + 101.0 - p  # A(100)
    a_min = 0.0 + 101.0 - p  # A(0)
    b_0 = 0.0 + 1.0 + p  # Bf(0)
    b_100 = 100.0 + 1.0 + p  # Bf(100)
    b_g = g + 1.0 + p
    alpha_lo = (b_0 + 1.0) / a_max
    alpha_hi = (b_100 + 1.0) / a_min
    ve = ((b_g + 1.0) / (v + 101.0 - p) - alpha_lo) / (alpha_hi - alpha_lo)
    beta_lo = 1.0 / b_100
    ge = (1.0 / b_g - beta_lo) / (1.0 / b_0 - beta_lo)
    return ve, ge


def fatigue_base(v: float, g: float) -> float:
    """Fatigue base ``fb = max(0, 30000 / (5 v + 100) - 0.01 g^2)`` (spec §5.4 step 7).

    Args:
        v: Velocity steering.
        g: Gain steering.

    Returns:
        The fatigue without amplification, in ``[0, 300]``.

    Examples:
        >>> fatigue_base(50.0, 50.0)
        60.71428571428571
    """
    return max(0.0, 30000.0 / (5.0 * v + 100.0) - 0.01 * (g * g))


def current_operational_cost(p: float, v: float, g: float) -> float:
    """Undelayed operational cost ``coc = exp((2 p + 2.5 g + 4 v) / 100)`` (spec §5.5).

    Args:
        p: Setpoint.
        v: Velocity steering.
        g: Gain steering.

    Returns:
        The current operational cost, in ``[1, e^8.5]``.

    Examples:
        >>> current_operational_cost(50.0, 50.0, 50.0)
        70.10541234668786
    """
    return math.exp((2.0 * p + 2.5 * g + 4.0 * v) / 100.0)


def operational_cost_convolution(history: Any) -> float:
    """Delayed operational cost ``oc = sum_i w[i] * O[i]`` (spec §5.5; ``O[0]`` is the oldest).

    Args:
        history: The 10 most recent ``coc`` values, oldest first.

    Returns:
        The convolved cost (the weights sum to 0.99999, not 1, as in the reference).

    Examples:
        >>> operational_cost_convolution([70.10541234668786] * 10)
        70.10471129256439
    """
    o0, o1, o2, o3, o4 = history[0], history[1], history[2], history[3], history[4]
    return _W0 * o0 + _W1 * o1 + _W2 * o2 + _W3 * o3 + _W4 * o4


def _next_hidden_fatigue(hidden: float, effective: float, noise: float) -> float:
    """Next hidden fatigue ``hv`` / ``hg``: reset, amplified or smoothed noise (spec §5.4)."""
    if effective <= ACTION_TOLERANCE:
        return effective
    if hidden >= FATIGUE_AMPLIFICATION_START:
        return min(FATIGUE_AMPLIFICATION_MAX, FATIGUE_AMPLIFICATION * hidden)
    return 0.9 * hidden + noise / 3.0


class IndustrialBenchmarkDynamics:
    """Full Industrial Benchmark state and its one-step transition (reference semantics).

    Construction mirrors the reference constructor ``IDS(p, stationary_p, inital_seed)``: the
    initial state of spec §3 is set, one setpoint sequence is defined (3 random draws, even for a
    stationary setpoint) and one internal step with the zero action is executed. The state after
    construction is what an agent sees at reset.

    Random draws are taken from ``rng`` in exactly the order of spec §7. With a legacy
    ``numpy.random.RandomState(seed)`` the trajectories equal the reference's bit for bit; with a
    ``numpy.random.Generator`` the same distributions are sampled through the generator's own
    algorithms (statistically equivalent, different numbers).

    Args:
        setpoint: Setpoint ``p`` in ``[0, 100]`` (validated by the caller).
        stationary_setpoint: Keep ``p`` constant (default). ``False`` runs the reference's random
            setpoint generator (spec §5.1).
        rng: Source of randomness, a ``RandomState`` (bit-exact reference mode) or ``Generator``.

    Examples:
        >>> dyn = IndustrialBenchmarkDynamics(50.0, rng=np.random.RandomState(1002))
        >>> round(dyn.reward, 9)
        -161.977195183
        >>> reward = dyn.step(0.1, -0.2, 0.3)
        >>> [round(x, 6) for x in dyn.observation()[:4]]
        [50.0, 50.1, 48.0, 51.72546]
    """

    def __init__(
        self, setpoint: float, *, stationary_setpoint: bool = True, rng: RandomSource
    ) -> None:
        if isinstance(rng, np.random.RandomState):
            self._rand = rng.random_sample  # == legacy ``rand()``
            self._randn = rng.standard_normal  # == legacy ``randn()``
            self._randint = rng.randint
        elif isinstance(rng, np.random.Generator):
            self._rand = rng.random
            self._randn = rng.standard_normal
            self._randint = rng.integers
        else:
            raise TypeError(
                f"rng must be a numpy.random.RandomState or numpy.random.Generator, got {type(rng).__name__}."
            )
        self._exponential = rng.exponential
        self._binomial = rng.binomial
        self._normal = rng.normal

        self.stationary_setpoint = bool(stationary_setpoint)
        # Observables.
        self.p = float(setpoint)
        self.v = 50.0
        self.g = 50.0
        self.h = 50.0
        self.f = 0.0
        self.c = 0.0
        self.cost = 0.0
        self.reward = 0.0
        # Hidden state.
        self.o: deque[float] = deque([0.0] * HISTORY_LENGTH, maxlen=HISTORY_LENGTH)
        self.coc = 0.0
        self.oc = 0.0
        self.fb = 0.0
        self.hv = 0.0
        self.hg = 0.0
        self.ve = 0.0
        self.ge = 0.0
        self.he = 0.0
        self.gs_domain = 1
        self.gs_response = 1
        self.gs_phi_idx = 0
        self.mc = 0.0
        # Derived per-step quantities (diagnostics; not part of the reference state).
        self.alpha = 0.0
        self.c_mean = 0.0
        # Setpoint generator.
        self.p_steps = 0
        self.p_step = 0
        self.p_change = 0.0
        self._first_step = True

        self._define_new_sequence()
        self.step(0.0, 0.0, 0.0)

    # ------------------------------------------------------------------ setpoint (spec §5.1)
    def _define_new_sequence(self) -> None:
        self.p_steps = int(self._randint(1, 100))
        self.p_step = 0
        p_change = 2.0 * self._rand() - 1.0
        if self._rand() < 0.1:
            p_change *= 0.0
        self.p_change = p_change

    def _update_setpoint(self) -> None:
        if self.p_step == self.p_steps:
            self._define_new_sequence()
        new_p = self.p + self.p_change
        if new_p > 100.0 or new_p < 0.0:
            if self._rand() > 0.5:
                self.p_change = -self.p_change
        self.p = min(max(new_p, 0.0), 100.0)
        self.p_step += 1

    # ------------------------------------------------------------------ one step (spec §4)
    def step(self, a_v: float, a_g: float, a_h: float) -> float:
        """Apply one action and advance the state by one time step.

        Args:
            a_v: Velocity delta; clipped to ``[-1, 1]``.
            a_g: Gain delta; clipped to ``[-1, 1]``.
            a_h: Shift delta; clipped to ``[-1, 1]``.

        Returns:
            The reward ``-(3 f + c)`` of the new state.
        """
        # 1. setpoint
        if not self.stationary_setpoint:
            self._update_setpoint()
        p = self.p
        # 2.-7. the sub-models, in the reference's order of random draws
        v, g, he = self._apply_action(a_v, a_g, a_h, p)
        f = self._update_fatigue(v, g, p)
        oc = self._update_operational_cost(v, g, p)
        mc = self._update_mis_calibration(he)
        c = self._update_consumption(oc, mc)

        # 8. cost and reward
        cost = CRF * f + CRC * c
        self.cost = cost
        self.reward = -cost
        return -cost

    def _apply_action(
        self, a_v: float, a_g: float, a_h: float, p: float
    ) -> tuple[float, float, float]:
        """Clip the deltas, move ``v, g, h`` and return ``(v, g, he)`` (step 2)."""
        a_v = min(max(a_v, -1.0), 1.0)
        a_g = min(max(a_g, -1.0), 1.0)
        a_h = min(max(a_h, -1.0), 1.0)
        v = min(max(self.v + VELOCITY_STEP * a_v, 0.0), 100.0)
        g = min(max(self.g + GAIN_STEP * a_g, 0.0), 100.0)
        h = min(max(self.h + SHIFT_STEP * a_h, 0.0), 100.0)
        he = min(
            max(GS_SCALE * h / 100.0 - GS_SETPOINT_DEPENDENCY * p - GS_BOUND, -GS_BOUND), GS_BOUND
        )
        self.v, self.g, self.h, self.he = v, g, h, he
        return v, g, he

    def _fatigue_noise(self, ve: float, ge: float) -> tuple[float, float]:
        """Draw the fatigue noise ``(n_v, n_g)`` of velocity and gain (step 3, draws 1-6)."""
        e_g = self._exponential(EXP_SCALE)
        e_v = self._exponential(EXP_SCALE)
        u_g = self._rand()
        u_v = self._rand()
        b_g = float(self._binomial(1, min(max(ge, 0.001), 0.999)))
        b_v = float(self._binomial(1, min(max(ve, 0.001), 0.999)))
        n_g = 2.0 * (1.0 / (1.0 + math.exp(-e_g)) - 0.5)
        n_v = 2.0 * (1.0 / (1.0 + math.exp(-e_v)) - 0.5)
        n_g += (1.0 - n_g) * u_g * b_g * ge
        n_v += (1.0 - n_v) * u_v * b_v * ve
        return n_v, n_g

    def _update_fatigue(self, v: float, g: float, p: float) -> float:
        """Advance the hidden fatigue state and return the fatigue ``f`` (step 3, draws 1-7)."""
        ve, ge = effective_actions(v, g, p)
        n_v, n_g = self._fatigue_noise(ve, ge)
        hg = _next_hidden_fatigue(self.hg, ge, n_g)
        hv = _next_hidden_fatigue(self.hv, ve, n_v)
        if max(hv, hg) == FATIGUE_AMPLIFICATION_MAX:  # exact test, reached through the cap
            alpha = 1.0 / (1.0 + math.exp(-self._normal(2.4, 0.4)))
        else:
            alpha = max(n_v, n_g)
        fb = max(0.0, 30000.0 / (5.0 * v + 100.0) - 0.01 * (g * g))
        f = fb * (1.0 + 2.0 * alpha) / 3.0
        self.ve, self.ge, self.hv, self.hg = ve, ge, hv, hg
        self.fb, self.f, self.alpha = fb, f, alpha
        return f

    def _update_operational_cost(self, v: float, g: float, p: float) -> float:
        """Record this step's ``coc`` and return the delayed operational cost ``oc`` (steps 4-5)."""
        coc = math.exp((2.0 * p + 2.5 * g + 4.0 * v) / 100.0)
        o = self.o
        if self._first_step:
            o.extend([coc] * HISTORY_LENGTH)
            self._first_step = False
        else:
            o.append(coc)  # maxlen drops the oldest entry
        oc = _W0 * o[0] + _W1 * o[1] + _W2 * o[2] + _W3 * o[3] + _W4 * o[4]
        self.coc, self.oc = coc, oc
        return oc

    def _update_mis_calibration(self, he: float) -> float:
        """Advance the Goldstone state machine and return the mis-calibration ``MC`` (step 6)."""
        domain, response, phi_idx = gs_transition(
            self.gs_domain, self.gs_response, self.gs_phi_idx, he
        )
        self.gs_domain, self.gs_response, self.gs_phi_idx = domain, response, phi_idx
        mc = -gs_penalty(phi_idx, he)
        self.mc = mc
        return mc

    def _update_consumption(self, oc: float, mc: float) -> float:
        """Draw the consumption ``c`` around its mean ``oc - 25 (MC - 1)`` (step 7, draw 8)."""
        e_mean = oc - CRGS * (mc - 1.0)
        c = e_mean - self._randn() * (1.0 + 0.005 * e_mean)
        self.c_mean, self.c = e_mean, c
        return c

    # ------------------------------------------------------------------ views
    def observation(self) -> list[float]:
        """Return the observable state ``[p, v, g, h, f, c]`` as Python floats."""
        return [self.p, self.v, self.g, self.h, self.f, self.c]

    def markov_state(self) -> dict[str, Any]:
        """Return a snapshot of the full (hidden) state, keyed like the reference trajectories.

        Returns:
            A dict with the observables, ``cost``, ``reward`` and the hidden keys ``coc, o, oc,
            fb, ge, ve, hg, hv, he, gs_domain, gs_sys_response, gs_phi_idx, MC`` plus the derived
            ``alpha`` and ``c_mean`` and the setpoint-generator internals.
        """
        return {
            "p": self.p,
            "v": self.v,
            "g": self.g,
            "h": self.h,
            "f": self.f,
            "c": self.c,
            "cost": self.cost,
            "reward": self.reward,
            "coc": self.coc,
            "o": list(self.o),
            "oc": self.oc,
            "fb": self.fb,
            "ge": self.ge,
            "ve": self.ve,
            "hg": self.hg,
            "hv": self.hv,
            "he": self.he,
            "gs_domain": self.gs_domain,
            "gs_sys_response": self.gs_response,
            "gs_phi_idx": self.gs_phi_idx,
            "MC": self.mc,
            "alpha": self.alpha,
            "c_mean": self.c_mean,
            "p_steps": self.p_steps,
            "p_step": self.p_step,
            "p_ch": self.p_change,
        }
