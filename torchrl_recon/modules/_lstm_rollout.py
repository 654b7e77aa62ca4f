"""The world model's autoregressive rollout as one autograd node with a hand-written BPTT.

Gradient planning differentiates a 200-step rollout 50 times per plan, and multi-step training
a 30-step one per batch. Recorded op by op, each step is ~16 autograd nodes and its backward
~25 more, and the per-node bookkeeping costs more than the arithmetic on these small tensors.
:class:`LSTMRollout` runs the same ops without recording them and replays their derivatives by
hand, with the ATen backward kernels autograd uses (``sigmoid_backward``, ``tanh_backward``,
...) in the order autograd accumulates them, so its states and gradients (actions, start state
and weights) are bitwise those of :func:`recorded_rollout`, the op-by-op reference
(``tests/modules/test_lstm_rollout.py``).
"""

from __future__ import annotations

import torch
from torch.autograd.function import once_differentiable

from torchrl_recon.modules.activations import ACTIVATION_BACKWARDS, ACTIVATIONS

# The kernels autograd's own derivative formulas call (resolved overloads: cheaper to call).
_sigmoid_backward = torch.ops.aten.sigmoid_backward.default
_tanh_backward = torch.ops.aten.tanh_backward.default


def recorded_rollout(
    s: torch.Tensor,
    h: torch.Tensor,
    c: torch.Tensor,
    actions: torch.Tensor,
    activation: str,
    *weights: torch.Tensor,
) -> torch.Tensor:
    """The reference: the same rollout with every op recorded by autograd, ``[R, H, N]``.

    Same arguments as :class:`LSTMRollout`. Slower; kept to test and benchmark the fused node.
    """
    w_a, bias, w_sh, w_d, b_d, w_out, b_out = weights
    act, hid = ACTIVATIONS[activation], h.shape[-1]
    rows, horizon, action_dim = actions.shape
    # [H, R, 4 hid] so each step is an `unbind` slice: indexing `gates_a[:, t]` would zero-fill
    # a full-size gradient per step in the backward (O(H²) memory traffic).
    gates_a = torch.addmm(bias, actions.transpose(0, 1).reshape(-1, action_dim), w_a).reshape(
        horizon, rows, 4 * hid
    )
    states = []
    for gates_t in gates_a.unbind(0):
        gates = torch.addmm(gates_t, torch.cat([s, h], 1), w_sh)
        i, f, g, o = gates.chunk(4, 1)
        c = torch.sigmoid(f) * c + torch.sigmoid(i) * torch.tanh(g)
        h = torch.sigmoid(o) * torch.tanh(c)
        s = s + torch.addmm(b_out, act(torch.addmm(b_d, h, w_d)), w_out)
        states.append(s)
    return torch.stack(states, 1)


def _mat2_grad(grad: torch.Tensor, mat1: torch.Tensor, mat2: torch.Tensor) -> torch.Tensor:
    """Gradient of ``mat2`` in ``addmm(b, mat1, mat2)``, as autograd's ``mm_mat2_backward``."""
    if mat2.stride(0) == 1 and mat2.stride(1) == mat2.size(0):  # column-major mat2
        return grad.t().mm(mat1).t()
    return mat1.t().mm(grad)


class LSTMRollout(torch.autograd.Function):
    """``states = LSTMRollout.apply(s0, h0, c0, actions, activation, *weights)``.

    Args (of ``apply``):
        s0, h0, c0: initial state and LSTM state, ``[R, N]``, ``[R, hid]``, ``[R, hid]``.
        actions: ``[R, H, M]``.
        activation: the dense layer's activation name.
        weights: the world model's folded weights ``w_a, bias, w_sh, w_d, b_d, w_out, b_out``
            (see ``LSTMWorldModel._folded_weights``).

    Returns:
        states s_1..s_H, ``[R, H, N]``. Differentiable once (no double backward).

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
    def forward(ctx, s0, h0, c0, actions, activation, w_a, bias, w_sh, w_d, b_d, w_out, b_out):
        act = ACTIVATIONS[activation]
        rows, horizon, action_dim = actions.shape
        hid = h0.shape[-1]
        # The same ops as recorded_rollout, so the states are bitwise the same.
        flat_actions = actions.transpose(0, 1).reshape(-1, action_dim)
        gates_a = torch.addmm(bias, flat_actions, w_a).reshape(horizon, rows, 4 * hid)
        s, h, c = s0, h0, c0
        saved = []
        states = []
        for gates_t in gates_a.unbind(0):
            x = torch.cat([s, h], 1)
            gates = torch.addmm(gates_t, x, w_sh)
            i, f, g, o = gates.chunk(4, 1)
            sf, si, tg, so = torch.sigmoid(f), torch.sigmoid(i), torch.tanh(g), torch.sigmoid(o)
            c_prev = c
            c = sf * c + si * tg
            tc = torch.tanh(c)
            h = so * tc
            pre = torch.addmm(b_d, h, w_d)
            z = act(pre)
            s = s + torch.addmm(b_out, z, w_out)
            saved.append((si, sf, tg, so, c_prev, tc, pre, z, x, h))
            states.append(s)
        ctx.saved, ctx.flat_actions = saved, flat_actions
        ctx.weights, ctx.activation = (w_a, w_sh, w_d, w_out), activation  # those backward needs
        ctx.shape = (rows, horizon, action_dim, s0.shape[-1])
        return torch.stack(states, 1)

    @staticmethod
    @once_differentiable
    def backward(ctx, grad_states):
        w_a, w_sh, w_d, w_out = ctx.weights
        need_weights = any(ctx.needs_input_grad[5:])
        act_backward = ACTIVATION_BACKWARDS[ctx.activation]
        rows, horizon, action_dim, obs_dim = ctx.shape
        outputs = grad_states.unbind(1)
        w_out_t, w_d_t, w_sh_t = w_out.t(), w_d.t(), w_sh.t()
        # ds, dh, dc: gradients of s_{t+2}, h_{t+1}, c_{t+1}·f_{t+1} from step t + 1; dx: its
        # cat's. Weight gradients sum the steps' contributions last step first, as autograd does.
        ds = dh = dc = dx = None
        dw = [None] * 5  # w_sh, w_d, b_d, w_out, b_out
        dgates_all = [None] * horizon
        for t in range(horizon - 1, -1, -1):
            si, sf, tg, so, c_prev, tc, pre, z, x, h = ctx.saved[t]
            # s_{t+1}: its output slice, then the residual (s_{t+2} = s_{t+1} + ...), then the
            # next step's cat — the order the recorded graph accumulates them in.
            if t == horizon - 1:
                ds = outputs[t]
            else:
                ds = (outputs[t] + ds) + dx[:, :obs_dim]
            dpre = act_backward(ds.mm(w_out_t), pre, z)
            dh_dense = dpre.mm(w_d_t)
            dh = dh_dense if t == horizon - 1 else dx[:, obs_dim:] + dh_dense
            dtc = dh * so
            dso = dh * tc
            dc_t = _tanh_backward(dtc, tc)
            dc = dc_t if t == horizon - 1 else dc_t + dc
            dgates = torch.cat(
                [
                    _sigmoid_backward(dc * tg, si),
                    _sigmoid_backward(dc * c_prev, sf),
                    _tanh_backward(dc * si, tg),
                    _sigmoid_backward(dso, so),
                ],
                1,
            )
            dgates_all[t] = dgates
            if need_weights:
                step = (
                    _mat2_grad(dgates, x, w_sh),
                    _mat2_grad(dpre, h, w_d),
                    dpre.sum(0),
                    _mat2_grad(ds, z, w_out),
                    ds.sum(0),
                )
                dw = (
                    list(step)
                    if t == horizon - 1
                    else [a + b for a, b in zip(dw, step, strict=True)]
                )
            dx = dgates.mm(w_sh_t)
            dc = dc * sf
        ds0 = ds + dx[:, :obs_dim]
        dh0 = dx[:, obs_dim:]
        dgates_flat = torch.stack(dgates_all).reshape(horizon * rows, -1)
        dactions = dgates_flat.mm(w_a.t()).reshape(horizon, rows, action_dim).transpose(0, 1)
        dw_a = dbias = None
        if need_weights:
            dw_a = _mat2_grad(dgates_flat, ctx.flat_actions, w_a)
            dbias = dgates_flat.sum(0)
        return ds0, dh0, dc, dactions, None, dw_a, dbias, *dw
