"""A bounded cache of a filter's data-independent part: gains and covariances.

The covariance recursion of a linear filter (and of its smoother) depends on the model's
matrices, Q, R and P0 only, not on the measured record. ``close_the_loop`` runs the
filter of one channel several times on one record (the trace, the higher orders, the
input lags), a test or a study runs one model on many records (seeds, a fleet of
machines of one design); each of those paid the time-varying part of the recursion
again (up to thousands of steps with ``tol = 1e-12``), ~20 % of a suite run.

The key is the exact bytes of every array (with its shape and dtype) and the other
arguments' ``repr``: a hit returns what the same computation returned, to the bit.
Cached arrays are made read-only, so that a caller that would change one in place fails
loudly instead of changing the next caller's result. The cache holds at most
``MAX_BYTES`` of arrays per process (least recently used first out).
"""

from __future__ import annotations

import hashlib
from collections import OrderedDict
from collections.abc import Callable
from typing import Any

import numpy as np

MAX_BYTES = 256 * 2**20  # [bytes] per process


def array_key(*items: Any) -> str:
    """A digest of ``items``: arrays by shape, dtype and bytes, anything else by ``repr``."""
    h = hashlib.blake2b(digest_size=20)
    for x in items:
        if isinstance(x, np.ndarray):
            a = np.ascontiguousarray(x)
            h.update(f"{a.shape}{a.dtype.str}".encode())
            h.update(a.tobytes())
        else:
            h.update(repr(x).encode())
        h.update(b"|")
    return h.hexdigest()


def _freeze(value: Any) -> int:
    """Make the arrays of ``value`` (an array, or a tuple / dataclass of them) read-only;
    return their size in bytes."""
    if isinstance(value, np.ndarray):
        value.flags.writeable = False
        return value.nbytes
    if isinstance(value, (tuple, list)):
        return sum(_freeze(v) for v in value)
    if hasattr(value, "__dataclass_fields__"):
        return sum(_freeze(getattr(value, f)) for f in value.__dataclass_fields__)
    return 0


class Memo:
    """Least-recently-used results of pure functions, bounded by the bytes they hold."""

    def __init__(self, max_bytes: int = MAX_BYTES):
        self.max_bytes = max_bytes
        self._items: OrderedDict[str, tuple[Any, int]] = OrderedDict()
        self._bytes = 0
        self.hits = self.misses = 0

    def get(self, key: str) -> Any | None:
        item = self._items.get(key)
        if item is None:
            self.misses += 1
            return None
        self._items.move_to_end(key)
        self.hits += 1
        return item[0]

    def put(self, key: str, value: Any) -> Any:
        size = _freeze(value)
        if size > self.max_bytes // 4:  # one result never takes most of the cache
            return value
        old = self._items.pop(key, None)
        if old is not None:
            self._bytes -= old[1]
        self._items[key] = (value, size)
        self._bytes += size
        while self._bytes > self.max_bytes and self._items:
            _, (_, s) = self._items.popitem(last=False)
            self._bytes -= s
        return value

    def clear(self) -> None:
        self._items.clear()
        self._bytes = 0

    def call(self, fn: Callable[..., Any], *args: Any) -> Any:
        """``fn(*args)``, computed once per distinct ``args`` (arrays compared by bytes)."""
        key = array_key(fn.__qualname__, *args)
        hit = self.get(key)
        return hit if hit is not None else self.put(key, fn(*args))


MEMO = Memo()


def schedule(compute: Callable[[], Any], key_items: tuple, N: int) -> Any:
    """A filter's gain schedule for a record of ``N`` samples, computed once per ``key_items``
    (the model's matrices, Q, R, P0 and the options) in a process.

    ``compute()`` returns a record with ``kconv``: the step at which the gains converged
    (then frozen for the rest of any record), or None if it ran to the record's end. A
    converged schedule serves every record longer than ``kconv`` (the recursion is the
    same up to there, and frozen after); one that ran to the end serves that length only.
    """
    key = array_key(*key_items)
    hit = MEMO.get(key)
    if hit is not None and hit.kconv is not None and hit.kconv < N:
        return hit
    key_n = array_key(*key_items, N)
    hit = MEMO.get(key_n)
    if hit is not None:
        return hit
    sched = compute()
    return MEMO.put(key if sched.kconv is not None else key_n, sched)
