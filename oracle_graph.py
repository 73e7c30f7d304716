"""Semantic configurations and the social partner's oracle graph (SPEC §2, §4; paper appendix
"Representing the social partner's knowledge").

This module owns the predicate layout that every other file uses:

    config = [close{0,1}, close{0,2}, ..., close{n-2,n-1},   # unordered pairs, lexicographic
              above(0,1), above(0,2), ..., above(n-1,n-2)]   # ordered pairs (i on j), lexicographic

with +1.0 for true and -1.0 for false (float32). For 5 blocks that is 10 + 20 = 30 numbers and
index 10 + 4i + (j if j < i else j - 1) is "i on j".
"""

from __future__ import annotations

import argparse
import collections
import functools
import itertools
import sys
import time

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


def describe(config) -> str:
    """Human-readable config: "0 on 1, close(0,1), close(2,3)"; "all apart" when nothing holds."""
    c = np.asarray(config)
    n = n_blocks_of(c.shape[-1])
    on = [f"{i} on {j}" for k, (i, j) in enumerate(above_pairs(n)) if c[len(close_pairs(n)) + k] > 0]
    close = [f"close({i},{j})" for k, (i, j) in enumerate(close_pairs(n)) if c[k] > 0]
    return ", ".join(on + close) or "all apart"


def n_blocks_of(dim: int) -> int:
    """Number of blocks whose configs have `dim` predicates, or a ValueError naming dim."""
    for n in range(MIN_BLOCKS, MAX_BLOCKS + 1):
        if config_dim(n) == dim:
            return n
    raise ValueError(f"no number of blocks in [{MIN_BLOCKS}, {MAX_BLOCKS}] has configs of length {dim}")


# ----------------------------------------------------------------------------------------------
# Bit masks and block permutations (SPEC §2)
# ----------------------------------------------------------------------------------------------
def to_mask(configs) -> np.ndarray:
    """+-1 configs (..., dim) -> int64 bit masks (...), bit k set iff predicate k is true."""
    c = np.asarray(configs)
    return (c > 0).astype(np.int64) @ (np.int64(1) << np.arange(c.shape[-1], dtype=np.int64))


def from_mask(masks, n_blocks: int) -> np.ndarray:
    """int bit masks (...) -> +-1 float32 configs (..., dim)."""
    bits = (np.asarray(masks, dtype=np.int64)[..., None] >> np.arange(config_dim(n_blocks))) & 1
    return (2 * bits - 1).astype(np.float32)


@functools.cache
def permutations(n_blocks: int) -> np.ndarray:
    """(n!, n) every permutation of the blocks; row 0 is the identity."""
    return _frozen(np.array(list(itertools.permutations(range(n_blocks))), dtype=np.int64))


@functools.cache
def _predicate_lookup(n_blocks: int) -> np.ndarray:
    """(2, n, n) layout indices: [0, i, j] = close{i, j} (symmetric), [1, i, j] = above(i on j)."""
    close = np.full((n_blocks, n_blocks), -1, dtype=np.int64)
    for k, (i, j) in enumerate(close_pairs(n_blocks)):
        close[i, j] = close[j, i] = k
    above = np.full((n_blocks, n_blocks), -1, dtype=np.int64)
    for k, (i, j) in enumerate(above_pairs(n_blocks)):
        above[i, j] = len(close_pairs(n_blocks)) + k
    return _frozen(np.stack([close, above]))


@functools.cache
def permutation_targets(n_blocks: int) -> np.ndarray:
    """(n!, dim): permutation p sends predicate k over blocks (a, b) to predicate [p][k] over (p(a), p(b))."""
    lookup = _predicate_lookup(n_blocks)
    pairs = predicate_blocks(n_blocks)
    kind = (np.arange(config_dim(n_blocks)) >= len(close_pairs(n_blocks))).astype(np.int64)
    p = permutations(n_blocks)
    return _frozen(lookup[kind[None, :], p[:, pairs[:, 0]], p[:, pairs[:, 1]]])


@functools.cache
def permutation_sources(n_blocks: int) -> np.ndarray:
    """(n!, dim) gather indices: permuted = config[..., sources[p]] (the inverse of the targets)."""
    tgt = permutation_targets(n_blocks)
    src = np.empty_like(tgt)
    np.put_along_axis(src, tgt, np.arange(tgt.shape[1])[None, :].repeat(len(tgt), 0), axis=1)
    return _frozen(src)


def permute(configs, n_blocks: int | None = None) -> np.ndarray:
    """Every block permutation of configs (..., dim) in one gather: (..., n!, dim)."""
    c = np.asarray(configs)
    return c[..., permutation_sources(n_blocks or n_blocks_of(c.shape[-1]))]


@functools.cache
def _mask_lut(n_blocks: int) -> np.ndarray:
    """(bytes, 256, n!) table: the permuted mask is the OR over the mask's bytes of lut[byte, value]."""
    tgt = permutation_targets(n_blocks)
    dim = tgt.shape[1]
    n_bytes = (dim + 7) // 8
    values = (np.arange(256)[:, None] >> np.arange(8)) & 1  # (256, 8) bits of each byte value
    lut = np.zeros((n_bytes, 256, len(tgt)), dtype=np.int64)
    for b in range(n_bytes):
        k = np.arange(8 * b, min(8 * b + 8, dim))
        lut[b] = values[:, : len(k)] @ (np.int64(1) << tgt[:, k]).T
    return _frozen(lut)


def permute_masks(masks, n_blocks: int) -> np.ndarray:
    """Every block permutation of int masks (...): (..., n!) int64."""
    m = np.asarray(masks, dtype=np.int64)
    lut = _mask_lut(n_blocks)
    out = lut[0][m & 255]
    for b in range(1, len(lut)):
        out = out | lut[b][(m >> (8 * b)) & 255]
    return out


def canonical(configs) -> np.ndarray:
    """Canonical form (...) = min over block permutations of the int mask. Equal iff equivalent."""
    c = np.asarray(configs)
    return permute_masks(to_mask(c), n_blocks_of(c.shape[-1])).min(axis=-1)


# ----------------------------------------------------------------------------------------------
# The one-object rule (paper: "attention bias", SPEC §2)
# ----------------------------------------------------------------------------------------------
@functools.cache
def _outside_masks(n_blocks: int) -> np.ndarray:
    """(n,) int masks: the predicates that block b takes no part in."""
    pairs = predicate_blocks(n_blocks)
    outside = (pairs[None, :, 0] != np.arange(n_blocks)[:, None]) & (pairs[None, :, 1] != np.arange(n_blocks)[:, None])
    return _frozen(outside.astype(np.int64) @ (np.int64(1) << np.arange(config_dim(n_blocks))))


def is_small_step(c1, c2) -> np.ndarray:
    """c1 -> c2 is a small step iff some predicate differs and one block takes part in all that differ."""
    c1, c2 = np.asarray(c1), np.asarray(c2)
    diff = to_mask(c1) ^ to_mask(c2)
    outside = _outside_masks(n_blocks_of(c1.shape[-1]))
    return (diff != 0) & ((diff[..., None] & outside) == 0).any(axis=-1)


# ----------------------------------------------------------------------------------------------
# The 11 evaluation classes (SPEC §4.1)
# ----------------------------------------------------------------------------------------------
# Structured classes as templates over k distinct blocks a, b, c, ... (0, 1, 2, ...): close pairs and
# "x on y" pairs; every injective assignment of real blocks to the template is a member.
_TEMPLATES = {
    "S2": (2, [(0, 1)], [(0, 1)]),
    "S3": (3, [(0, 1), (1, 2)], [(0, 1), (1, 2)]),
    "S2&S2": (4, [(0, 1), (2, 3)], [(0, 1), (2, 3)]),
    "S2&S3": (5, [(0, 1), (2, 3), (3, 4)], [(0, 1), (2, 3), (3, 4)]),
    "P3": (3, [(0, 1), (0, 2), (1, 2)], [(2, 0), (2, 1)]),
    "P3&S2": (5, [(0, 1), (0, 2), (1, 2), (3, 4)], [(2, 0), (2, 1), (3, 4)]),
    "S4": (4, [(0, 1), (1, 2), (2, 3)], [(0, 1), (1, 2), (2, 3)]),
    "S5": (5, [(0, 1), (1, 2), (2, 3), (3, 4)], [(0, 1), (1, 2), (2, 3), (3, 4)]),
}
CLASS_NAMES = ("C1", "C2", "C3", "S2", "S3", "S2&S2", "S2&S3", "P3", "P3&S2", "S4", "S5")


@functools.cache
def evaluation_classes(n_blocks: int) -> dict[str, np.ndarray]:
    """Class name -> (size, dim) configs, in the paper's order, keeping the classes that fit n blocks."""
    n = check_n_blocks(n_blocks)
    classes = {}
    for name in CLASS_NAMES:
        if name[0] == "C":  # exactly i close pairs, every other predicate false
            pairs = [tuple(p) for p in close_pairs(n)]
            members = [make_config(n, close=combo) for combo in itertools.combinations(pairs, int(name[1]))]
        else:
            k, close, above = _TEMPLATES[name]
            members = [
                make_config(n, [(s[a], s[b]) for a, b in close], [(s[a], s[b]) for a, b in above])
                for s in itertools.permutations(range(n), k)
            ]
        if members:
            unique = np.unique(to_mask(np.array(members)))
            classes[name] = _frozen(from_mask(unique, n))
    return classes


# ----------------------------------------------------------------------------------------------
# The oracle graph (SPEC §4; paper appendix "Representing the social partner's knowledge")
# ----------------------------------------------------------------------------------------------
# Drop cells: 4 x 36 (x, y) positions in steps of half a block; a block is 0.9 x 0.9 and one level tall.
GRID_XY = np.array(list(itertools.product(np.arange(0, 2, 0.5), np.arange(0, 18, 0.5))))  # (144, 2)
_D = np.abs(GRID_XY[:, None, :] - GRID_XY[None, :, :])
FOOTPRINT_OVERLAP = np.clip(0.9 - _D[..., 0], 0, None) * np.clip(0.9 - _D[..., 1], 0, None)  # (144, 144)
CLOSE_SQ, ABOVE_SQ = 1 + 1.4**2, 1.9  # grid predicates, squared distances over (level, x, y)
STABLE_OVERLAP = 0.5  # a dropped block rests on what it overlaps by more than this, else the move fails
_EPS = 1e-9


def start_state(n_blocks: int) -> tuple[np.ndarray, np.ndarray]:
    """(cells, levels) of the root: block k on the floor at (x, y) = (0, 3.5 k), all far apart."""
    cells = np.array([int(np.flatnonzero((GRID_XY == (0.0, 3.5 * k)).all(1))[0]) for k in range(n_blocks)])
    return cells, np.zeros(n_blocks, dtype=np.int64)


def all_drops(cells: np.ndarray, levels: np.ndarray) -> np.ndarray:
    """Resting level of every move (block m into cell c) as an (n, 144) array; -1 = not allowed.

    A block can move iff nothing rests on it. Dropped from the top, it falls level by level; at the
    first level where its footprint overlaps blocks, a total overlap > 0.5 makes it rest on top of
    them, a smaller one makes the move unstable (rejected); the floor stops it."""
    n = len(cells)
    overlap = FOOTPRINT_OVERLAP[:, cells]  # (144, n): target cell vs each block's footprint
    on_top = (levels[None, :] == levels[:, None] + 1) & (FOOTPRINT_OVERLAP[cells[:, None], cells[None, :]] > 0)
    movable = ~on_top.any(axis=1)  # (n,) nothing rests on block m
    at_level = (levels[:, None] == np.arange(n)).astype(float)  # (n blocks, n levels)
    others = 1.0 - np.eye(n)  # the moving block does not support itself
    total = np.einsum("ck,mk,kl->mcl", overlap, others, at_level)  # (m, cell, level) overlap per level
    hit = total > _EPS
    top = n - 1 - np.argmax(hit[..., ::-1], axis=-1)  # highest level with any overlap
    support = np.take_along_axis(total, top[..., None], axis=-1)[..., 0]
    rest = np.where(hit.any(-1), np.where(support > STABLE_OVERLAP + _EPS, top + 1, -1), 0)
    rest[rest >= n] = -1
    rest[~movable] = -1
    return rest


def drop(cells, levels, block: int, cell: int):
    """Move `block` into drop cell `cell`: the new (cells, levels), or None if the move is not allowed."""
    cells, levels = np.asarray(cells), np.asarray(levels)
    rest = all_drops(cells, levels)[block, cell]
    if rest < 0:
        return None
    cells, levels = cells.copy(), levels.copy()
    cells[block], levels[block] = cell, rest
    return cells, levels


def grid_config(cells, levels) -> np.ndarray:
    """The semantic config of a grid state (grid predicates of SPEC §4)."""
    p = np.column_stack([levels, GRID_XY[cells]]).astype(float)  # (level, x, y)
    n = len(p)
    d2 = ((p[:, None, :] - p[None, :, :]) ** 2).sum(-1)
    dl = p[:, None, 0] - p[None, :, 0]
    ci, cj = close_pairs(n).T
    ai, aj = above_pairs(n).T
    close = d2[ci, cj] < CLOSE_SQ
    above = (dl[ai, aj] == 1) & (d2[ai, aj] < ABOVE_SQ)
    return np.where(np.concatenate([close, above]), np.float32(1), np.float32(-1))


@functools.cache
def _bit_tables(n_blocks: int):
    """(n, n) int64 bit of close{m, k} and of "m on k" (0 on the diagonal); (n,) masks of m's predicates."""
    lookup = _predicate_lookup(n_blocks)
    bits = np.where(lookup >= 0, np.int64(1) << np.maximum(lookup, 0), 0)
    involving = ~_outside_masks(n_blocks) & ((np.int64(1) << config_dim(n_blocks)) - 1)
    return bits[0], bits[1], involving


def _child_masks(cells, levels, mask: int, rest: np.ndarray) -> np.ndarray:
    """(n, 144) config masks after each move (rest from all_drops): only the moved block's predicates
    change, so they are recomputed against the others and merged into the parent's mask."""
    close_bit, on_bit, involving = _bit_tables(len(cells))
    moved = np.concatenate([rest[..., None], np.broadcast_to(GRID_XY, rest.shape + (2,))], axis=-1)  # (m, c, 3)
    fixed = np.column_stack([levels, GRID_XY[cells]])  # (k, 3)
    delta = moved[:, :, None, :] - fixed[None, None, :, :]  # (m, c, k, 3)
    d2 = (delta**2).sum(-1)
    close = d2 < CLOSE_SQ
    m_on_k = (delta[..., 0] == 1) & (d2 < ABOVE_SQ)
    k_on_m = (delta[..., 0] == -1) & (d2 < ABOVE_SQ)
    new = (close * close_bit[:, None, :] + m_on_k * on_bit[:, None, :] + k_on_m * on_bit.T[:, None, :]).sum(-1)
    return (mask & ~involving)[:, None] | new


def _search_classes(n_blocks: int):
    """Breadth-first search over permutation classes (SPEC §4): expand the first grid state that
    reaches each new class; return the spanning tree's edges as (parent mask, child mask) pairs."""
    cells, levels = start_state(n_blocks)
    root = int(to_mask(grid_config(cells, levels)))
    seen = set(permute_masks(root, n_blocks).tolist())  # every config of every class found so far
    queue = collections.deque([(cells, levels, root)])
    parents, children = [], []
    while queue:
        cells, levels, mask = queue.popleft()
        rest = all_drops(cells, levels)
        child = _child_masks(cells, levels, mask, rest)
        valid = np.flatnonzero(rest.ravel() >= 0)  # moves in (block, cell) order
        uniq, first = np.unique(child.ravel()[valid], return_index=True)
        for i in np.argsort(first):  # first-reached order keeps the search breadth-first and deterministic
            m = int(uniq[i])
            if m in seen:
                continue
            seen.update(permute_masks(m, n_blocks).tolist())
            block, cell = divmod(int(valid[first[i]]), len(GRID_XY))
            new_cells, new_levels = cells.copy(), levels.copy()
            new_cells[block], new_levels[block] = cell, rest[block, cell]
            queue.append((new_cells, new_levels, m))
            parents.append(mask)
            children.append(m)
    return root, np.array(parents, dtype=np.int64), np.array(children, dtype=np.int64)


def bfs_hops(indptr: np.ndarray, indices: np.ndarray, start: int) -> np.ndarray:
    """Edge count from `start` to every node of a CSR graph (-1: unreachable), one numpy pass per level."""
    hops = np.full(len(indptr) - 1, -1, dtype=np.int64)
    hops[start], frontier, d = 0, np.array([start]), 0
    while len(frontier):
        d += 1
        starts, counts = indptr[frontier], indptr[frontier + 1] - indptr[frontier]
        # all CSR rows of the frontier at once: start of each row + offset within it
        offsets = np.arange(counts.sum()) - np.repeat(np.cumsum(counts) - counts, counts)
        nxt = np.unique(indices[np.repeat(starts, counts) + offsets])
        frontier = nxt[hops[nxt] < 0]
        hops[frontier] = d
    return hops


class OracleGraph:
    """The social partner's knowledge (SPEC §4): every permutation of every class the grid search found,
    linked by every permutation of the spanning tree's edges, in both directions.

    Nodes are kept as sorted int masks; adjacency is CSR (indptr, indices) over node indices, so that
    membership and neighbour queries are numpy look-ups."""

    def __init__(self, n_blocks: int = 5):
        start = time.perf_counter()
        self.n_blocks = n = check_n_blocks(n_blocks)
        self.dim = config_dim(n)
        root, parents, children = _search_classes(n)
        self.root_mask = root
        self.tree_edges = np.column_stack([parents, children])  # (classes - 1, 2) masks: one per class found
        self.n_classes = len(children) + 1
        # Lift: the same permutation on both ends of every tree edge.
        src = permute_masks(parents, n).ravel()
        dst = permute_masks(children, n).ravel()
        self.masks = np.unique(np.concatenate([src, dst, permute_masks(root, n)]))
        a, b = np.searchsorted(self.masks, src), np.searchsorted(self.masks, dst)
        pairs = np.unique(np.concatenate([a * len(self.masks) + b, b * len(self.masks) + a]))
        heads, tails = np.divmod(pairs, len(self.masks))
        self.indptr = np.searchsorted(heads, np.arange(len(self.masks) + 1))
        self.indices = tails
        self.build_seconds = time.perf_counter() - start
        self._class_masks = {name: to_mask(c) for name, c in evaluation_classes(n).items()}

    # --- nodes --------------------------------------------------------------------------------
    @property
    def n_nodes(self) -> int:
        return len(self.masks)

    @property
    def n_edges(self) -> int:
        """Directed edges (each adjacency counted in both directions)."""
        return len(self.indices)

    @property
    def nodes(self) -> np.ndarray:
        """(n_nodes, dim) every oracle config, in mask order."""
        return from_mask(self.masks, self.n_blocks)

    def index(self, configs) -> np.ndarray:
        """Node index of each config (...), -1 where it is not an oracle node."""
        m = to_mask(self._check(configs))
        i = np.minimum(np.searchsorted(self.masks, m), len(self.masks) - 1)
        return np.where(self.masks[i] == m, i, -1)

    def contains(self, configs) -> np.ndarray:
        return self.index(configs) >= 0

    def __contains__(self, config) -> bool:
        return bool(self.contains(config))

    # --- edges --------------------------------------------------------------------------------
    def neighbour_indices(self, node: int) -> np.ndarray:
        return self.indices[self.indptr[node] : self.indptr[node + 1]]

    def neighbours(self, config) -> np.ndarray:
        """(k, dim) the oracle neighbours of config (semantically adjacent); empty if not a node."""
        i = int(self.index(config))
        if i < 0:
            return np.empty((0, self.dim), np.float32)
        return from_mask(self.masks[self.neighbour_indices(i)], self.n_blocks)

    def depths(self, start=None) -> np.ndarray:
        """Edge distance of every node from `start` (default: all apart) by breadth-first search; -1 if unreachable."""
        s = int(self.index(make_config(self.n_blocks) if start is None else start))
        return bfs_hops(self.indptr, self.indices, s)

    # --- evaluation classes -------------------------------------------------------------------
    @property
    def classes(self) -> dict[str, np.ndarray]:
        """Evaluation class name -> (size, dim) configs (SPEC §4.1)."""
        return evaluation_classes(self.n_blocks)

    def class_of(self, configs) -> np.ndarray:
        """Evaluation class name of each config (...), "" where it belongs to none."""
        m = to_mask(self._check(configs))
        out = np.full(m.shape, "", dtype=object)
        for name, members in self._class_masks.items():
            out[np.isin(m, members)] = name
        return out

    def sample_goal(self, class_name: str, rng: np.random.Generator, size: int | None = None) -> np.ndarray:
        """Goal(s) drawn uniformly from an evaluation class."""
        if class_name not in self.classes:
            raise ValueError(f"unknown class {class_name!r} for {self.n_blocks} blocks; known: {list(self.classes)}")
        members = self.classes[class_name]
        return members[rng.integers(len(members), size=size)]

    def _check(self, configs) -> np.ndarray:
        c = np.asarray(configs)
        if c.shape[-1:] != (self.dim,):
            raise ValueError(f"configs must have {self.dim} predicates for {self.n_blocks} blocks, got shape {c.shape}")
        return c


def summary(graph: OracleGraph) -> str:
    depth = graph.depths()
    hist = np.bincount(depth[depth >= 0])
    lines = [
        f"oracle graph, {graph.n_blocks} blocks (built in {graph.build_seconds * 1e3:.0f} ms)",
        f"  permutation classes  {graph.n_classes} (spanning-tree edges: {len(graph.tree_edges)})",
        f"  nodes                {graph.n_nodes:,} configs ({config_dim(graph.n_blocks)} predicates each)",
        f"  edges                {graph.n_edges:,} directed ({graph.n_edges // 2:,} adjacencies)",
        "  depth from all-apart " + ", ".join(f"{d}: {c:,}" for d, c in enumerate(hist)),
    ]
    if (depth < 0).any():
        lines.append(f"  unreachable          {(depth < 0).sum():,}")
    lines.append("  evaluation classes   " + ", ".join(f"{k}: {len(v)}" for k, v in graph.classes.items()))
    members = np.concatenate(list(graph.classes.values()))
    lines.append(f"                       {len(members)} configs, all oracle nodes: {graph.contains(members).all()}")
    return "\n".join(lines)


def main(argv=None):
    def n_blocks_arg(text):
        try:
            return check_n_blocks(int(text))
        except ValueError:
            message = f"must be an integer in [{MIN_BLOCKS}, {MAX_BLOCKS}], got {text!r}"
            raise argparse.ArgumentTypeError(message) from None

    parser = argparse.ArgumentParser(description="Build the social partner's oracle graph and print a summary.")
    parser.add_argument("--n-blocks", type=n_blocks_arg, default=5, help="number of blocks (2-5)")
    args = parser.parse_args(argv)
    print(summary(OracleGraph(args.n_blocks)))


if __name__ == "__main__":
    sys.exit(main())
