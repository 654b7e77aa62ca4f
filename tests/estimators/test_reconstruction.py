from __future__ import annotations

import pytest
import torch
from tensordict import TensorDict

from torchrl_recon.estimators import ReconstructionUncertainty


def _ae(window: int = 5) -> ReconstructionUncertainty:
    torch.manual_seed(0)
    ae = ReconstructionUncertainty(3, 2, window=window, hidden_size=16)
    ae.fit_normalization(torch.randn(100, 3) * 3 + 2, torch.rand(100, 2))
    return ae


def _naive_u(
    ae: ReconstructionUncertainty, obs: torch.Tensor, action: torch.Tensor
) -> torch.Tensor:
    x = ae.input_norm.normalize(torch.cat([obs, action], -1))
    out = []
    for t in range(x.shape[0] - ae.window + 1):
        w = x[t : t + ae.window].reshape(-1)
        recon = ae.decoder(torch.relu(ae.encoder(w)))
        out.append(((recon - w) ** 2).sum().sqrt() / ae.window)  # paper eq. 2
    return torch.stack(out)


@pytest.mark.parametrize("batch", [(), (3,), (2, 4)])
def test_score_matches_paper_equation_for_every_window(batch):
    ae = _ae()
    obs, action = torch.randn(*batch, 12, 3), torch.randn(*batch, 12, 2)
    u = ae.score(obs, action)
    assert u.shape == (*batch, 8)
    flat_u = u.reshape(-1, 8)
    flat_o, flat_a = obs.reshape(-1, 12, 3), action.reshape(-1, 12, 2)
    for i in range(flat_u.shape[0]):
        torch.testing.assert_close(
            flat_u[i], _naive_u(ae, flat_o[i], flat_a[i]), atol=1e-5, rtol=1e-5
        )


def test_score_windows_and_forward():
    ae = _ae()
    obs, action = torch.randn(2, 9, 3), torch.randn(2, 9, 2)
    u = ae.score(obs, action)
    windows = torch.cat([obs, action], -1)[:, 4:9]
    torch.testing.assert_close(ae.score_windows(windows), u[:, 4])
    td = ae(TensorDict({"observation": obs, "action": action}, [2, 9]))
    assert td["uncertainty"].shape == (2, 9)
    assert torch.isnan(td["uncertainty"][:, :4]).all()
    torch.testing.assert_close(td["uncertainty"][:, 4:], u)


@pytest.mark.parametrize("activation", ["relu", "tanh", "elu"])
def test_blocked_and_autograd_paths_agree(activation):
    torch.manual_seed(0)
    ae = ReconstructionUncertainty(3, 2, window=5, hidden_size=16, activation=activation)
    ae.fit_normalization(torch.randn(100, 3), torch.rand(100, 2))
    obs, action = torch.randn(150, 40, 3), torch.randn(150, 40, 2)  # several blocks
    with torch.no_grad():
        fast = ae.score(obs, action)
    slow = ae.score(obs, action)
    assert slow.requires_grad and not fast.requires_grad
    torch.testing.assert_close(fast, slow.detach(), atol=1e-5, rtol=1e-5)


def test_gradient_reaches_actions():
    ae = _ae()
    action = torch.randn(4, 10, 2, requires_grad=True)
    ae.score(torch.randn(4, 10, 3), action).sum().backward()
    assert action.grad.abs().sum() > 0


@pytest.mark.parametrize(
    "obs, action, match",
    [
        (torch.randn(2, 9, 4), torch.randn(2, 9, 2), "obs"),
        (torch.randn(2, 9, 3), torch.randn(2, 8, 2), "disagree"),
        (torch.randn(2, 4, 3), torch.randn(2, 4, 2), "window=5"),
        (torch.full((2, 9, 3), float("nan")), torch.randn(2, 9, 2), "NaN"),
    ],
)
def test_bad_input_is_a_clear_error(obs, action, match):
    with pytest.raises(ValueError, match=match):
        _ae().score(obs, action)


def test_normalizer_rejects_nan_and_constant_features_get_unit_scale():
    ae = _ae()
    with pytest.raises(ValueError, match="NaN"):
        ae.fit_normalization(torch.full((10, 3), float("nan")), torch.zeros(10, 2))
    ae.fit_normalization(torch.ones(10, 3), torch.randn(10, 2))
    assert torch.equal(ae.input_norm.scale[:3], torch.ones(3))


if __name__ == "__main__":
    pytest.main([__file__, "-q"])
