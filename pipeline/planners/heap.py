"""A 4-ary min-heap over two parallel arrays (keys, items), for numba kernels.

Generic over dtypes (numba compiles one version per signature): the fill uses float32 keys
and int32 items, the searches float64 keys and int64 items. Ties pop in no set order.
"""

from __future__ import annotations

import numpy as np

from ..runtime.jit import njit


@njit(cache=True)
def heap_push(keys, items, n, key, item):
    """Insert (key, item) into the heap of size ``n``; returns the new size."""
    k = n
    while k > 0:
        p = (k - 1) >> 2
        if key < keys[p]:
            keys[k] = keys[p]
            items[k] = items[p]
            k = p
        else:
            break
    keys[k] = key
    items[k] = item
    return n + 1


@njit(cache=True)
def heap_pop(keys, items, n):
    """Remove the smallest entry of the heap of size ``n``; returns (key, item)."""
    key = keys[0]
    item = items[0]
    n -= 1
    last_k = keys[n]
    last_i = items[n]
    k = 0
    while True:
        c = 4 * k + 1
        if c >= n:
            break
        m = c
        mk = keys[c]
        for j in range(c + 1, min(c + 4, n)):
            if keys[j] < mk:
                mk = keys[j]
                m = j
        if mk < last_k:
            keys[k] = mk
            items[k] = items[m]
            k = m
        else:
            break
    keys[k] = last_k
    items[k] = last_i
    return key, item


@njit(cache=True)
def grown(arr, n, size):
    """A new array of ``size`` entries (arr's dtype) holding ``arr``'s first ``n``.

    An element loop, not a slice copy (``new[:n] = arr[:n]``): numba compiles a slice copy
    with the text of its shape-mismatch error (string formatting: seconds of the first kernel
    compiled in each process on a new machine; the warm-up, the workers)."""
    new = np.empty(size, dtype=arr.dtype)
    for j in range(n):
        new[j] = arr[j]
    return new


@njit(cache=True)
def heap_reserve(keys, items, n, extra):
    """The heap's arrays with room for ``extra`` more entries beyond its size ``n`` (doubled, or
    more, when short; lazy deletion can hold a node several times).

    Call it outside a search's inner loop, never inside: an array variable that the loop may
    reassign costs numba a reference-count update on every pass (RA* took half as long
    again)."""
    if n + extra <= keys.size:
        return keys, items
    size = max(2 * keys.size, n + extra)
    return grown(keys, n, size), grown(items, n, size)
