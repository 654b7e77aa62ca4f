"""Keep torch's thread count where the run set it while TorchRL's batched envs start and close.

TorchRL's ``SerialEnv``/``ParallelEnv`` reset ``torch.set_num_threads`` when they close (to the
count torch had when ``torchrl`` was imported, e.g. 1 -> 2 on a 2-core machine), so a recipe's
``threads: 1`` would silently become 2 after the first batched collection.
"""

from __future__ import annotations

from collections.abc import Iterator
from contextlib import contextmanager

import torch
from torchrl.envs import EnvBase


@contextmanager
def keep_num_threads() -> Iterator[int]:
    """Restore ``torch.get_num_threads()`` on exit, whatever the block did to it.

    Examples:
        >>> import torch
        >>> before = torch.get_num_threads()
        >>> with keep_num_threads():
        ...     torch.set_num_threads(before + 1)
        >>> torch.get_num_threads() == before
        True
    """
    threads = torch.get_num_threads()
    try:
        yield threads
    finally:
        if torch.get_num_threads() != threads:
            torch.set_num_threads(threads)


def close_env(env: EnvBase) -> None:
    """Close ``env`` (a no-op if it is closed already) without changing torch's thread count.

    Examples:
        >>> from torchrl_recon.envs import make_env
        >>> env = make_env("drone", seed=0, num_envs=2, parallel=False)
        >>> close_env(env); close_env(env)
        >>> env.is_closed
        True
    """
    with keep_num_threads():
        env.close(raise_if_closed=False)


@contextmanager
def closing_env(env: EnvBase) -> Iterator[EnvBase]:
    """``with closing_env(make_env(...)) as env:``: :func:`close_env` on the way out, also when
    the block raises or is interrupted (a batched env's workers do not outlive a failed stage).

    Examples:
        >>> from torchrl_recon.envs import make_env
        >>> try:
        ...     with closing_env(make_env("drone", seed=0)) as env:
        ...         raise KeyboardInterrupt
        ... except KeyboardInterrupt:
        ...     env.is_closed
        True
    """
    try:
        yield env
    finally:
        close_env(env)
