"""Shared fixtures: a seeded generator and a factory of random test systems."""

from __future__ import annotations

import os
from types import SimpleNamespace

import numpy as np
import pytest

from greybox import named_ss

# The suite runs on every core (pytest-xdist, `-n auto` in pyproject.toml): each worker
# then keeps BLAS to one thread, and so do the subprocesses it starts (tutorials, the
# CLI), or two workers' BLAS pools would fight over the same cores.
if os.environ.get("PYTEST_XDIST_WORKER"):
    from threadpoolctl import threadpool_limits

    for _var in ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS"):
        os.environ[_var] = "1"
    _BLAS_LIMIT = threadpool_limits(limits=1, user_api="blas")


def _cache_group(module) -> str | None:
    """The xdist group of a module that keeps runs in a process-wide cache (a
    ``functools.lru_cache`` at module level, its own or imported): the module that defines
    the cache, so that every test reading it runs in one worker. Spread over two, each
    worker ran the cached close-the-loop runs its tests asked for (measured: 6 runs of
    3-12 s paid twice in one suite run). None if the module has no cache."""
    homes = sorted({v.__module__ for v in vars(module).values()
                    if callable(v) and hasattr(v, "cache_info")})
    if not homes:
        return None
    others = [h for h in homes if h != module.__name__]
    return others[0] if others else module.__name__


@pytest.hookimpl(tryfirst=True)
def pytest_collection_modifyitems(config, items):
    """Tests that share a module-scoped fixture or a module's cache run in one worker
    (``--dist loadgroup``), unless they name their own group; modules with slow tests run
    first.

    Spread over two workers, each would run the fixture (a close-the-loop run per seed,
    up to a minute each) once: the shared-state law's three seeds ran twice.
    """
    for item in items:
        if item.get_closest_marker("xdist_group"):  # grouped by the test itself
            continue
        info = getattr(item, "_fixtureinfo", None)
        defs = info.name2fixturedefs.values() if info is not None else ()
        if any(d[-1].scope == "module" for d in defs):
            item.add_marker(pytest.mark.xdist_group(item.module.__name__))
        elif (group := _cache_group(item.module)) is not None:
            item.add_marker(pytest.mark.xdist_group(group))
    # modules with slow tests first (each kept whole: a module fixture is set up once): the
    # workers take the long ones early and the short ones fill in at the end
    slow = {item.module.__name__ for item in items if item.get_closest_marker("slow")}
    items.sort(key=lambda item: item.module.__name__ not in slow)


@pytest.fixture
def rng() -> np.random.Generator:
    """A fresh seeded generator for each test (no global seeding)."""
    return np.random.default_rng(20240917)


def make_random_system(rng: np.random.Generator, *, n: int = 3, m: int = 1, p: int = 2,
                       md: int = 1, rho: float = 0.9, dt: float = 0.1,
                       feedthrough: bool = True) -> SimpleNamespace:
    """Random stable discrete model with inputs ``[u0.., d0..]`` satisfying (17).

    A has spectral radius ``rho``; G is redrawn until ``C G`` is well
    conditioned (smallest singular value > 0.2 times the largest), so
    rank(C G) = rank(G) = md holds with a margin. The known inputs may feed
    through (D != 0); the unknown inputs never do. Q is a random positive
    semidefinite matrix, R a random positive definite one.

    Returns a namespace with ``sys`` (control.StateSpace, dt set, named
    signals), the matrices ``A, B, C, D, G, Q, R`` and the labels.
    """
    A = rng.standard_normal((n, n))
    A *= rho / np.max(np.abs(np.linalg.eigvals(A)))
    B = rng.standard_normal((n, m))
    C = rng.standard_normal((p, n))
    D = rng.standard_normal((p, m)) if feedthrough else np.zeros((p, m))
    while True:
        G = rng.standard_normal((n, md))
        s = np.linalg.svd(C @ G, compute_uv=False)
        if s.min() > 0.2 * s.max():
            break
    W = rng.standard_normal((n, n))
    Q = 0.02 * W @ W.T / n
    V = rng.standard_normal((p, p))
    R = 0.01 * (V @ V.T / p + np.eye(p))
    known = [f"u{i}" for i in range(m)]
    unknown = [f"d{j}" for j in range(md)]
    sys = named_ss(A, np.hstack([B, G]), C, np.hstack([D, np.zeros((p, md))]), dt,
                   states=[f"x{i}" for i in range(n)], inputs=known + unknown,
                   outputs=[f"y{i}" for i in range(p)], name="random_system")
    return SimpleNamespace(sys=sys, A=A, B=B, C=C, D=D, G=G, Q=Q, R=R,
                           known=known, unknown=unknown, n=n, m=m, p=p, md=md, dt=dt)


@pytest.fixture(scope="session")
def random_system():
    """The factory :func:`make_random_system` (call it with an ``rng``)."""
    return make_random_system


# Every close_the_loop report the suite computes is checked against its golden snapshot
# (tests/golden_guard.py): installed before the test modules import the entry points.
import golden_guard  # noqa: E402

golden_guard.install()
