"""Shared fixtures: small world models and estimators trained once per session on real env data
(``tests/trained.py``).

The whole suite runs on one thread (torch here, OpenMP/MKL in any subprocess a test starts):
timing-sensitive tests slow down 10-60x when torch uses 2 threads on a loaded machine. This file
imports no torch itself: the pytest-xdist controller loads it and runs no test (importing torch
and the library took it ~5 s before it started its workers).
"""

from __future__ import annotations

import logging
import os

import pytest

for _var in ("OMP_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ[_var] = "1"  # inherited by every subprocess a test starts (collectors, the CLI)


def pytest_configure(config: pytest.Config) -> None:
    """One torch thread wherever tests run (a worker, or the one process without xdist)."""
    controller = not hasattr(config, "workerinput") and config.getoption("numprocesses", None)
    if controller:
        return
    import torch

    torch.set_num_threads(1)
    logging.getLogger("torchrl").setLevel(logging.WARNING)


@pytest.fixture(scope="session")
def trained_models(tmp_path_factory):
    """``trained_models(name)`` → dict with data, world model and estimator, trained once per env
    and test run: under pytest-xdist the first worker to ask trains and saves it (tensors only,
    read back with ``weights_only``), the others load it."""
    from tests.trained import train_models, train_once

    cache = {}
    shared = None
    if os.environ.get("PYTEST_XDIST_WORKER"):  # this run's folder, common to its workers
        shared = tmp_path_factory.getbasetemp().parent / "trained_models"
        shared.mkdir(exist_ok=True)

    def get(name: str) -> dict:
        if name not in cache:
            cache[name] = train_models(name) if shared is None else train_once(name, shared)
        return cache[name]

    return get


@pytest.fixture(params=["aot_eager", pytest.param("inductor", marks=pytest.mark.slow)])
def compile_backend(request, monkeypatch):
    """What ``torch.compile`` builds with in a test of a compiled fit or pass: ``aot_eager`` in
    make test (Dynamo and AOTAutograd, forward and backward, no C++ build: seconds; the blocks of
    a threaded pass then hold the GIL, so their logic is checked, not their speed; Inductor's
    options and mode are dropped), Inductor as the library asks for it in make test-all (tens
    of seconds a build with a cold cache, as on a fresh machine). The planners' kept compiled
    passes are dropped before and after, so none built with the other backend is reused."""
    import torch

    from torchrl_recon.planners import executors

    if request.param == "aot_eager":
        real = torch.compile

        def traced(fn, *, fullgraph=False, dynamic=None, **_):
            return real(fn, fullgraph=fullgraph, dynamic=dynamic, backend="aot_eager")

        monkeypatch.setattr(torch, "compile", traced)
    for kept in (executors.compiled_pass, executors.threaded_pass):
        kept.cache_clear()
    yield request.param
    for kept in (executors.compiled_pass, executors.threaded_pass):
        kept.cache_clear()
