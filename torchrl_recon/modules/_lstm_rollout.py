"""The world model's LSTM: one cell, one rollout, and the accelerators that run it faster.

* :func:`lstm_cell` is the LSTM step, the one place its math is written: the state ``(h, c)``
  from the gates' pre-activations, for one model (``[B, 4·hid]``) or a population (a leading
  member dim ``P`` on every tensor). The world model's teacher-forced member loop, the
  reference rollout and the fused node's forward call it; only the no-grad accelerator lays
  the same math out its own way (feature-major, in place).
* :func:`recorded_rollout` is the reference autoregressive rollout, every op recorded by
  autograd (:func:`_unrolled`: the cell, the dense layer and the residual state update, step by
  step).
* :func:`rollout` picks, in one place, how a call runs: the reference, or an accelerator held
  to it by ``tests/modules/test_lstm_rollout.py``:

  - :class:`LSTMRollout`, when a gradient is needed: the same forward (:func:`_unrolled`)
    without recording, as one autograd node whose backward through time is written by hand
    with the ATen kernels autograd uses (``sigmoid_backward``, ``tanh_backward``, ...) in the
    order autograd accumulates them. Gradient planning differentiates a 200-step rollout 50
    times per plan and multi-step training a 30-step one per batch; recorded, each step is ~16
    autograd nodes and ~25 more in its backward, whose bookkeeping costs more than the
    arithmetic on these small tensors. For one model its states and gradients (actions, start
    state and weights) are bitwise the reference's;
  - :func:`rollout_inplace` (:func:`rollout_traced` under ``torch.compile``), when none is
    and the model is one: preallocated feature-major buffers, in-place ops.

Members: with a leading member dim ``P`` on every tensor (weights ``[P, ...]``, states
``[P, R, ...]``) each matmul becomes a batched one (``bmm``/``baddbmm``); 2-D weights run the
single model's exact ops (a batched matmul of one member need not be bitwise the plain one).
"""

from __future__ import annotations

from collections.abc import Callable
from typing import NamedTuple

import torch
from torch.autograd.function import once_differentiable

from torchrl_recon.modules.activations import (
    ACTIVATION_BACKWARDS,
    ACTIVATIONS,
    INPLACE_ACTIVATIONS,
)

# The kernels autograd's own derivative formulas call (resolved overloads: cheaper to call).
_sigmoid_backward = torch.ops.aten.sigmoid_backward.default
_tanh_backward = torch.ops.aten.tanh_backward.default


def _addmm(bias: torch.Tensor, mat1: torch.Tensor, mat2: torch.Tensor) -> torch.Tensor:
    """``addmm`` for one model's 2-D weights, ``baddbmm`` over the members of ``[P, ...]`` ones."""
    if mat2.dim() == 2:
        return torch.addmm(bias, mat1, mat2)
    return torch.baddbmm(bias.unsqueeze(-2), mat1, mat2)


def _addmm_step(gates: torch.Tensor, mat1: torch.Tensor, mat2: torch.Tensor) -> torch.Tensor:
    """``gates + mat1 @ mat2`` where ``gates`` already holds a full ``[*P, R, 4 hid]`` term."""
    if mat2.dim() == 2:
        return torch.addmm(gates, mat1, mat2)
    return torch.baddbmm(gates, mat1, mat2)


def _mm(mat1: torch.Tensor, mat2: torch.Tensor) -> torch.Tensor:
    """``mm`` for 2-D operands, ``bmm`` over a leading member dim."""
    return mat1.mm(mat2) if mat2.dim() == 2 else torch.bmm(mat1, mat2)


def _matvec(mat: torch.Tensor, vec: torch.Tensor) -> torch.Tensor:
    """``mat @ vec`` for ``[A, B] @ [B]``, or per member for ``[P, A, B] @ [P, B]``."""
    return mat @ vec if mat.dim() == 2 else torch.bmm(mat, vec.unsqueeze(-1)).squeeze(-1)


def _mat2_grad(grad: torch.Tensor, mat1: torch.Tensor, mat2: torch.Tensor) -> torch.Tensor:
    """Gradient of ``mat2`` in ``addmm(b, mat1, mat2)``, as autograd's ``mm_mat2_backward``."""
    if mat2.dim() == 3:  # members: baddbmm's backward
        return torch.bmm(mat1.transpose(-1, -2), grad)
    if mat2.stride(0) == 1 and mat2.stride(1) == mat2.size(0):  # column-major mat2
        return grad.t().mm(mat1).t()
    return mat1.t().mm(grad)


def sigmoid_tanh(x: torch.Tensor) -> torch.Tensor:
    """``tanh(x)`` as ``2·sigmoid(2x) − 1``: within float32 rounding of ``torch.tanh`` (absolute
    error ~1e-7) and several times faster on the CPU, whose ``tanh`` kernel is slow. A
    population's rollout uses it; a single model keeps ``torch.tanh`` (bitwise its reference).
    """
    return torch.sigmoid(x * 2).mul(2).sub_(1)


class CellActivations(NamedTuple):
    """One step's gate activations and ``tanh(c)``, what the hand-written backward reads."""

    si: torch.Tensor  # sigmoid(i)
    sf: torch.Tensor  # sigmoid(f)
    tg: torch.Tensor  # tanh(g)
    so: torch.Tensor  # sigmoid(o)
    tc: torch.Tensor  # tanh(c) of the new c


def lstm_cell(
    gates: torch.Tensor,
    c: torch.Tensor,
    *,
    tanh: Callable[[torch.Tensor], torch.Tensor] = torch.tanh,
    one_sigmoid: bool = False,
) -> tuple[torch.Tensor, torch.Tensor, CellActivations]:
    """One LSTM step from its gates' pre-activations: ``c' = σ(f)·c + σ(i)·tanh(g)``,
    ``h' = σ(o)·tanh(c')`` (``nn.LSTM``'s cell and gate order i, f, g, o).

    Args:
        gates: ``[*P, B, 4·hid]``, the input and recurrent parts and both biases summed.
        c: the cell state ``[*P, B, hid]``.

    Keyword Args:
        tanh: ``torch.tanh`` (the reference) or :func:`sigmoid_tanh` (a population's speed).
        one_sigmoid: compute all four gates under one ``sigmoid`` call, with ``tanh(g) =
            2·sigmoid(2g) − 1`` (the ``g`` block of ``gates`` is doubled in place, so only
            where nothing records autograd: the fused rollout of a population).

    Returns:
        ``(h', c', activations)``.

    Examples:
        >>> h, c, _ = lstm_cell(torch.zeros(2, 3, 4 * 5), torch.ones(2, 3, 5))
        >>> h.shape, c[0, 0, 0].item()
        (torch.Size([2, 3, 5]), 0.5)
    """
    if one_sigmoid:
        hid = gates.shape[-1] // 4
        gates[..., 2 * hid : 3 * hid].mul_(2)
        si, sf, s2g, so = torch.sigmoid(gates).chunk(4, -1)
        tg = s2g.mul(2).sub_(1)
    else:
        i, f, g, o = gates.chunk(4, -1)
        si, sf, tg, so = torch.sigmoid(i), torch.sigmoid(f), tanh(g), torch.sigmoid(o)
    c = sf * c + si * tg
    tc = tanh(c)
    return so * tc, c, CellActivations(si, sf, tg, so, tc)


def fold_weights(
    w_ih: torch.Tensor,
    w_hh: torch.Tensor,
    b_ih: torch.Tensor,
    b_hh: torch.Tensor,
    w_dense: torch.Tensor,
    b_dense: torch.Tensor,
    w_head: torch.Tensor,
    b_head: torch.Tensor,
    norms: tuple[torch.Tensor, ...],
) -> tuple[torch.Tensor, ...]:
    """Fold the normalisations into the weights so the rollout works in raw units.

    Args:
        w_ih, w_hh, b_ih, b_hh: the LSTM's weights (``nn.LSTM`` layout, ``[*P, 4 hid, N + M]``...).
        w_dense, b_dense, w_head, b_head: the dense and output layers (``nn.Linear`` layout).
        norms: ``(obs_loc, obs_scale, action_loc, action_scale, delta_loc, delta_scale)``.

    Returns:
        ``w_a, bias, w_sh, w_d, b_d, w_out, b_out``, the weights :class:`LSTMRollout` takes,
        with the optional member dim ``P`` leading each.
    """
    obs_loc, obs_scale, act_loc, act_scale, delta_loc, delta_scale = norms
    n = obs_loc.shape[-1]
    w_s = w_ih[..., :n] / obs_scale.unsqueeze(-2)
    w_a = w_ih[..., n:] / act_scale.unsqueeze(-2)
    bias = b_ih + b_hh - _matvec(w_s, obs_loc) - _matvec(w_a, act_loc)
    w_sh = torch.cat([w_s, w_hh], -1).transpose(-1, -2)  # [*P, N + hid, 4 hid]
    w_out = (w_head * delta_scale.unsqueeze(-1)).transpose(-1, -2)  # [*P, dense, N]
    b_out = b_head * delta_scale + delta_loc
    return w_a.transpose(-1, -2), bias, w_sh, w_dense.transpose(-1, -2), b_dense, w_out, b_out


def rollout(
    s: torch.Tensor,
    h: torch.Tensor,
    c: torch.Tensor,
    actions: torch.Tensor,
    activation: str,
    *weights: torch.Tensor,
    reference: bool = False,
) -> torch.Tensor:
    """The rollout ``[*P, R, H, N]``, run by the reference or by the accelerator for this call
    (the one place that chooses; same arguments as :class:`LSTMRollout`).

    ``reference=True``, or a population's call that needs no gradient: :func:`recorded_rollout`.
    A gradient needed: :class:`LSTMRollout`. Neither, one model: :func:`rollout_inplace`.

    Examples:
        >>> from torchrl_recon.modules import LSTMWorldModel
        >>> model, zeros = LSTMWorldModel(6, 3), torch.zeros(4, 32)
        >>> states = rollout(torch.zeros(4, 6), zeros, zeros, torch.rand(4, 20, 3), "relu",
        ...                  *model._folded_weights())
        >>> states.shape, type(states.grad_fn).__name__
        (torch.Size([4, 20, 6]), 'LSTMRolloutBackward')
    """
    inputs = (s, h, c, actions)
    needs_grad = torch.is_grad_enabled() and any(x.requires_grad for x in (*inputs, *weights))
    if reference or (not needs_grad and actions.dim() > 3):
        return recorded_rollout(*inputs, activation, *weights)
    if needs_grad:  # one autograd node with a hand-written backward through time
        return LSTMRollout.apply(*inputs, activation, *weights)
    return rollout_inplace(*inputs, activation, *weights)


class _Step(NamedTuple):
    """What one step of :func:`_unrolled` keeps for the hand-written backward."""

    cell: CellActivations
    c_prev: torch.Tensor  # the cell state the step started from
    pre: torch.Tensor  # the dense layer's pre-activation
    z: torch.Tensor  # and its output
    x: torch.Tensor  # the step's [s; h] (the recurrent matmul's input)
    h: torch.Tensor  # the step's new h


def _unrolled(
    s: torch.Tensor,
    h: torch.Tensor,
    c: torch.Tensor,
    actions: torch.Tensor,
    activation: str,
    weights: tuple[torch.Tensor, ...],
    **cell: object,
) -> tuple[torch.Tensor, torch.Tensor, list[_Step]]:
    """The rollout, step by step: the states ``[*P, R, H, N]``, the actions as one
    ``[*P, H·R, M]`` matrix (steps major) and each step's :class:`_Step`.

    ``cell``: :func:`lstm_cell`'s keywords. Recorded by autograd when grad mode is on.
    """
    w_a, bias, w_sh, w_d, b_d, w_out, b_out = weights
    act, hid = ACTIVATIONS[activation], h.shape[-1]
    *members, rows, horizon, action_dim = actions.shape
    # [*P, H, R, 4 hid] so each step is an `unbind` slice: indexing `gates_a[:, t]` would
    # zero-fill a full-size gradient per step in the backward (O(H²) memory traffic).
    flat = actions.transpose(-3, -2).reshape(*members, horizon * rows, action_dim)
    gates_a = _addmm(bias, flat, w_a).reshape(*members, horizon, rows, 4 * hid)
    states, steps = [], []
    for gates_t in gates_a.unbind(-3):
        x, c_prev = torch.cat([s, h], -1), c
        h, c, activations = lstm_cell(_addmm_step(gates_t, x, w_sh), c, **cell)
        pre = _addmm(b_d, h, w_d)
        z = act(pre)
        s = s + _addmm(b_out, z, w_out)
        steps.append(_Step(activations, c_prev, pre, z, x, h))
        states.append(s)
    return torch.stack(states, -2), flat, steps


def recorded_rollout(
    s: torch.Tensor,
    h: torch.Tensor,
    c: torch.Tensor,
    actions: torch.Tensor,
    activation: str,
    *weights: torch.Tensor,
) -> torch.Tensor:
    """The reference: the rollout with every op recorded by autograd, ``[*P, R, H, N]``.

    Same arguments as :class:`LSTMRollout`. Slower; kept to test and benchmark the fused node.
    """
    return _unrolled(s, h, c, actions, activation, weights)[0]


class LSTMRollout(torch.autograd.Function):
    """``states = LSTMRollout.apply(s0, h0, c0, actions, activation, *weights)``.

    Args (of ``apply``):
        s0, h0, c0: initial state and LSTM state, ``[*P, R, N]``, ``[*P, R, hid]``, ``[*P, R, hid]``.
        actions: ``[*P, R, H, M]``.
        activation: the dense layer's activation name.
        weights: the world model's folded weights ``w_a, bias, w_sh, w_d, b_d, w_out, b_out``
            (see :func:`fold_weights`), ``[*P, ...]`` each.

    Returns:
        states s_1..s_H, ``[*P, R, H, N]``. Differentiable once (no double backward).
        ``P`` is the optional member dim of a population (see the module docstring), whose
        forward runs the cell with :func:`sigmoid_tanh` under one sigmoid (within rounding of
        the reference).

    Examples:
        >>> from torchrl_recon.modules import LSTMWorldModel
        >>> model = LSTMWorldModel(6, 3)
        >>> actions = torch.rand(4, 20, 3, requires_grad=True)
        >>> states = LSTMRollout.apply(torch.zeros(4, 6), torch.zeros(4, 32), torch.zeros(4, 32),
        ...                            actions, "relu", *model._folded_weights())
        >>> states.sum().backward(); actions.grad.shape, model.lstm.weight_hh_l0.grad.shape
        (torch.Size([4, 20, 3]), torch.Size([128, 32]))
    """

    @staticmethod
    def forward(ctx, s0, h0, c0, actions, activation, *weights):
        members = actions.dim() > 3
        cell = dict(tanh=sigmoid_tanh, one_sigmoid=True) if members else {}
        states, ctx.flat_actions, ctx.steps = _unrolled(
            s0, h0, c0, actions, activation, weights, **cell
        )
        w_a, _, w_sh, w_d, _, w_out, _ = weights
        ctx.weights, ctx.activation = (w_a, w_sh, w_d, w_out), activation  # those backward needs
        ctx.shape = (*actions.shape[:-2], actions.shape[-1], s0.shape[-1])
        return states

    @staticmethod
    @once_differentiable
    def backward(ctx, grad_states):
        *members, rows, action_dim, obs_dim = ctx.shape
        w_a = ctx.weights[0]
        ds0, dh0, dc0, grads = _through_time(ctx, grad_states)
        dgates_flat = _steps_flat([dgates for dgates, _, _ in grads], members)
        dactions = None
        if ctx.needs_input_grad[3]:  # planning: the actions' gradient; fitting: none
            horizon = len(grads)
            dactions = (
                _mm(dgates_flat, w_a.transpose(-1, -2))
                .reshape(*members, horizon, rows, action_dim)
                .transpose(-3, -2)
            )
        dweights = [None] * 7
        if any(ctx.needs_input_grad[5:]):
            dweights = _weight_grads(ctx, grads, dgates_flat)
        return ds0, dh0, dc0, dactions, None, *dweights


def _step_backward(
    step: _Step,
    ds: torch.Tensor,
    dh_next: torch.Tensor | None,
    dc_next: torch.Tensor | None,
    w_out_t: torch.Tensor,
    w_d_t: torch.Tensor,
    act_backward: Callable,
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """One step's backward through the output layer, the dense layer and the cell.

    Args:
        step: what the step's forward kept.
        ds: the gradient of the step's new state s.
        dh_next, dc_next: those of its new h and c (times the next step's σ(f)) from the next
            step; None at the last step.

    Returns:
        ``(dgates, dpre, dc)``: the gradients of the step's gate pre-activations, of its dense
        pre-activation and of its new c.
    """
    si, sf, tg, so, tc = step.cell
    dpre = act_backward(_mm(ds, w_out_t), step.pre, step.z)
    dh_dense = _mm(dpre, w_d_t)
    dh = dh_dense if dh_next is None else dh_next + dh_dense
    dc_t = _tanh_backward(dh * so, tc)
    dc = dc_t if dc_next is None else dc_t + dc_next
    dgates = torch.cat(
        [
            _sigmoid_backward(dc * tg, si),
            _sigmoid_backward(dc * step.c_prev, sf),
            _tanh_backward(dc * si, tg),
            _sigmoid_backward(dh * tc, so),
        ],
        -1,
    )
    return dgates, dpre, dc


def _through_time(ctx, grad_states: torch.Tensor) -> tuple:
    """The backward through time, last step first: ``(ds0, dh0, dc0, grads)`` with ``grads``
    each step's ``(dgates, dpre, ds)``, first step first.

    ``ds`` of s_{t+1} sums its output slice, then the residual (s_{t+2} = s_{t+1} + ...), then
    the next step's cat: the order the recorded graph accumulates them in.
    """
    obs_dim = ctx.shape[-1]
    _, w_sh, w_d, w_out = ctx.weights
    w_out_t, w_d_t, w_sh_t = (w.transpose(-1, -2) for w in (w_out, w_d, w_sh))
    act_backward = ACTIVATION_BACKWARDS[ctx.activation]
    ds = dx = dc = None  # of s_{t+2}, of step t + 1's cat, of c_{t+1}·σ(f_{t+1})
    grads = []
    for step, out in zip(reversed(ctx.steps), reversed(grad_states.unbind(-2)), strict=True):
        if dx is None:
            ds, dh_next = out, None
        else:
            ds, dh_next = (out + ds) + dx[..., :obs_dim], dx[..., obs_dim:]
        dgates, dpre, dc = _step_backward(step, ds, dh_next, dc, w_out_t, w_d_t, act_backward)
        grads.append((dgates, dpre, ds))
        dx = _mm(dgates, w_sh_t)
        dc = dc * step.cell.sf
    return ds + dx[..., :obs_dim], dx[..., obs_dim:], dc, grads[::-1]


def _steps_flat(items: list[torch.Tensor], members: list[int]) -> torch.Tensor:
    """Per-step ``[*P, R, D]`` tensors, first step first, as one ``[*P, H·R, D]`` (steps major)."""
    stacked = torch.stack(items, -3)
    return stacked.reshape(*members, stacked.shape[-3] * stacked.shape[-2], -1)


def _weight_grads(ctx, grads: list[tuple], dgates_flat: torch.Tensor) -> list[torch.Tensor]:
    """The gradients of the folded weights ``w_a, bias, w_sh, w_d, b_d, w_out, b_out``.

    One model sums each step's contributions, last step first, as autograd does (bitwise the
    reference's); a population's are one batched matmul over all steps.
    """
    w_a, w_sh, w_d, w_out = ctx.weights
    members = ctx.shape[:-3]
    dw_a = _mat2_grad(dgates_flat, ctx.flat_actions, w_a)
    dbias = dgates_flat.sum(-2)
    if members:
        xs, hs, zs = (_steps_flat([getattr(s, k) for s in ctx.steps], members) for k in "xhz")
        dpre, ds = (_steps_flat([g[k] for g in grads], members) for k in (1, 2))
        return [
            dw_a,
            dbias,
            _mat2_grad(dgates_flat, xs, w_sh),
            _mat2_grad(dpre, hs, w_d),
            dpre.sum(-2),
            _mat2_grad(ds, zs, w_out),
            ds.sum(-2),
        ]
    total = None
    for step, (dgates, dpre, ds) in zip(reversed(ctx.steps), reversed(grads), strict=True):
        each = (
            _mat2_grad(dgates, step.x, w_sh),
            _mat2_grad(dpre, step.h, w_d),
            dpre.sum(-2),
            _mat2_grad(ds, step.z, w_out),
            ds.sum(-2),
        )
        total = each if total is None else [a + b for a, b in zip(total, each, strict=True)]
    return [dw_a, dbias, *total]


def _step_weights(
    weights: tuple[torch.Tensor, ...], n: int, hid: int
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """The folded weights (:func:`fold_weights`) as the no-grad rollouts multiply them,
    feature-major, each bias riding inside its matmul on a constant-1 row of the input:

    * ``w_x`` ``[4 hid, N + hid + 1 + M]``: all four gates from ``[s; h; 1; a]`` in one
      matmul, gate rows reordered to ``[i, f, o | g]`` and the ``g`` rows doubled (exact: a
      power of two), so one sigmoid covers all four (``tanh(g) = 2·sigmoid(2g) − 1``);
    * ``w_d1`` ``[dense, hid + 1]``: the dense layer from ``[h; 1]``;
    * ``w_out1`` ``[N, dense + 1]``: the state change from ``[z; 1]``.
    """
    w_a, bias, w_sh, w_d, b_d, w_out, b_out = weights
    like = dict(dtype=w_sh.dtype, device=w_sh.device)
    order = torch.cat(
        [
            torch.arange(0, 2 * hid, device=w_sh.device),
            torch.arange(3 * hid, 4 * hid, device=w_sh.device),
            torch.arange(2 * hid, 3 * hid, device=w_sh.device),
        ]
    )
    # after the reordering: sigmoid(2g) in the last block
    double_g = torch.cat([torch.ones(3 * hid, 1, **like), torch.full((hid, 1), 2.0, **like)])
    w_x = torch.cat([w_sh, bias[None], w_a])  # [N + hid + 1 + M, 4 hid]: rows of [s; h; 1; a]
    w_x = (w_x.t()[order] * double_g).contiguous()
    w_d1 = torch.cat([w_d, b_d[None]]).t().contiguous()  # [dense, hid + 1]
    w_out1 = torch.cat([w_out, b_out[None]]).t().contiguous()  # [N, dense + 1]
    return w_x, w_d1, w_out1


@torch.no_grad()
def rollout_inplace(
    s: torch.Tensor,
    h: torch.Tensor,
    c: torch.Tensor,
    actions: torch.Tensor,
    activation: str,
    *weights: torch.Tensor,
) -> torch.Tensor:
    """The rollout of :class:`LSTMRollout` for one model (2-D weights) without autograd.

    Preallocated buffers, in-place ops, 14 small kernels a step (16 with one matmul per gate
    input), feature-major: every buffer is
    ``[features, R]``, so each matmul is ``W @ X`` with the R candidates as its long side. The
    output head (N state columns) and the dense layer read as ``X @ W`` had a short side of
    N + 1 or dense columns, which the CPU's GEMM runs at a fraction of its rate; feature-major
    the same products take about a quarter of the time and a CEM call about 11 % less (see
    ``docs/benchmarks.md``). Each step is three matmuls (:func:`_step_weights`): the four gates
    from step t's column block ``[s; h; 1; a]`` of one ``[H + 1, N + hid + 1 + M, R]`` slab
    (the actions laid into it once), the dense layer from the ``[h; 1]`` rows the step writes
    into block t + 1, and the state ``s + W·z`` written by one ``addmm`` into block t + 1's
    ``s`` rows. The gates are one ``[4·hidden, R]`` buffer reused every step (a slab of all
    steps' gates cost page faults between planner iterations). Both tanh are computed as
    ``tanh(x) = 2·sigmoid(2x) − 1`` (:func:`sigmoid_tanh`): the CPU's ``tanh`` kernel is about
    5× slower per element than its ``sigmoid`` and was half of a CEM call.

    Traced by ``torch.compile`` (a compiled plan or pass), it runs :func:`rollout_traced`
    instead: the same ops on the same values (bitwise the same states with Dynamo's ``eager``
    backend), written without writes into views of a buffer, which functionalisation would
    turn into a copy of the whole buffer per step.
    """
    if torch.compiler.is_compiling():
        return rollout_traced(s, h, c, actions, activation, *weights)
    n, hid, dense = s.shape[-1], h.shape[-1], weights[3].shape[-1]
    rows, horizon, m = actions.shape
    w_x, w_d1, w_out1 = _step_weights(weights, n, hid)
    x_rows = n + hid + 1 + m
    slab = s.new_empty(horizon + 1, x_rows, rows)  # block t: [s_t; h_t; 1; a_t]
    slab[0, :n], slab[0, n : n + hid] = s.t(), h.t()
    slab[:, n + hid] = 1
    slab[:horizon, n + hid + 1 :] = actions.permute(1, 2, 0)
    slab[horizon, n + hid + 1 :] = 0  # never read
    gates = s.new_empty(4 * hid, rows)
    z1 = s.new_ones(dense + 1, rows)
    c = c.t().contiguous()
    tg = s.new_empty(hid, rows)
    act_ = INPLACE_ACTIVATIONS[activation]
    i, f, o, g2 = (gates[k * hid : (k + 1) * hid] for k in range(4))
    for t in range(horizon):
        x, nxt = slab[t], slab[t + 1]
        torch.mm(w_x, x, out=gates).sigmoid_()  # i, f, o, sigmoid(2g)
        torch.mul(g2, 2, out=tg).sub_(1)  # tanh(g)
        c.mul_(f).addcmul_(i, tg)
        torch.mul(c, 2, out=tg).sigmoid_().mul_(2).sub_(1)  # tanh(c)
        torch.mul(o, tg, out=nxt[n : n + hid])  # h
        act_(torch.mm(w_d1, nxt[n : n + hid + 1], out=z1[:dense]))
        torch.addmm(x[:n], w_out1, z1, out=nxt[:n])  # s + W·z + b
    return slab[1:, :n].permute(2, 0, 1)


def rollout_traced(
    s: torch.Tensor,
    h: torch.Tensor,
    c: torch.Tensor,
    actions: torch.Tensor,
    activation: str,
    *weights: torch.Tensor,
) -> torch.Tensor:
    """:func:`rollout_inplace` as ``torch.compile`` traces it: the same ops on the same values,
    each step's ``[s; h; 1; a]`` a ``cat`` and each state its own tensor, stacked once.

    Written into views of one preallocated slab (``out=slab[t + 1]``), every step became a
    rewrite of the whole slab once functionalised (O(H²·R) traffic, and ~31 ATen nodes a
    step); here a step is ~23 nodes, three of them matmuls (one for the gates, one per head),
    and Inductor lays the steps' states into the stacked result.
    """
    n, hid = s.shape[-1], h.shape[-1]
    horizon = actions.shape[1]
    w_x, w_d1, w_out1 = _step_weights(weights, n, hid)
    act = ACTIVATIONS[activation]
    ones = s.new_ones(1, s.shape[0])
    steps = actions.permute(1, 2, 0)  # [H, M, R]
    st, hz, ct = s.t(), torch.cat([h.t(), ones]), c.t()  # hz: [h; 1]
    states = []
    for t in range(horizon):
        gates = torch.mm(w_x, torch.cat([st, hz, steps[t]])).sigmoid()  # i, f, o, sigmoid(2g)
        i, f, o, g2 = (gates[k * hid : (k + 1) * hid] for k in range(4))
        tg = g2 * 2 - 1  # tanh(g)
        ct = torch.addcmul(ct * f, i, tg)
        hz = torch.cat([o * ((ct * 2).sigmoid() * 2 - 1), ones])  # [h; 1], h = o·tanh(c)
        st = torch.addmm(st, w_out1, torch.cat([act(torch.mm(w_d1, hz)), ones]))
        states.append(st)
    return torch.stack(states).permute(2, 0, 1)
