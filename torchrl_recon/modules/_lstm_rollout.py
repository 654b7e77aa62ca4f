"""The world model's autoregressive rollout as one autograd node with a hand-written BPTT.

Gradient planning differentiates a 200-step rollout 50 times per plan, and multi-step training
a 30-step one per batch. Recorded op by op, each step is ~16 autograd nodes and its backward
~25 more, and the per-node bookkeeping costs more than the arithmetic on these small tensors.
:class:`LSTMRollout` runs the same ops without recording them and replays their derivatives by
hand, with the ATen backward kernels autograd uses (``sigmoid_backward``, ``tanh_backward``,
...) in the order autograd accumulates them, so its states and gradients (actions, start state
and weights) are bitwise those of :func:`recorded_rollout`, the op-by-op reference
(``tests/modules/test_lstm_rollout.py``).

Both also run a population of models at once: with a leading member dim ``P`` on every
tensor (weights ``[P, ...]``, states ``[P, R, ...]``), each matmul becomes a batched one
(``bmm``/``baddbmm``) over the members; 2-D weights run the single model's exact ops.
"""

from __future__ import annotations

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


def _mm(mat1: torch.Tensor, mat2: torch.Tensor) -> torch.Tensor:
    """``mm`` for 2-D operands, ``bmm`` over a leading member dim."""
    return mat1.mm(mat2) if mat2.dim() == 2 else torch.bmm(mat1, mat2)


def _matvec(mat: torch.Tensor, vec: torch.Tensor) -> torch.Tensor:
    """``mat @ vec`` for ``[A, B] @ [B]``, or per member for ``[P, A, B] @ [P, B]``."""
    return mat @ vec if mat.dim() == 2 else torch.bmm(mat, vec.unsqueeze(-1)).squeeze(-1)


def sigmoid_tanh(x: torch.Tensor) -> torch.Tensor:
    """``tanh(x)`` as ``2·sigmoid(2x) − 1``: within float32 rounding of ``torch.tanh`` (absolute
    error ~1e-7) and several times faster on the CPU, whose ``tanh`` kernel is slow. A
    population's rollout uses it; a single model keeps ``torch.tanh`` (bitwise its reference).
    """
    return torch.sigmoid(x * 2).mul(2).sub_(1)


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
    *members, rows, horizon, action_dim = actions.shape
    # [*P, H, R, 4 hid] so each step is an `unbind` slice: indexing `gates_a[:, t]` would
    # zero-fill a full-size gradient per step in the backward (O(H²) memory traffic).
    flat = actions.transpose(-3, -2).reshape(*members, horizon * rows, action_dim)
    gates_a = _addmm(bias, flat, w_a).reshape(*members, horizon, rows, 4 * hid)
    states = []
    for gates_t in gates_a.unbind(-3):
        gates = _addmm_step(gates_t, torch.cat([s, h], -1), w_sh)
        i, f, g, o = gates.chunk(4, -1)
        c = torch.sigmoid(f) * c + torch.sigmoid(i) * torch.tanh(g)
        h = torch.sigmoid(o) * torch.tanh(c)
        s = s + _addmm(b_out, act(_addmm(b_d, h, w_d)), w_out)
        states.append(s)
    return torch.stack(states, -2)


def _addmm_step(gates: torch.Tensor, mat1: torch.Tensor, mat2: torch.Tensor) -> torch.Tensor:
    """``gates + mat1 @ mat2`` where ``gates`` already holds a full ``[*P, R, 4 hid]`` term."""
    if mat2.dim() == 2:
        return torch.addmm(gates, mat1, mat2)
    return torch.baddbmm(gates, mat1, mat2)


def _mat2_grad(grad: torch.Tensor, mat1: torch.Tensor, mat2: torch.Tensor) -> torch.Tensor:
    """Gradient of ``mat2`` in ``addmm(b, mat1, mat2)``, as autograd's ``mm_mat2_backward``."""
    if mat2.dim() == 3:  # members: baddbmm's backward
        return torch.bmm(mat1.transpose(-1, -2), grad)
    if mat2.stride(0) == 1 and mat2.stride(1) == mat2.size(0):  # column-major mat2
        return grad.t().mm(mat1).t()
    return mat1.t().mm(grad)


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
        ``P`` is the optional member dim of a population (see the module docstring).

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
        *members, rows, horizon, action_dim = actions.shape
        hid = h0.shape[-1]
        # The same ops as recorded_rollout, so the states are bitwise the same.
        flat_actions = actions.transpose(-3, -2).reshape(*members, horizon * rows, action_dim)
        gates_a = _addmm(bias, flat_actions, w_a).reshape(*members, horizon, rows, 4 * hid)
        s, h, c = s0, h0, c0
        saved = []
        states = []
        tanh = sigmoid_tanh if members else torch.tanh
        for gates_t in gates_a.unbind(-3):
            x = torch.cat([s, h], -1)
            gates = _addmm_step(gates_t, x, w_sh)
            if members:  # one sigmoid over all gates: tanh(g) = 2·sigmoid(2g) − 1
                gates[..., 2 * hid : 3 * hid].mul_(2)
                si, sf, s2g, so = torch.sigmoid(gates).chunk(4, -1)
                tg = s2g.mul(2).sub_(1)
            else:
                i, f, g, o = gates.chunk(4, -1)
                sf, si, tg, so = torch.sigmoid(f), torch.sigmoid(i), tanh(g), torch.sigmoid(o)
            c_prev = c
            c = sf * c + si * tg
            tc = tanh(c)
            h = so * tc
            pre = _addmm(b_d, h, w_d)
            z = act(pre)
            s = s + _addmm(b_out, z, w_out)
            saved.append((si, sf, tg, so, c_prev, tc, pre, z, x, h))
            states.append(s)
        ctx.saved, ctx.flat_actions = saved, flat_actions
        ctx.weights, ctx.activation = (w_a, w_sh, w_d, w_out), activation  # those backward needs
        ctx.shape = (members, rows, horizon, action_dim, s0.shape[-1])
        return torch.stack(states, -2)

    @staticmethod
    @once_differentiable
    def backward(ctx, grad_states):
        w_a, w_sh, w_d, w_out = ctx.weights
        need_weights = any(ctx.needs_input_grad[5:])
        act_backward = ACTIVATION_BACKWARDS[ctx.activation]
        members, rows, horizon, action_dim, obs_dim = ctx.shape
        outputs = grad_states.unbind(-2)
        w_out_t, w_d_t, w_sh_t = (w.transpose(-1, -2) for w in (w_out, w_d, w_sh))
        # ds, dh, dc: gradients of s_{t+2}, h_{t+1}, c_{t+1}·f_{t+1} from step t + 1; dx: its
        # cat's. Weight gradients sum the steps' contributions last step first, as autograd does.
        ds = dh = dc = dx = None
        dw = [None] * 5  # w_sh, w_d, b_d, w_out, b_out
        dgates_all = [None] * horizon
        # A population's weight gradients are one batched matmul over all steps after the loop
        # (a single model sums per-step ones, bitwise as autograd does).
        per_step = need_weights and not members
        dpre_all, ds_all = [None] * horizon, [None] * horizon
        for t in range(horizon - 1, -1, -1):
            si, sf, tg, so, c_prev, tc, pre, z, x, h = ctx.saved[t]
            # s_{t+1}: its output slice, then the residual (s_{t+2} = s_{t+1} + ...), then the
            # next step's cat — the order the recorded graph accumulates them in.
            if t == horizon - 1:
                ds = outputs[t]
            else:
                ds = (outputs[t] + ds) + dx[..., :obs_dim]
            dpre = act_backward(_mm(ds, w_out_t), pre, z)
            dh_dense = _mm(dpre, w_d_t)
            dh = dh_dense if t == horizon - 1 else dx[..., obs_dim:] + dh_dense
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
                -1,
            )
            dgates_all[t], dpre_all[t], ds_all[t] = dgates, dpre, ds
            if per_step:
                step = (
                    _mat2_grad(dgates, x, w_sh),
                    _mat2_grad(dpre, h, w_d),
                    dpre.sum(-2),
                    _mat2_grad(ds, z, w_out),
                    ds.sum(-2),
                )
                dw = (
                    list(step)
                    if t == horizon - 1
                    else [a + b for a, b in zip(dw, step, strict=True)]
                )
            dx = _mm(dgates, w_sh_t)
            dc = dc * sf
        ds0 = ds + dx[..., :obs_dim]
        dh0 = dx[..., obs_dim:]
        dgates_flat = torch.stack(dgates_all, -3).reshape(*members, horizon * rows, -1)
        dactions = None
        if ctx.needs_input_grad[3]:  # planning: the actions' gradient; fitting: none
            dactions = (
                _mm(dgates_flat, w_a.transpose(-1, -2))
                .reshape(*members, horizon, rows, action_dim)
                .transpose(-3, -2)
            )
        dw_a = dbias = None
        if need_weights:
            dw_a = _mat2_grad(dgates_flat, ctx.flat_actions, w_a)
            dbias = dgates_flat.sum(-2)
        if need_weights and members:

            def flat(items: list[torch.Tensor]) -> torch.Tensor:
                return torch.stack(items, -3).reshape(*members, horizon * rows, -1)

            xs, hs, zs = (flat([saved[k] for saved in ctx.saved]) for k in (8, 9, 7))
            dpre_flat, ds_flat = flat(dpre_all), flat(ds_all)
            dw = [
                _mat2_grad(dgates_flat, xs, w_sh),
                _mat2_grad(dpre_flat, hs, w_d),
                dpre_flat.sum(-2),
                _mat2_grad(ds_flat, zs, w_out),
                ds_flat.sum(-2),
            ]
        return ds0, dh0, dc, dactions, None, dw_a, dbias, *dw


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
