"""``benchmarks/peers/side_by_side.py``: our online runs beside PETS's, from their files."""

from __future__ import annotations

import json
from pathlib import Path

from tests.scripts import load_script

SCRIPT = Path(__file__).parents[1] / "benchmarks" / "peers" / "side_by_side.py"
OURS = Path(__file__).parents[1] / "docs" / "results" / "online" / "Pendulum-v1"


def _load():
    return load_script(SCRIPT)


def _pets_run(folder: Path, returns: list[float], **timing) -> None:
    folder.mkdir(parents=True)
    rows = "".join(f"{200 * (i + 1)},{r}\n" for i, r in enumerate(returns))
    (folder / "results.csv").write_text("env_step,episode_reward\n" + rows)
    base = {"task": "pendulum", "plan_ms_per_step": 1900.0, "fit_s_per_refit": 2.0}
    (folder / "timing.json").write_text(json.dumps(base | timing))


def test_the_table_holds_each_agents_last_half_and_timings(tmp_path):
    side = _load()
    _pets_run(tmp_path / "seed0", [-1000, -500, -200, -100])  # last half: -150
    _pets_run(tmp_path / "seed1", [-900, -400, -300, -150, -130], random_steps=100)  # -193.3
    pets = side.pets(tmp_path, "pendulum")
    assert pets["curves"][0][0] == (400, -1000)  # after its random episode of 200 steps
    assert pets["curves"][1][0] == (300, -900)
    ours = side.ours(OURS)
    published = [json.loads((OURS / f"seed{s}" / "results.json").read_text()) for s in range(5)]
    assert [round(side.last_half(c), 6) for c in ours["curves"]] == [
        round(r["mean_return_last_half"], 6) for r in published
    ]
    text = side.table({"ours": ours, "PETS": pets})
    assert "| PETS | 2 | 4/5 | — | -172 ± 31 (per seed -150, -193) | 1900.0 | 2.00 |" in text
    (tmp_path / "seed1" / "timing.json").unlink()  # a run stopped before its end
    stopped = side.table({"PETS": side.pets(tmp_path, "pendulum")})
    assert "| PETS | 2 | 4/5 | — | -172 ± 31 (per seed -150, -193) | 1900.0 | 2.00 |" in stopped
    out = tmp_path / "curves.png"
    side.plot({"ours": ours, "PETS": pets}, out, "Pendulum-v1")
    assert out.stat().st_size > 1000
