"""One BLAS thread for thin or small matrix products (``threadpoolctl``, optional).

The chunked products of greybox are thin (n x n times n x chunk) or small
(a few hundred rows); a multithreaded BLAS gains nothing on them and, on a
loaded 2-core machine, each call can stall for milliseconds waiting for its
second thread (measured: 0.27 s instead of 0.014 s for 31 chunks of a 6 x 6
product; 32 s instead of ~1.5 s for N4SID at N = 1e6).

The controller is built once: building it scans the loaded libraries, which
costs ~1.5 ms, too much for a call made thousands of times (e.g. inside an
output-error search).
"""

from __future__ import annotations

import contextlib
import functools
import threading

__all__ = ["one_blas_thread", "single_thread_blas"]

_CONTROLLER = None
_LOCAL = threading.local()  # .depth: how many single_thread_blas contexts this thread is in


class _OneThread:
    """The limit of :func:`single_thread_blas`: set on entering the outermost context of a
    thread, restored on leaving it; an inner one only counts (setting the limit costs
    ~10 us, and an output-error search enters one per simulation, ~5 % of its time)."""

    __slots__ = ("_limiter",)

    def __enter__(self):
        depth = getattr(_LOCAL, "depth", 0)
        self._limiter = None if depth else _CONTROLLER.limit(limits=1, user_api="blas")
        _LOCAL.depth = depth + 1
        return self

    def __exit__(self, *exc):
        _LOCAL.depth -= 1
        if self._limiter is not None:
            self._limiter.restore_original_limits()
        return False


def single_thread_blas():
    """Context limiting BLAS to one thread; a no-op without ``threadpoolctl``. Nested
    contexts of one thread set the limit once (the outermost)."""
    global _CONTROLLER
    try:
        from threadpoolctl import ThreadpoolController
    except ImportError:  # pragma: no cover - optional
        return contextlib.nullcontext()
    if _CONTROLLER is None:
        _CONTROLLER = ThreadpoolController()
    return _OneThread()


def one_blas_thread(func):
    """Decorator: run ``func`` under :func:`single_thread_blas` (a whole search of small
    matrix operations: a 6 x 6 ``expm`` took 7.8 ms with two BLAS threads on a busy 2-core
    machine, 0.05 ms with one)."""

    @functools.wraps(func)
    def wrapper(*args, **kwargs):
        with single_thread_blas():
            return func(*args, **kwargs)

    return wrapper
