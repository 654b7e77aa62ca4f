"""docs/custom_env.md: its Python blocks run, in order, at a small size."""

from __future__ import annotations

import math
import re
from pathlib import Path

import pytest

DOC = Path(__file__).resolve().parents[1] / "docs" / "custom_env.md"
SMALL = "FRAMES, FIT_STEPS, EPISODES, STEPS = 600, 100, 1, 12  # tutorial size"


def _blocks() -> list[str]:
    return re.findall(r"```python\n(.*?)```", DOC.read_text(), flags=re.S)


def test_the_tutorial_code_runs_at_a_small_size(capsys):
    blocks = _blocks()
    assert len(blocks) >= 4
    code = "\n".join(blocks)
    sized = re.sub(
        r"^FRAMES, FIT_STEPS, EPISODES, STEPS = .*# tutorial size$", SMALL, code, flags=re.M
    )
    assert sized != code, "the tutorial's size line moved: update SMALL"
    namespace: dict = {"__name__": "custom_env_tutorial"}
    exec(compile(sized, str(DOC), "exec"), namespace)
    assert "[-2.0] [2.0]" in capsys.readouterr().out  # the env's bounds, not [-1, 1]
    results = namespace["results"]
    assert list(results) == ["random"] + [f"MPC, relative beta {b}" for b in (0.0, 0.1, 0.3, 1.0)]
    assert all(math.isfinite(v) and v > 0 for v in results.values())
    assert namespace["beta_1"] > 0
    # the CLI's cost (my_costs.pendulum) is the API's pendulum_cost
    import torch

    obs = torch.tensor([[0.6, 0.8, -1.5]])
    act = torch.tensor([[1.2]])
    assert namespace["pendulum"](obs, act, obs).item() == pytest.approx(
        namespace["pendulum_cost"](obs, act, obs).item()
    )
