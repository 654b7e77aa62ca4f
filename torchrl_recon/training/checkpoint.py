"""Self-contained checkpoints: module class, constructor config and weights (with normalisation)."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import torch
from torch import nn

from torchrl_recon._files import write_atomically

FORMAT_VERSION = 1


def _module_classes() -> dict[str, type[nn.Module]]:
    from torchrl_recon.modules import (
        EnsembleUncertainty,
        LSTMWorldModel,
        MCDropoutUncertainty,
        ReconstructionUncertainty,
        RNDUncertainty,
    )

    return {
        cls.__name__: cls
        for cls in (
            LSTMWorldModel,
            ReconstructionUncertainty,
            EnsembleUncertainty,
            MCDropoutUncertainty,
            RNDUncertainty,
        )
    }


def save_checkpoint(
    path: str | Path, modules: dict[str, nn.Module], *, extra: dict[str, Any] | None = None
) -> None:
    """Atomically write ``modules`` (each with a ``config()`` method) and plain-data ``extra`` to ``path``.

    Examples:
        >>> import tempfile
        >>> from torchrl_recon.modules import LSTMWorldModel
        >>> path = Path(tempfile.mkdtemp()) / "model.pt"
        >>> save_checkpoint(path, {"world_model": LSTMWorldModel(6, 3)})
        >>> load_modules(path)["world_model"].obs_dim
        6
    """
    payload = {
        "format": FORMAT_VERSION,
        "modules": {
            name: {"class": type(m).__name__, "config": m.config(), "state_dict": m.state_dict()}
            for name, m in modules.items()
        },
        "extra": extra or {},
    }
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    write_atomically(path, lambda tmp: torch.save(payload, tmp))


def _read(path: str | Path) -> dict:
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"No checkpoint at {path}.")
    payload = torch.load(path, map_location="cpu", weights_only=True)
    if not isinstance(payload, dict) or payload.get("format") != FORMAT_VERSION:
        raise ValueError(f"{path} is not a torchrl_recon checkpoint of format {FORMAT_VERSION}.")
    return payload


def load_checkpoint(path: str | Path, modules: dict[str, nn.Module]) -> dict[str, Any]:
    """Load weights into existing ``modules``; a class or config mismatch is a clear error. Returns ``extra``."""
    payload = _read(path)
    for name, module in modules.items():
        if name not in payload["modules"]:
            raise KeyError(
                f"Checkpoint {path} has no module {name!r}; it has {sorted(payload['modules'])}."
            )
        saved = payload["modules"][name]
        if saved["class"] != type(module).__name__:
            raise ValueError(
                f"Checkpoint {path}: {name!r} is a {saved['class']}, not a {type(module).__name__}."
            )
        if saved["config"] != module.config():
            diff = {
                k: (saved["config"].get(k), v)
                for k, v in module.config().items()
                if saved["config"].get(k) != v
            }
            raise ValueError(
                f"Checkpoint {path}: {name!r} config mismatch (saved, expected): {diff}."
            )
        module.load_state_dict(saved["state_dict"])
    return payload["extra"]


def load_modules(path: str | Path) -> dict[str, nn.Module]:
    """Rebuild every module stored in ``path`` from its saved config and weights."""
    payload = _read(path)
    classes = _module_classes()
    out = {}
    for name, saved in payload["modules"].items():
        if saved["class"] not in classes:
            raise ValueError(
                f"Checkpoint {path}: unknown module class {saved['class']!r}; expected one of {sorted(classes)}."
            )
        module = classes[saved["class"]](**saved["config"])
        module.load_state_dict(saved["state_dict"])
        out[name] = module
    return out
