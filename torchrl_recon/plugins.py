"""Parts named in a recipe: a key of a registry (a shipped class) or a class of the user's own
(``my_planners:MyPlanner``), with the keywords of that class.

A registry is a plain ``{name: class}`` dict (:data:`torchrl_recon.planners.registry.PLANNERS`,
:data:`torchrl_recon.estimators.ESTIMATORS`); :func:`resolve_class` looks a name up there or
imports ``module:Class`` and checks it subclasses the part's base class;
:func:`check_keywords` checks a recipe's ``kwargs`` against the class's signature before
anything is built. Both raise one line naming what is wrong and what was expected.
"""

from __future__ import annotations

import importlib
import inspect
from collections.abc import Mapping, Sequence
from typing import Any, TypeVar

__all__ = ["check_keywords", "import_object", "resolve_class"]

T = TypeVar("T")


def import_object(spec: str, what: str) -> Any:
    """The attribute ``Name`` of ``module`` for ``"module:Name"`` (importing ``module`` runs its
    code, as any import does).

    Raises:
        ValueError: one line: ``spec`` is not ``module:Name``, the module cannot be imported
            (or fails while importing), or it has no such attribute.

    Examples:
        >>> import_object("torchrl_recon.planners:CEMPlanner", "planner").__name__
        'CEMPlanner'
        >>> import_object("torchrl_recon.planners:NoSuchPlanner", "planner")
        Traceback (most recent call last):
        ...
        ValueError: planner 'torchrl_recon.planners:NoSuchPlanner': module 'torchrl_recon.planners' has no attribute 'NoSuchPlanner'; its own: [].
    """
    module, _, name = str(spec).partition(":")
    if not module or not name or ":" in name:
        raise ValueError(f"{what} must be 'module:Name', got {spec!r}.")
    where = f"{what} {spec!r}"
    try:
        mod = importlib.import_module(module)
    except ModuleNotFoundError as e:
        raise ValueError(
            f"{where}: cannot import module {module!r} ({e}); put the folder holding "
            f"{module.split('.')[0]}.py on PYTHONPATH (e.g. PYTHONPATH=. torchrl-recon ...)."
        ) from None
    except Exception as e:  # the user's module fails while importing
        raise ValueError(
            f"{where}: importing module {module!r} failed: {type(e).__name__}: {e}"
        ) from None
    if not hasattr(mod, name):
        raise ValueError(
            f"{where}: module {module!r} has no attribute {name!r}; its own: {_own_names(mod)}."
        )
    return getattr(mod, name)


def _own_names(module: Any) -> list[str]:
    """The public functions and classes ``module`` defines itself (not those it imports)."""
    return sorted(
        n
        for n, v in vars(module).items()
        if callable(v)
        and not n.startswith("_")
        and getattr(v, "__module__", None) == module.__name__
    )


def resolve_class(spec: str, registry: Mapping[str, type[T]], base: type[T], what: str) -> type[T]:
    """The class a recipe's ``kind`` names: a key of ``registry``, or ``module:Class`` (a
    subclass of ``base``, imported).

    Args:
        spec: a key of ``registry``, or ``"my_planners:MyPlanner"``.
        registry: the shipped classes by name.
        base: the class every part of this kind derives from.
        what: the part's name in messages (``"planner"``).

    Raises:
        ValueError: one line: an unknown name (listing the shipped ones), a module or class
            that cannot be imported, or a class that is not a subclass of ``base``.

    Examples:
        >>> registry = {"dict": dict}
        >>> resolve_class("dict", registry, dict, "mapping").__name__
        'dict'
        >>> resolve_class("collections:OrderedDict", registry, dict, "mapping").__name__
        'OrderedDict'
        >>> resolve_class("collections:deque", registry, dict, "mapping")
        Traceback (most recent call last):
        ...
        ValueError: mapping 'collections:deque' is not a subclass of builtins.dict.
    """
    if spec in registry:
        return registry[spec]
    if ":" not in str(spec):
        raise ValueError(
            f"unknown {what} {spec!r}; expected one of {sorted(registry)} or 'module:Class' "
            f"(a subclass of {base.__module__}.{base.__name__} in a module on PYTHONPATH)."
        )
    cls = import_object(spec, what)
    if not (isinstance(cls, type) and issubclass(cls, base)):
        raise ValueError(f"{what} {spec!r} is not a subclass of {base.__module__}.{base.__name__}.")
    return cls


def check_keywords(
    cls: type,
    kwargs: Mapping[str, Any],
    *,
    positional: int = 0,
    keywords: Sequence[str] = (),
    given_by: str = "",
) -> None:
    """Check that ``cls(<positional>, <keywords>, **kwargs)`` binds, as the builder calls it:
    every keyword is one ``cls`` takes, none is one the builder passes itself, none required
    is missing.

    Args:
        cls: the class to be built.
        kwargs: the recipe's keywords of it.
        positional: how many arguments the builder passes by position (first).
        keywords: the keywords the builder passes itself.
        given_by: where the builder's ``keywords`` come from, for the message.

    Raises:
        TypeError: one line naming the class, the keywords at fault and those it accepts.

    Examples:
        >>> class Part:
        ...     def __init__(self, model, *, horizon, steps=5): ...
        >>> check_keywords(Part, {"horizon": 3}, positional=1)
        >>> check_keywords(Part, {"horizon": 3, "step": 2}, positional=1)
        Traceback (most recent call last):
        ...
        TypeError: Part does not accept ['step']; it accepts ['horizon', 'steps'].
        >>> check_keywords(Part, {"steps": 2}, positional=1)
        Traceback (most recent call last):
        ...
        TypeError: Part needs ['horizon'] (no default).
    """
    name = getattr(cls, "__qualname__", repr(cls))
    try:
        signature = inspect.signature(cls)
    except (TypeError, ValueError):  # no signature to read (a builtin): the call will tell
        return
    params = list(signature.parameters.values())
    by_position = [p.name for p in params if p.kind in (p.POSITIONAL_ONLY, p.POSITIONAL_OR_KEYWORD)]
    taken = set(by_position[:positional]) | set(keywords)
    own = [
        p
        for p in params
        if p.name not in taken and p.kind in (p.POSITIONAL_OR_KEYWORD, p.KEYWORD_ONLY)
    ]
    accepted = sorted(p.name for p in own)
    clash = sorted(set(kwargs) & taken)
    if clash:
        source = f" (from {given_by})" if given_by else ""
        raise TypeError(
            f"{name} gets {clash} from the recipe already{source}; give them there, not in kwargs."
        )
    var_keyword = any(p.kind is p.VAR_KEYWORD for p in params)
    if not var_keyword:
        unknown = sorted(set(kwargs) - set(accepted))
        if unknown:
            raise TypeError(f"{name} does not accept {unknown}; it accepts {accepted}.")
    missing = sorted(p.name for p in own if p.default is p.empty and p.name not in kwargs)
    if missing:
        raise TypeError(f"{name} needs {missing} (no default).")
    try:  # whatever else the signature refuses (keywords the builder passes it lacks, ...)
        signature.bind(*(None,) * positional, **dict.fromkeys(keywords), **kwargs)
    except TypeError as e:
        raise TypeError(
            f"{name} cannot be called as {name}(<{positional} positional>"
            f"{''.join(', ' + k + '=...' for k in keywords)}, **kwargs): {e}."
        ) from None
