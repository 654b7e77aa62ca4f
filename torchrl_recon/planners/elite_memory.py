"""Remember a plan's elites and find them again from the warm start the next plan gets."""

from __future__ import annotations

import torch

__all__ = ["EliteMemory"]

MEMORY_ROWS = 256
"""Plans :class:`EliteMemory` keeps at most, newest first (more only while one call has more)."""


def shift_index(horizon: int, device: torch.device) -> torch.Tensor:
    """``[H, H]``: row s lists the steps of a plan shifted by s, padded with its last step."""
    steps = torch.arange(horizon, device=device)
    return (steps[:, None] + steps[None, :]).clamp(max=horizon - 1)


class EliteMemory:
    """The elites of earlier plans, found again by the warm start derived from their plan.

    iCEM carries the elites of one time step's search, shifted by the steps executed since,
    into the next one (Pinneri et al. 2020). A planner is called with rows of contexts that
    may differ from call to call (:class:`~torchrl_recon.policies.MPCPolicy` re-plans only the
    rows that need it) and with the previous plan shifted by however many steps were executed,
    as ``init``. So the memory keys each remembered row by its plan: a warm start that equals a
    remembered plan shifted by s steps and padded with its last action (exactly what
    ``MPCPolicy`` passes) recalls that row's elites shifted by the same s steps and padded the
    same way. Other warm starts recall nothing. A recalled row is forgotten (it is consumed);
    rows not recalled are kept, newest first, up to ``MEMORY_ROWS``.

    Examples:
        >>> memory = EliteMemory()
        >>> plan = torch.arange(4.0).view(1, 4, 1)  # one row, H = 4, M = 1
        >>> memory.remember(plan, plan[:, None] + torch.tensor([0.0, 10.0]).view(1, 2, 1, 1))
        >>> elites, found = memory.recall(torch.tensor([[[1.0], [2.0], [3.0], [3.0]]]))  # shifted by 1
        >>> found.tolist(), elites[0, :, :, 0].tolist()
        ([True], [[1.0, 2.0, 3.0, 3.0], [11.0, 12.0, 13.0, 13.0]])
        >>> memory.recall(torch.tensor([[[1.0], [2.0], [3.0], [3.0]]])) is None  # consumed
        True
    """

    def __init__(self) -> None:
        self.plans: torch.Tensor | None = None  # [R', H, M]
        self.elites: torch.Tensor | None = None  # [R', E, H, M]

    def forget(self) -> None:
        """Drop every remembered row."""
        self.plans = self.elites = None

    def remember(self, plans: torch.Tensor, elites: torch.Tensor) -> None:
        """Remember ``elites`` ``[R, E, H, M]`` of the rows whose plans are ``plans`` ``[R, H, M]``."""
        if self.plans is not None and (
            self.elites.shape[1:] != elites.shape[1:] or self.plans.device != plans.device
        ):
            self.forget()
        if self.plans is not None:
            keep = max(MEMORY_ROWS - len(plans), 0)
            plans = torch.cat([plans, self.plans[:keep]])
            elites = torch.cat([elites, self.elites[:keep]])
        self.plans, self.elites = plans, elites

    def recall(self, init: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor] | None:
        """The remembered elites ``[R, E, H, M]`` for warm starts ``init`` ``[R, H, M]``, shifted
        as ``init`` is, with a ``[R]`` mask of the rows found (other rows: zeros); None when no
        row is found. Where several remembered rows or shifts match, the first (newest row,
        smallest shift) is taken."""
        plans, elites = self.plans, self.elites
        if (
            plans is None
            or plans.shape[1:] != init.shape[1:]
            or plans.device != init.device
            or plans.dtype != init.dtype
        ):
            return None
        shifts = shift_index(init.shape[-2], init.device)  # [S, H]
        # First actions first: init[r, 0] == plans[r', s], then the whole shifted plan.
        hits = (init[:, None, None, 0, :] == plans[None]).all(-1).nonzero()  # [P, 3]: r, r', s
        if len(hits) == 0:
            return None
        r, source, s = hits.unbind(-1)
        shifted = plans[source].gather(-2, shifts[s][..., None].expand(-1, -1, init.shape[-1]))
        hits = hits[(shifted == init[r]).flatten(1).all(-1)]
        if len(hits) == 0:
            return None
        # hits are sorted by r: the first of each row's run.
        _, counts = hits[:, 0].unique_consecutive(return_counts=True)
        r, source, s = hits[counts.cumsum(0) - counts].unbind(-1)
        index = shifts[s][:, None, :, None].expand(-1, elites.shape[1], -1, elites.shape[-1])
        found = torch.zeros(len(init), dtype=torch.bool, device=init.device)
        found[r] = True
        out = elites.new_zeros(len(init), *elites.shape[1:])
        out[r] = elites[source].gather(-2, index)
        unused = torch.ones(len(plans), dtype=torch.bool, device=plans.device)
        unused[source] = False
        self.plans, self.elites = plans[unused], elites[unused]
        if not unused.any():
            self.forget()
        return out, found
