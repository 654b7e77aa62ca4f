"""Errors the library raises for bad input, damaged files and a machine that lacks what a run
asks for (the CLI maps them to exit code 2)."""

from __future__ import annotations

__all__ = ["CompilerNotFoundError", "DamagedFileError", "RecipeError"]


class DamagedFileError(ValueError):
    """A file the library reads back is missing, truncated, altered or would run code.

    The message names the file, what was expected and what to do (e.g. delete the stage record
    that wrote it, so that the stage is computed again).

    Examples:
        >>> issubclass(DamagedFileError, ValueError)
        True
    """


class RecipeError(ValueError):
    """A recipe or an override is not valid: unknown key, wrong type, bad value, no composition.

    The message names the recipe file and every offending key.

    Examples:
        >>> issubclass(RecipeError, ValueError)
        True
    """


class CompilerNotFoundError(RuntimeError):
    """``compile=True`` on the CPU, and torch.compile cannot build its kernels: no C++ compiler
    on ``PATH`` (``torchrl_recon.devices.check_compile_support``).

    Examples:
        >>> issubclass(CompilerNotFoundError, RuntimeError)
        True
    """
