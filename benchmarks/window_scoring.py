"""Scoring every window of K candidate sequences with the world model ensemble.

Two ways to read the sliding T-windows of ``[K, L, N + M]`` through E LSTM members, each window
from a fresh state: a copy of every window through ``predict_delta`` (the input projection and
the head on all T steps of every window, the code before ``predict_window_deltas``), and
``WorldModelEnsembleUncertainty.score_sequence`` (``predict_window_deltas``: the input
projection once per sequence step, the head once per window). Both give the same scores; the
autoencoder's score of the same windows is timed beside them. Also prints the new path's
arithmetic limit: its FLOPs over the GEMM rate measured here (one ``baddbmm`` of the
recurrence's shape), as ``N.Nx its arithmetic limit``.

Run: python benchmarks/window_scoring.py [--candidates 1000] [--horizon 50] [--obs-dim 34]
     [--action-dim 8] [--repeats 5]
Prints each time, then ``speed-up vs window copies: X.Xx`` and ``x AE: Y.Y``.
"""

from __future__ import annotations

import argparse

import torch
from _common import (
    WINDOW,
    gemm_gflops,
    gemm_line,
    limit_ms,
    limit_text,
    parse_device_args,
    setup_done,
)

from torchrl_recon.estimators import ReconstructionUncertainty, WorldModelEnsembleUncertainty
from torchrl_recon.estimators.uncertainty import window_view
from torchrl_recon.runs.timing import interleaved_median_ms


def window_copies_score(est: WorldModelEnsembleUncertainty, x: torch.Tensor) -> torch.Tensor:
    """u of every window read as a copy through ``predict_delta`` (all T steps' head), in
    row blocks of 2048 steps like ``score_sequence``."""
    n, members, t = est.obs_dim, est.num_members, est.window
    sigma = est.input_norm.scale[:n]
    outs = []
    for block in x.split(max(1, 2048 // x.shape[1])):
        windows = window_view(block, t).reshape(-1, t, est.feature_dim)
        windows = windows.expand(members, *windows.shape)
        pred = est.members.predict_delta(windows[..., :n], windows[..., n:])[..., -1, :]
        pred = pred * (est.members.delta_norm.scale[:, None] / sigma)
        pred = pred + est.members.delta_norm.loc[:, None] / sigma
        u = (pred - pred.mean(0)).square().mean(0).mean(-1)
        outs.append(u.view(block.shape[0], -1))
    return torch.cat(outs)


def new_path_flops(est: WorldModelEnsembleUncertainty, rows: int, length: int) -> float:
    """Multiply-adds × 2 of ``predict_window_deltas`` on ``[rows, length]`` (GEMMs only)."""
    m, f, n, t = est.members, est.feature_dim, est.obs_dim, est.window
    h, d, windows = m.hidden_size, m.dense_size, length - t + 1
    per_member = rows * (length * f * 4 * h + windows * t * h * 4 * h + windows * (h * d + d * n))
    return 2.0 * est.num_members * per_member


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--candidates", type=int, default=1000)
    parser.add_argument("--horizon", type=int, default=50)
    parser.add_argument("--obs-dim", type=int, default=34)  # the Minitaur's; IB: 6
    parser.add_argument("--action-dim", type=int, default=8)  # the Minitaur's; IB: 3
    parser.add_argument("--members", type=int, default=5)
    parser.add_argument("--repeats", type=int, default=5)
    parser.add_argument("--threads", type=int, default=torch.get_num_threads())
    args, device = parse_device_args(parser)
    setup_done()
    torch.manual_seed(0)
    n, m = args.obs_dim, args.action_dim
    sizes = dict(window=WINDOW, hidden_size=32, dense_size=32)
    est = WorldModelEnsembleUncertainty(n, m, num_members=args.members, **sizes).to(device)
    ae = ReconstructionUncertainty(n, m, window=WINDOW, hidden_size=100).to(device)
    data = torch.randn(500, n + m, device=device)
    for e in (est, ae):
        e.fit_normalization(data[:, :n], data[:, n:])
    length = WINDOW - 1 + args.horizon
    x = torch.randn(args.candidates, length, n + m, device=device)
    with torch.no_grad():
        if not torch.equal(window_copies_score(est, x), est.score_sequence(x)):
            print("note: the two paths differ in the last bits on this machine")
        ms = interleaved_median_ms(
            {
                "window_copies": lambda: window_copies_score(est, x),
                "score_sequence": lambda: est.score_sequence(x),
                "autoencoder": lambda: ae.score_sequence(x),
            },
            args.repeats,
            device=device,
        )
    print(
        f"K={args.candidates}, L={length}, N+M={n + m}, E={args.members}, "
        f"threads={args.threads}, median of {args.repeats} round-robin calls"
    )
    for name, value in ms.items():
        print(f"{name}: {value:.1f} ms")
    # The GEMM rate of the recurrence's own product: [E, rows, hid] @ [E, hid, 4·hid].
    shape = (args.members, max(1, 2048 // length) * args.horizon, 32, 4 * 32)
    rate = gemm_gflops(device, shape, args.repeats * 20)
    print(gemm_line(rate, shape))
    limit = limit_ms(new_path_flops(est, args.candidates, length), rate)
    print(
        f"arithmetic limit of score_sequence: {limit:.1f} ms; measured "
        f"{limit_text(ms['score_sequence'], limit)}"
    )
    print(f"speed-up vs window copies: {ms['window_copies'] / ms['score_sequence']:.2f}x")
    print(f"x AE: {ms['score_sequence'] / ms['autoencoder']:.1f}")


if __name__ == "__main__":
    main()
