"""Checkpoints that read as weights but are not well-formed are refused in one line, and a
refused load leaves the modules it was given as they were."""

from __future__ import annotations

import pytest
import torch

from torchrl_recon.errors import DamagedFileError
from torchrl_recon.fitting.checkpoint import load_checkpoint, load_modules, save_checkpoint
from torchrl_recon.modules import LSTMWorldModel, ReconstructionUncertainty


def _models(seed: int) -> dict[str, torch.nn.Module]:
    torch.manual_seed(seed)
    return {
        "world_model": LSTMWorldModel(3, 2, window=4),
        "uncertainty": ReconstructionUncertainty(3, 2, window=4, hidden_size=8),
    }


def _damaged(tmp_path, damage) -> str:
    """A checkpoint of :func:`_models` rewritten (still weights and plain data) by ``damage``."""
    path = tmp_path / "m.pt"
    save_checkpoint(path, _models(0), extra={"step": 3})
    payload = torch.load(path, weights_only=True)
    damage(payload)
    torch.save(payload, path)
    return str(path)


def _state(payload: dict, name: str = "world_model") -> dict:
    return payload["modules"][name]["state_dict"]


STRUCTURE = {
    "modules not a dict": (
        lambda p: p.update(modules=[]),
        "a checkpoint holds dicts 'modules' and 'extra'",
    ),
    "no extra": (lambda p: p.pop("extra"), "a checkpoint holds dicts 'modules' and 'extra'"),
    "entry without weights": (
        lambda p: p["modules"]["world_model"].pop("state_dict"),
        "module 'world_model' is not a dict of 'class', 'config' and a tensor 'state_dict'",
    ),
    "a weight that is a number": (
        lambda p: _state(p).update({"head.bias": 1.0}),
        "module 'world_model' is not a dict of 'class', 'config' and a tensor 'state_dict'",
    ),
    "class not a string": (
        lambda p: p["modules"]["world_model"].update({"class": 3}),
        "module 'world_model' is not a dict of 'class', 'config' and a tensor 'state_dict'",
    ),
}


@pytest.mark.parametrize("case", list(STRUCTURE))
def test_a_checkpoint_of_the_wrong_structure_is_refused_by_both_loaders(case, tmp_path):
    damage, expected = STRUCTURE[case]
    path = _damaged(tmp_path, damage)
    for load in (lambda: load_modules(path), lambda: load_checkpoint(path, _models(1))):
        with pytest.raises(DamagedFileError) as err:
            load()
        message = str(err.value)
        assert expected in message and path in message and "\n" not in message, message


def test_weights_that_do_not_fit_are_named_and_change_no_module(tmp_path):
    # the second module's weight is the wrong size: the first, which fits, must not load either
    path = _damaged(
        tmp_path, lambda p: _state(p, "uncertainty").update({"decoder.bias": torch.zeros(2)})
    )
    models = _models(1)
    before = {n: {k: v.clone() for k, v in m.state_dict().items()} for n, m in models.items()}
    with pytest.raises(DamagedFileError) as err:
        load_checkpoint(path, models)
    message = str(err.value)
    assert "the weights of 'uncertainty' do not fit its saved config" in message, message
    assert "decoder.bias" in message and "[2]" in message and "\n" not in message, message
    for name, module in models.items():
        for key, value in module.state_dict().items():
            assert torch.equal(value, before[name][key]), (name, key)
    with pytest.raises(DamagedFileError, match=r"decoder\.bias"):
        load_modules(path)


def test_a_missing_weight_is_named(tmp_path):
    path = _damaged(tmp_path, lambda p: _state(p).pop("head.weight"))
    with pytest.raises(DamagedFileError, match=r"Missing key\(s\).*head\.weight"):
        load_checkpoint(path, _models(1))


def test_a_saved_config_that_builds_nothing_is_refused(tmp_path):
    path = _damaged(tmp_path, lambda p: p["modules"]["world_model"]["config"].update(window=-1))
    with pytest.raises(DamagedFileError, match="the saved config of 'world_model' does not build"):
        load_modules(path)
    with pytest.raises(ValueError, match="config mismatch"):  # the module given has window 4
        load_checkpoint(path, _models(1))


def test_an_unknown_class_is_refused_without_importing_anything(tmp_path):
    path = _damaged(tmp_path, lambda p: p["modules"]["world_model"].update({"class": "os.system"}))
    with pytest.raises(ValueError, match="unknown module class 'os.system'"):
        load_modules(path)
    with pytest.raises(ValueError, match="is a os.system, not a LSTMWorldModel"):
        load_checkpoint(path, _models(1))


def test_a_good_checkpoint_still_loads_every_module(tmp_path):
    path = tmp_path / "m.pt"
    saved = _models(0)
    save_checkpoint(path, saved, extra={"step": 3})
    models = _models(1)
    assert load_checkpoint(path, models) == {"step": 3}
    for name, module in models.items():
        for key, value in module.state_dict().items():
            torch.testing.assert_close(value, saved[name].state_dict()[key])
