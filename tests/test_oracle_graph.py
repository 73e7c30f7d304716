"""oracle_graph.py: layout, permutations, canonical forms, the small-step rule, the grid search, the
oracle graph and the 11 evaluation classes (SPEC §2, §4)."""

import itertools
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from chisquare import uniform_pvalue
from hypothesis import given, settings
from hypothesis import strategies as st

import fetch5_env as fe
import oracle_graph as og

ROOT = Path(__file__).resolve().parent.parent


@pytest.fixture(scope="module")
def oracle5():
    return og.OracleGraph(5)


@pytest.fixture(scope="module")
def oracle3():
    return og.OracleGraph(3)


# ------------------------------------------------------------------------------------------------
# Layout and permutations
# ------------------------------------------------------------------------------------------------
def test_layout_puts_close_pairs_first_then_i_on_j_at_10_plus_4i_plus_j_shifted():
    assert og.close_pairs(5).tolist()[:3] == [[0, 1], [0, 2], [0, 3]] and og.close_pairs(5).tolist()[-1] == [3, 4]
    for k, (i, j) in enumerate(og.above_pairs(5)):
        assert 10 + k == 10 + 4 * i + (j if j < i else j - 1)
    assert og.config_dim(5) == 30 and og.config_dim(3) == 9
    c = og.make_config(5, close=[(1, 0)], above=[(3, 2)])
    assert np.flatnonzero(c > 0).tolist() == [0, 10 + 4 * 3 + 2]
    assert og.describe(c) == "3 on 2, close(0,1)" and og.describe(og.make_config(3)) == "all apart"


def test_masks_round_trip_and_bad_predicates_are_named():
    rng = np.random.default_rng(0)
    configs = rng.choice([-1.0, 1.0], size=(50, 30)).astype(np.float32)
    np.testing.assert_array_equal(og.from_mask(og.to_mask(configs), 5), configs)
    with pytest.raises(ValueError, match="'above', 2, 2"):
        og.make_config(3, above=[(2, 2)])
    with pytest.raises(ValueError, match="length 7"):
        og.n_blocks_of(7)


def test_permuting_a_config_equals_the_config_of_the_permuted_scene():
    """The permutation convention: p sends block a's role to block p(a) (SPEC §2)."""
    rng = np.random.default_rng(1)
    perms = og.permutations(5)
    for _ in range(20):
        pos = rng.uniform(0, 0.12, size=(5, 3))
        pos[:, 2] = rng.choice([0.0, 0.05, 0.1], size=5)
        config = fe.semantic_config(pos)
        k = rng.integers(len(perms))
        moved = np.empty_like(pos)
        moved[perms[k]] = pos  # block p(a) stands where block a stood
        np.testing.assert_array_equal(og.permute(config)[k], fe.semantic_config(moved))


def test_permuting_masks_matches_permuting_configs():
    configs = np.random.default_rng(2).choice([-1.0, 1.0], size=(30, 30)).astype(np.float32)
    np.testing.assert_array_equal(og.permute_masks(og.to_mask(configs), 5), og.to_mask(og.permute(configs)))
    assert og.permute(configs).shape == (30, 120, 30)
    np.testing.assert_array_equal(og.permute(configs)[:, 0], configs)  # row 0 is the identity


masks30 = st.integers(min_value=0, max_value=2**30 - 1)


@settings(max_examples=300, deadline=None)
@given(mask=masks30, k=st.integers(0, 119))
def test_canonical_form_is_invariant_under_block_permutations(mask, k):
    config = og.from_mask(mask, 5)
    assert og.canonical(config) == og.canonical(og.permute(config)[k])


@settings(max_examples=300, deadline=None)
@given(mask=masks30, k=st.integers(0, 119), flip=st.one_of(st.none(), st.integers(0, 29)), other=masks30)
def test_canonical_forms_are_equal_exactly_for_permutation_equivalent_configs(mask, k, flip, other):
    a = og.from_mask(mask, 5)
    for b in (og.permute(a)[k], og.from_mask(mask ^ (0 if flip is None else 1 << flip), 5), og.from_mask(other, 5)):
        equivalent = bool((og.permute(a) == b).all(axis=1).any())  # brute force over all 120 permutations
        assert (og.canonical(a) == og.canonical(b)) == equivalent


def test_canonical_form_separates_classes_a_graph_hash_would_merge():
    # Same degree sequence and predicate counts, different structure: a 3-stack and a pyramid.
    s3 = og.make_config(3, close=[(0, 1), (1, 2)], above=[(0, 1), (1, 2)])
    chain = og.make_config(3, close=[(0, 1), (1, 2)], above=[(0, 1), (2, 1)])
    assert og.canonical(s3) != og.canonical(chain)


# ------------------------------------------------------------------------------------------------
# The one-object rule
# ------------------------------------------------------------------------------------------------
def test_small_step_needs_one_block_in_every_changed_predicate():
    apart = og.make_config(5)
    assert og.is_small_step(apart, og.make_config(5, close=[(0, 1)]))
    assert og.is_small_step(apart, og.make_config(5, close=[(0, 1), (0, 2)], above=[(0, 1)]))  # all about 0
    assert not og.is_small_step(apart, og.make_config(5, close=[(0, 1), (2, 3)]))  # two blocks moved
    assert not og.is_small_step(apart, apart)  # nothing changed
    batch = np.stack([og.make_config(5, close=[(0, 1)]), og.make_config(5, close=[(1, 2), (3, 4)])])
    assert og.is_small_step(apart[None], batch).tolist() == [True, False]


# ------------------------------------------------------------------------------------------------
# Grid rules (SPEC §4)
# ------------------------------------------------------------------------------------------------
def cell(x, y):
    return int(np.flatnonzero((og.GRID_XY == (x, y)).all(1))[0])


def state(*blocks):
    """Blocks as (level, x, y)."""
    return np.array([cell(x, y) for _, x, y in blocks]), np.array([lv for lv, _, _ in blocks])


def test_grid_has_144_drop_cells_and_the_start_spreads_blocks_far_apart():
    assert len(og.GRID_XY) == 144
    cells, levels = og.start_state(5)
    np.testing.assert_array_equal(og.GRID_XY[cells], [(0, 3.5 * k) for k in range(5)])
    assert (og.grid_config(cells, levels) == -1).all()


def test_aligned_drop_stacks_the_block_on_top():
    cells, levels = state((0, 0, 0), (0, 0, 5))
    cells, levels = og.drop(cells, levels, block=1, cell=cell(0, 0))
    assert levels.tolist() == [0, 1]
    np.testing.assert_array_equal(og.grid_config(cells, levels), og.make_config(2, close=[(0, 1)], above=[(1, 0)]))
    cells, levels = og.drop(*state((0, 0, 0), (1, 0, 0), (0, 1, 5)), block=2, cell=cell(0, 0))
    assert levels.tolist() == [0, 1, 2]  # it stops on the highest block it meets


def test_half_offset_drop_bridging_two_blocks_makes_a_pyramid():
    cells, levels = og.drop(*state((0, 0, 0), (0, 1, 0), (0, 0, 6)), block=2, cell=cell(0.5, 0))
    assert levels.tolist() == [0, 0, 1]  # overlaps 0.36 + 0.36 > 0.5
    p3 = og.make_config(3, close=[(0, 1), (0, 2), (1, 2)], above=[(2, 0), (2, 1)])
    np.testing.assert_array_equal(og.grid_config(cells, levels), p3)


@pytest.mark.parametrize(
    "blocks, target",
    [
        (((0, 0, 0), (0, 0, 6)), (0.5, 0)),  # half offset over one block: overlap 0.36
        (((0, 0, 0), (0, 0, 6)), (0.5, 0.5)),  # quarter overlap: 0.16
        (((0, 0, 0), (0, 1, 1), (0, 0, 6)), (0.5, 0.5)),  # two quarter overlaps: 0.32
    ],
)
def test_partial_overlap_of_at_most_half_is_rejected(blocks, target):
    cells, levels = state(*blocks)
    assert og.drop(cells, levels, block=len(blocks) - 1, cell=cell(*target)) is None


def test_only_blocks_with_nothing_on_top_can_move():
    cells, levels = state((0, 0, 0), (1, 0, 0), (0, 0, 8))
    rest = og.all_drops(cells, levels)
    assert (rest[0] == -1).all()  # the bottom of the stack is held down
    assert (rest[1] >= 0).any() and (rest[2] >= 0).any()
    cells, levels = state((0, 0, 0), (0, 1, 0), (1, 0.5, 0))  # pyramid: both bases are held
    rest = og.all_drops(cells, levels)
    assert (rest[:2] == -1).all() and (rest[2] >= 0).any()


# ------------------------------------------------------------------------------------------------
# The oracle graph
# ------------------------------------------------------------------------------------------------
@pytest.mark.parametrize("n", [3, 4, 5])
def test_oracle_is_a_spanning_tree_over_classes_lifted_to_all_permutations(n, request):
    g = og.OracleGraph(n)
    parents, children = g.tree_edges.T
    assert len(g.tree_edges) == g.n_classes - 1
    # each tree edge discovers a new class, from a class found before it: a tree rooted at "all apart"
    child_classes = og.permute_masks(children, n).min(1)
    root_class = og.permute_masks(g.root_mask, n).min()
    assert len(set(child_classes.tolist()) | {root_class}) == g.n_classes
    found = {root_class}
    for p, c in zip(og.permute_masks(parents, n).min(1), child_classes, strict=True):
        assert p in found
        found.add(c)
    # nodes are exactly the permutations of the class representatives
    reps = np.concatenate([[g.root_mask], children])
    np.testing.assert_array_equal(g.masks, np.unique(og.permute_masks(reps, n)))
    # edges: symmetric, every one a small step, and the graph is connected
    heads = np.repeat(np.arange(g.n_nodes), np.diff(g.indptr))
    forward = set(zip(heads.tolist(), g.indices.tolist(), strict=True))
    assert all((b, a) in forward for a, b in forward)
    assert og.is_small_step(g.nodes[heads], g.nodes[g.indices]).all()
    assert (g.depths() >= 0).all()


def brute_force_configs_3_blocks():
    """Every placement of 3 blocks in a window of the grid, enumerated exhaustively, kept if stable
    (blocks on one level never overlap; a raised block overlaps the level below by more than 0.5 in
    total), and read with the grid predicates: the set of masks of their configs."""
    xs, ys, levels = np.arange(0, 2, 0.5), np.arange(0, 4.5, 0.5), np.arange(3)
    spots = np.array(list(itertools.product(levels, xs, ys)))  # (level, x, y)
    p = spots[np.array(list(itertools.product(range(len(spots)), repeat=3)))]  # (placements, 3, 3)
    d = p[:, :, None, :] - p[:, None, :, :]
    overlap = np.clip(0.9 - np.abs(d[..., 1]), 0, None) * np.clip(0.9 - np.abs(d[..., 2]), 0, None)
    overlap[:, np.arange(3), np.arange(3)] = 0
    dl, d2 = d[..., 0], (d**2).sum(-1)
    clash = ((dl == 0) & (overlap > 0)).any(axis=(1, 2))
    supported = (p[:, :, 0] == 0) | ((overlap * (dl == 1)).sum(-1) > 0.5)
    keep = ~clash & supported.all(1)
    ci, cj = og.close_pairs(3).T
    ai, aj = og.above_pairs(3).T
    close = d2[keep][:, ci, cj] < 2.96
    above = (dl[keep][:, ai, aj] == 1) & (d2[keep][:, ai, aj] < 1.9)
    return np.unique(og.to_mask(np.where(np.concatenate([close, above], axis=1), 1.0, -1.0)))


def test_three_block_oracle_nodes_equal_an_exhaustive_search_of_stable_placements(oracle3):
    np.testing.assert_array_equal(oracle3.masks, brute_force_configs_3_blocks())


def test_neighbour_queries_work_both_ways(oracle5):
    apart = og.make_config(5)
    near = oracle5.neighbours(apart)
    assert len(near) > 0 and og.is_small_step(apart[None], near).all()
    for c in near:
        assert (oracle5.neighbours(c) == apart).all(1).any()
    assert og.make_config(5, above=[(0, 1), (1, 0)]) not in oracle5  # impossible: both on each other
    assert oracle5.neighbours(og.make_config(5, above=[(0, 1), (1, 0)])).shape == (0, 30)
    with pytest.raises(ValueError, match=r"30 predicates.*\(9,\)"):
        oracle5.index(np.ones(9))


# ------------------------------------------------------------------------------------------------
# The 11 evaluation classes
# ------------------------------------------------------------------------------------------------
SIZES5 = {"C1": 10, "C2": 45, "C3": 120, "S2": 20, "S3": 60, "S2&S2": 60, "S2&S3": 120, "P3": 30, "P3&S2": 60}
SIZES5 |= {"S4": 120, "S5": 120}


def test_eleven_classes_have_the_paper_sizes_are_oracle_nodes_and_closed_under_permutation(oracle5):
    classes = oracle5.classes
    assert {k: len(v) for k, v in classes.items()} == SIZES5 and list(classes) == list(SIZES5)
    all_masks = np.concatenate([og.to_mask(v) for v in classes.values()])
    assert len(np.unique(all_masks)) == 765  # disjoint
    for name, members in classes.items():
        assert oracle5.contains(members).all(), name
        masks = set(og.to_mask(members).tolist())
        assert set(og.to_mask(og.permute(members)).ravel().tolist()) == masks, name
        assert (oracle5.class_of(members) == name).all()
    assert oracle5.class_of(og.make_config(5)) == ""


def test_class_definitions_read_as_in_the_spec():
    s3 = og.make_config(5, close=[(0, 1), (1, 2)], above=[(0, 1), (1, 2)])
    p3 = og.make_config(5, close=[(0, 1), (0, 2), (1, 2)], above=[(2, 0), (2, 1)])
    g = og.OracleGraph(5)
    assert g.class_of(np.stack([s3, p3])).tolist() == ["S3", "P3"]


@pytest.mark.parametrize(
    "n, names", [(3, ["C1", "C2", "C3", "S2", "S3", "P3"]), (4, ["C1", "C2", "C3", "S2", "S3", "S2&S2", "P3", "S4"])]
)
def test_fewer_blocks_keep_the_classes_that_fit(n, names):
    g = og.OracleGraph(n)
    assert list(g.classes) == names
    assert all(g.contains(v).all() for v in g.classes.values())


def test_goals_are_sampled_uniformly_from_a_class(oracle5):
    rng = np.random.default_rng(0)
    goals = oracle5.sample_goal("S2", rng, size=4000)
    assert (oracle5.class_of(goals) == "S2").all()
    counts = np.unique(og.to_mask(goals), return_counts=True)[1]
    assert len(counts) == 20 and uniform_pvalue(counts) > 1e-3  # 200 expected each
    with pytest.raises(ValueError, match="'S6'"):
        oracle5.sample_goal("S6", rng)


# ------------------------------------------------------------------------------------------------
# Command line
# ------------------------------------------------------------------------------------------------
def run_cli(*args):
    return subprocess.run([sys.executable, "oracle_graph.py", *args], cwd=ROOT, capture_output=True, text=True)


def test_cli_prints_a_summary_and_rejects_a_bad_block_count():
    out = run_cli("--n-blocks", "5")
    assert out.returncode == 0
    for word in ("permutation classes", "nodes", "edges", "depth", "S5: 120", "built in"):
        assert word in out.stdout
    bad = run_cli("--n-blocks", "9")
    assert bad.returncode == 2 and "'9'" in bad.stderr
