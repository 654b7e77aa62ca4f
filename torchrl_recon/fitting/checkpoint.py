"""Self-contained checkpoints: module class, constructor config and weights (with normalisation)."""

from __future__ import annotations

import copy
from pathlib import Path
from typing import Any

import torch
from torch import nn

from torchrl_recon.errors import DamagedFileError
from torchrl_recon.runs.files import write_atomically

FORMAT_VERSION = 1
MapLocation = str | torch.device


FORMER_NAMES = {"WorldModelPopulation": "LSTMWorldModel"}
"""Class names older checkpoints hold → the class that loads them (R world models are one
``LSTMWorldModel`` with ``num_members=R`` now)."""


def _module_classes() -> dict[str, type[nn.Module]]:
    """The classes a checkpoint may name: the world model, every registered estimator kind and
    the autoencoder population, and the former names of these."""
    from torchrl_recon.modules import (
        ESTIMATORS,
        LSTMWorldModel,
        ReconstructionPopulation,
        RewardModel,
    )

    classes = {cls.__name__: cls for cls in (LSTMWorldModel, ReconstructionPopulation, RewardModel)}
    classes.update((cls.__name__, cls) for cls in ESTIMATORS.values())
    classes.update((old, classes[new]) for old, new in FORMER_NAMES.items())
    return classes


def _to_cpu(obj: Any) -> Any:
    """``obj`` with every tensor (in dicts, lists, tuples) on the CPU; unchanged if all are.

    A rebuilt ``state_dict`` keeps its ``_metadata`` (the module versions ``load_state_dict``
    reads).
    """
    if isinstance(obj, torch.Tensor):
        return obj if obj.device.type == "cpu" else obj.detach().cpu()
    if isinstance(obj, dict):
        items = {k: _to_cpu(v) for k, v in obj.items()}
        if all(items[k] is v for k, v in obj.items()):
            return obj
        out = type(obj)(items)
        if hasattr(obj, "_metadata"):
            out._metadata = obj._metadata
        return out
    if isinstance(obj, (list, tuple)) and not hasattr(obj, "_fields"):
        items = [_to_cpu(v) for v in obj]
        return obj if all(a is b for a, b in zip(items, obj, strict=True)) else type(obj)(items)
    return obj


def save_checkpoint(
    path: str | Path, modules: dict[str, nn.Module], *, extra: dict[str, Any] | None = None
) -> None:
    """Atomically write ``modules`` (each with a ``config()`` method) and plain-data ``extra`` to ``path``.

    Tensors are saved on the CPU (a checkpoint does not depend on the device it was made on);
    :func:`load_checkpoint` and :func:`load_modules` place them with ``map_location``.

    Examples:
        >>> import tempfile
        >>> from torchrl_recon.modules import LSTMWorldModel
        >>> path = Path(tempfile.mkdtemp()) / "model.pt"
        >>> save_checkpoint(path, {"world_model": LSTMWorldModel(6, 3)})
        >>> load_modules(path)["world_model"].obs_dim
        6
    """
    _check_modules(modules)
    payload = {
        "format": FORMAT_VERSION,
        "modules": {
            name: {
                "class": type(m).__name__,
                "config": _to_cpu(m.config()),
                "state_dict": _to_cpu(m.state_dict()),
            }
            for name, m in modules.items()
        },
        "extra": _to_cpu(extra or {}),
    }
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    write_atomically(path, lambda tmp: torch.save(payload, tmp))


def _check_modules(modules: object) -> None:
    """Refuse ``modules`` unless a dict of names to modules that have a ``config()``."""
    if not isinstance(modules, dict):
        raise TypeError(
            f"modules must be a dict of names to modules, got {type(modules).__name__}."
        )
    for name, module in modules.items():
        if not isinstance(name, str) or not isinstance(module, nn.Module):
            raise TypeError(
                f"modules must map str names to torch modules, got {name!r}: "
                f"{type(module).__name__}."
            )
        if not callable(getattr(module, "config", None)):
            raise TypeError(
                f"modules[{name!r}] is a {type(module).__name__}, which has no config() to "
                "rebuild it from; save the library's modules (or give yours a config())."
            )


def _reason(err: BaseException) -> str:
    text = str(err).strip().splitlines()
    return text[0] if text else type(err).__name__


def _read(path: str | Path, map_location: MapLocation) -> dict:
    """The checkpoint's payload, loaded as weights only and checked for its structure."""
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"No checkpoint at {path}.")
    try:
        payload = torch.load(path, map_location=map_location, weights_only=True)
    except Exception as err:  # truncated, garbage or a pickle that is more than weights
        raise DamagedFileError(
            f"{path} cannot be read as a torchrl_recon checkpoint ({_reason(err)}); it is "
            "truncated, damaged or holds objects other than weights and plain data, and is "
            "never unpickled. Save it again (or delete the stage record that wrote it)."
        ) from None
    if not isinstance(payload, dict) or payload.get("format") != FORMAT_VERSION:
        raise DamagedFileError(
            f"{path} is not a torchrl_recon checkpoint of format {FORMAT_VERSION}."
        )
    modules, extra = payload.get("modules"), payload.get("extra")
    if not isinstance(modules, dict) or not isinstance(extra, dict):
        raise DamagedFileError(f"{path}: a checkpoint holds dicts 'modules' and 'extra'.")
    for name, saved in modules.items():
        if (
            not isinstance(saved, dict)
            or not isinstance(saved.get("class"), str)
            or not isinstance(saved.get("config"), dict)
            or not isinstance(saved.get("state_dict"), dict)
            or not all(isinstance(v, torch.Tensor) for v in saved["state_dict"].values())
        ):
            raise DamagedFileError(
                f"{path}: module {name!r} is not a dict of 'class', 'config' and a tensor "
                "'state_dict'."
            )
    return payload


def _load_state(path: str | Path, name: str, module: nn.Module, state: dict) -> None:
    try:
        module.load_state_dict(state)
    except RuntimeError as err:
        # load_state_dict's message opens with a header line; the first mismatch follows it
        lines = [line.strip() for line in str(err).splitlines() if line.strip()]
        reason = (lines[1] if len(lines) > 1 else _reason(err)).rstrip(".")
        raise DamagedFileError(
            f"{path}: the weights of {name!r} do not fit its saved config ({reason})."
        ) from None


def load_checkpoint(
    path: str | Path, modules: dict[str, nn.Module], *, map_location: MapLocation = "cpu"
) -> dict[str, Any]:
    """Load weights into existing ``modules``; a class or config mismatch is a clear error. Returns ``extra``.

    The file is read with ``torch.load(..., weights_only=True)``: it never runs code. The
    weights are copied into each module's own parameters (so they land on the module's
    device); ``map_location`` places the tensors of the returned ``extra``.

    Raises:
        FileNotFoundError: no file at ``path``.
        DamagedFileError: the file is truncated, garbage, a pickle of objects, not a
            checkpoint of this format, or holds weights that do not fit their saved config.
        KeyError: the file has no module of a requested name.
        ValueError: a stored class or config differs from the module's.

    On any of these errors no module is changed.

    Examples:
        >>> import tempfile
        >>> from torchrl_recon.modules import LSTMWorldModel
        >>> path = Path(tempfile.mkdtemp()) / "model.pt"
        >>> save_checkpoint(path, {"world_model": LSTMWorldModel(6, 3)}, extra={"step": 10})
        >>> load_checkpoint(path, {"world_model": LSTMWorldModel(6, 3)})
        {'step': 10}
    """
    payload = _read(path, map_location)
    for name, module in modules.items():  # every module checked before any is changed
        if name not in payload["modules"]:
            raise KeyError(
                f"Checkpoint {path} has no module {name!r}; it has {sorted(payload['modules'])}."
            )
        saved = payload["modules"][name]
        if FORMER_NAMES.get(saved["class"], saved["class"]) != type(module).__name__:
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
        # load_state_dict copies every tensor that fits before it raises: try a copy first
        _load_state(path, name, copy.deepcopy(module), saved["state_dict"])
    for name, module in modules.items():
        module.load_state_dict(payload["modules"][name]["state_dict"])
    return payload["extra"]


def load_modules(path: str | Path, *, map_location: MapLocation = "cpu") -> dict[str, nn.Module]:
    """Rebuild every module stored in ``path`` from its saved config and weights, on ``map_location``.

    Read with ``weights_only=True`` (never runs code); errors as in :func:`load_checkpoint`.

    Examples:
        >>> import tempfile
        >>> from torchrl_recon.modules import LSTMWorldModel
        >>> path = Path(tempfile.mkdtemp()) / "model.pt"
        >>> save_checkpoint(path, {"world_model": LSTMWorldModel(6, 3)})
        >>> next(load_modules(path, map_location="cpu")["world_model"].parameters()).device
        device(type='cpu')
    """
    payload = _read(path, map_location)
    classes = _module_classes()
    out = {}
    for name, saved in payload["modules"].items():
        if saved["class"] not in classes:
            raise ValueError(
                f"Checkpoint {path}: unknown module class {saved['class']!r}; expected one of {sorted(classes)}."
            )
        try:
            module = classes[saved["class"]](**saved["config"])
        except (TypeError, ValueError) as err:
            raise DamagedFileError(
                f"{path}: the saved config of {name!r} does not build a {saved['class']} "
                f"({_reason(err)})."
            ) from None
        _load_state(path, name, module, saved["state_dict"])
        out[name] = module.to(map_location)
    return out
