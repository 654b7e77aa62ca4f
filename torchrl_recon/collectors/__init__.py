"""Data collection: random exploration (and, on the planning engine, guided exploration)."""

from __future__ import annotations

from torchrl_recon.collectors.random import collect_random

__all__ = ["collect_random"]
