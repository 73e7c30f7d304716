"""Semantic configurations and the social partner's oracle graph (SPEC §2, §4; paper appendix
"Representing the social partner's knowledge").

This module owns the predicate layout that every other file uses:

    config = [close{0,1}, close{0,2}, ..., close{n-2,n-1},   # unordered pairs, lexicographic
              above(0,1), above(0,2), ..., above(n-1,n-2)]   # ordered pairs (i on j), lexicographic

with +1.0 for true and -1.0 for false (float32). For 5 blocks that is 10 + 20 = 30 numbers and
index 10 + 4i + (j if j < i else j - 1) is "i on j".
"""

from __future__ import annotations

import functools
import itertools

import numpy as np

MIN_BLOCKS, MAX_BLOCKS = 2, 5


def _frozen(a: np.ndarray) -> np.ndarray:
    """Cached tables are shared by every caller: make them read-only."""
    a.setflags(write=False)
    return a


def check_n_blocks(n_blocks) -> int:
    """Return n_blocks as an int, or raise a ValueError naming the bad value."""
    if isinstance(n_blocks, bool) or not isinstance(n_blocks, (int, np.integer)):
        raise ValueError(f"n_blocks must be an integer in [{MIN_BLOCKS}, {MAX_BLOCKS}], got {n_blocks!r}")
    if not MIN_BLOCKS <= n_blocks <= MAX_BLOCKS:
        raise ValueError(f"n_blocks must be in [{MIN_BLOCKS}, {MAX_BLOCKS}], got {n_blocks}")
    return int(n_blocks)


# ----------------------------------------------------------------------------------------------
# Layout (SPEC §2)
# ----------------------------------------------------------------------------------------------
@functools.cache
def close_pairs(n_blocks: int) -> np.ndarray:
    """(n(n-1)/2, 2) unordered pairs {i, j}, i < j, in lexicographic order."""
    return _frozen(np.array(list(itertools.combinations(range(n_blocks), 2)), dtype=np.int64).reshape(-1, 2))


@functools.cache
def above_pairs(n_blocks: int) -> np.ndarray:
    """(n(n-1), 2) ordered pairs (i, j) meaning "i on j", in lexicographic order."""
    return _frozen(np.array(list(itertools.permutations(range(n_blocks), 2)), dtype=np.int64).reshape(-1, 2))


def config_dim(n_blocks: int) -> int:
    """Number of predicates: n(n-1)/2 close + n(n-1) above (30 for 5 blocks, 9 for 3)."""
    return n_blocks * (n_blocks - 1) // 2 + n_blocks * (n_blocks - 1)


@functools.cache
def predicate_blocks(n_blocks: int) -> np.ndarray:
    """(dim, 2): the two blocks each predicate is about, in layout order."""
    return _frozen(np.concatenate([close_pairs(n_blocks), above_pairs(n_blocks)]))


@functools.cache
def _predicate_index(n_blocks: int) -> dict:
    """Layout index of each predicate: ("close", i, j) with i < j, and ("above", i, j) for i on j."""
    nc = len(close_pairs(n_blocks))
    index = {("close", int(i), int(j)): k for k, (i, j) in enumerate(close_pairs(n_blocks))}
    index.update({("above", int(i), int(j)): nc + k for k, (i, j) in enumerate(above_pairs(n_blocks))})
    return index


def make_config(n_blocks: int, close=(), above=()) -> np.ndarray:
    """The config where exactly the given predicates are true: close={(i, j), ...} (either order),
    above={(i, j), ...} meaning i on j. Example: make_config(5, close=[(0, 1)], above=[(0, 1)])."""
    index = _predicate_index(check_n_blocks(n_blocks))
    config = -np.ones(config_dim(n_blocks), dtype=np.float32)
    try:
        config[[index["close", min(i, j), max(i, j)] for i, j in close]] = 1.0
        config[[index["above", i, j] for i, j in above]] = 1.0
    except KeyError as e:
        raise ValueError(f"no such predicate for {n_blocks} blocks: {e.args[0]}") from None
    return config
