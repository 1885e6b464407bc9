"""numba, where installed (the ``fast`` extra): compiled loops that cannot be vectorized.

:data:`HAVE_NUMBA` says whether it is installed (and not switched off by
``GREYBOX_NO_NUMBA=1``); :func:`lazy_njit` compiles a function
on its first call (numba imported then, 80 ms, not at ``import greybox``) and caches the
machine code on disk, so a later process loads it in ~0.1 s instead of compiling. The
callers keep a NumPy/SciPy path for a machine without numba.
"""

from __future__ import annotations

import importlib.util
import os
import threading
from collections.abc import Callable

#: numba installed and not switched off (``GREYBOX_NO_NUMBA=1`` runs the NumPy/SciPy
#: paths: a comparison, or a machine where numba misbehaves).
HAVE_NUMBA = importlib.util.find_spec("numba") is not None and \
    os.environ.get("GREYBOX_NO_NUMBA", "") != "1"


def compile_once(build: Callable) -> Callable[[], object]:
    """``get()``: ``build(numba)`` run on the first call only (under a lock: a fleet's
    threads may reach it together), its result returned on every call."""
    done: list = []
    lock = threading.Lock()

    def get():
        if not done:
            with lock:
                if not done:
                    import numba

                    done.append(build(numba))
        return done[0]
    return get


def lazy_njit(fn: Callable) -> Callable:
    """``fn`` compiled by ``numba.njit(cache=True)`` on its first call.

    Only for a function that calls no other compiled function (a kernel with compiled
    helpers builds them together with :func:`compile_once`, see :mod:`greybox.lawsim`)."""
    get = compile_once(lambda numba: numba.njit(cache=True)(fn))

    def call(*args):
        return get()(*args)

    call.__wrapped__ = fn
    call.__doc__ = fn.__doc__
    return call
