"""gangstr_hme.py, the social partner: stepping stones, frontier and beyond goals, social cycles,
internalization and rehearsal, the ablations (SPEC §7)."""

import csv
from collections import Counter, deque
from pathlib import Path
from types import SimpleNamespace

import inprocess
import numpy as np
import pytest
import torch
from chisquare import uniform_pvalue

import gangstr_hme as gh
import oracle_graph as og
import plumbing

ROOT = Path(__file__).resolve().parent.parent
N = 3


def M(close=(), above=()):
    return int(og.to_mask(og.make_config(N, close=close, above=above)))


APART = M()
C01 = M(close=[(0, 1)])


@pytest.fixture(scope="module")
def sp():
    return gh.SocialPartner(N)


def stream(seed: int) -> SimpleNamespace:
    """What the partner reads of a worker when it draws: its random stream."""
    return SimpleNamespace(rng=np.random.default_rng(seed))


def agent_graph(edges=(), nodes=()):
    """An agent graph holding `nodes` and the edges (s, f) (each with all its joint permutations)."""
    g = gh.SemanticGraph(N, gh.Args(n_blocks=N))
    for m in nodes:
        g.add_config(m)
    for s, f in edges:
        g.add_config(s)
        g.add_config(f)
        g.edge_class(s, f)
    return g


def brute_force_stones(sp, g):
    """Agent nodes in the oracle with an oracle neighbour the agent has no edge to (plain Python)."""
    agent_edges = {(g.masks[u], g.masks[v]) for u, v, _ in g.edge_log}
    stones = set()
    for m in g.masks:
        if m in sp.oracle.masks:
            nbrs = og.to_mask(sp.oracle.neighbours(og.from_mask(m, N))).tolist()
            if any((m, c) not in agent_edges for c in nbrs):
                stones.add(m)
    return stones


def reachable(g, start):
    seen, todo = {start}, deque([start])
    while todo:
        u = todo.popleft()
        for v in g.succ[g.node_of[u]] if u in g.node_of else []:
            if g.masks[v] not in seen:
                seen.add(g.masks[v])
                todo.append(g.masks[v])
    return seen


def random_agent_graph(sp, seed, p_node=0.6, p_edge=0.5):
    """Random oracle nodes, each with a random share of its oracle edges."""
    rng = np.random.default_rng(seed)
    nodes = [int(m) for m in sp.oracle.masks if rng.random() < p_node]
    edges = [
        (m, int(c))
        for m in nodes
        for c in og.to_mask(sp.oracle.neighbours(og.from_mask(m, N)))
        if rng.random() < p_edge
    ]
    return agent_graph(edges, nodes)


# ------------------------------------------------------------------------------------------------
# 1. Stepping stones, frontier and beyond goals on hand-built agent graphs over the 3-block oracle
# ------------------------------------------------------------------------------------------------
def test_a_known_config_is_a_stepping_stone_until_every_oracle_neighbour_has_an_agent_edge(sp):
    neighbours = og.to_mask(sp.oracle.neighbours(og.from_mask(APART, N))).tolist()
    assert set(og.OracleGraph(N).class_of(og.from_mask(neighbours, N))) == {"C1", "S2"}  # push or stack
    g = agent_graph(nodes=[APART])
    assert sp.stepping_stones(g).tolist() == [APART]
    g = agent_graph([(APART, C01)])  # edges to the 3 close pairs, not yet to the 6 stacks
    assert APART in sp.stepping_stones(g)
    g = agent_graph([(APART, C01), (APART, M(close=[(0, 1)], above=[(0, 1)]))])
    assert APART not in sp.stepping_stones(g)
    assert set(sp.stepping_stones(g).tolist()) == brute_force_stones(sp, g)


def test_configs_outside_the_oracle_are_never_stepping_stones(sp):
    impossible = M(above=[(0, 1), (1, 0)])
    g = agent_graph(nodes=[impossible])
    assert len(sp.stepping_stones(g)) == 0
    assert sp.beyond_goal(g, impossible, stream(0)) is None


@pytest.mark.parametrize("seed", range(8))
def test_stepping_stones_match_a_brute_force_check(sp, seed):
    g = random_agent_graph(sp, seed)
    assert set(sp.stepping_stones(g).tolist()) == brute_force_stones(sp, g)


@pytest.mark.parametrize("elsewhere", [False, True], ids=["current included", "elsewhere"])
@pytest.mark.parametrize("seed", range(8))
def test_frontier_goals_are_stepping_stones_reachable_from_the_current_config(sp, seed, elsewhere):
    # elsewhere (--strategy frontier): a goal the agent must move to, never its own config.
    g = random_agent_graph(sp, seed, p_edge=0.3)
    w = stream(seed)
    stones = brute_force_stones(sp, g)
    for start in g.masks[:: max(1, g.n_nodes // 6)]:
        allowed = (stones & reachable(g, start)) - ({start} if elsewhere else set())
        drawn = {sp.frontier_goal(g, start, w, elsewhere=elsewhere) for _ in range(60)}
        if not allowed:
            assert drawn == {None}
        else:
            assert drawn <= allowed and len(drawn) >= min(2, len(allowed))


@pytest.mark.parametrize("seed", range(8))
def test_beyond_goals_are_oracle_neighbours_without_an_agent_edge(sp, seed):
    g = random_agent_graph(sp, seed)
    w = stream(seed)
    agent_edges = {(g.masks[u], g.masks[v]) for u, v, _ in g.edge_log}
    for m in g.masks:
        nbrs = set(og.to_mask(sp.oracle.neighbours(og.from_mask(m, N))).tolist())
        allowed = {c for c in nbrs if (m, c) not in agent_edges}
        drawn = {sp.beyond_goal(g, m, w) for _ in range(30)}
        assert drawn == {None} if not allowed else drawn <= allowed


def test_with_no_stepping_stone_left_the_partner_proposes_nothing(sp):
    everything = [(int(sp.edge_heads[k]), int(sp.edge_tails[k])) for k in range(len(sp.edge_heads))]
    g = agent_graph(everything)
    assert len(sp.stepping_stones(g)) == 0
    w = stream(0)
    assert all(sp.frontier_goal(g, m, w) is None and sp.beyond_goal(g, m, w) is None for m in g.masks)


# ------------------------------------------------------------------------------------------------
# 2. The social cycle, step by step, with a scripted stand-in for the policy
# ------------------------------------------------------------------------------------------------
class ScriptedWorld:
    """Replaces the policy and the physics of the run's one worker: a segment toward goal g succeeds
    iff script(g, deterministic) says so, and the world's config becomes g on success. Every reset goes
    back to `start`."""

    def __init__(self, run, monkeypatch, start, script):
        self.config, self.start, self.script, self.log = start, start, script, []
        monkeypatch.setattr(run.workers[0].env, "reset", self.reset)
        monkeypatch.setattr(gh, "current_config", lambda env: self.config)
        monkeypatch.setattr(gh, "run_segments", lambda agent, workers, requests: [self.segment(run.args, *r[:2])
                                                                                  for r in requests])  # fmt: skip

    def reset(self, **kw):
        self.config = self.start
        self.log.append("reset")

    def segment(self, args, g, deterministic):
        goal, before = og.from_mask(g, N), self.config
        success = self.script(g, deterministic)
        self.config = g if success else before
        self.log.append((g, "det" if deterministic else "stoch", success))
        ag = np.tile(og.from_mask(before, N), (args.segment_len + 1, 1))
        ag[-1] = og.from_mask(self.config, N)
        zeros = np.zeros((args.segment_len + 1, 55), np.float32)
        return gh.Segment(zeros, ag, goal, np.zeros((args.segment_len, 4), np.float32), success, True)


def hme_run(**kw):
    args = dict(n_blocks=N, sp_ratio=1.0, segment_len=4, stable_steps=2) | kw
    return gh.Run(gh.Args(**args), torch.device("cpu"))


def one_cycle_of(run, program) -> list:
    """One cycle of the run's one worker running `program` (a cycle program such as
    run.sampler.social_cycle), its pairs merged at the end as after any cycle; the cycle's segments."""
    (w,) = run.workers
    w.left, w.segments = run.args.n_segments, []
    gh.drive(run.learner.agent, {w: program(w)})
    run.sampler.after_cycle()
    return w.segments


PICKERS = ["", "novelty", "zpd"]  # the partner's uniform draw; the learner's picks (SPEC §7.1), in each strategy


@pytest.mark.parametrize("picks", PICKERS, ids=["uniform", "novelty", "zpd"])
def test_social_cycle_follows_the_protocol_step_by_step(monkeypatch, picks):
    run = hme_run(learner_picks=picks)
    assert (type(run.sampler.sp).__name__ == "LearnerPicks") == bool(picks)
    # The agent has made every move from "all apart" (to each close pair and each 2-stack) and nothing
    # since: those configs are its frontier, "all apart" is not.
    run.learner.graph = agent_graph([(APART, C01), (APART, M(close=[(0, 1)], above=[(0, 1)]))])
    frontiers = set(og.to_mask(run.sampler.sp.oracle.neighbours(og.from_mask(APART, N))).tolist())
    assert set(run.sampler.sp.stepping_stones(run.learner.graph).tolist()) == frontiers
    beyond_tries = []

    def script(goal, deterministic):
        if deterministic:
            return True  # going to the frontier works
        beyond_tries.append(goal)
        return len(beyond_tries) % 2 == 1  # beyond goals: success, failure, success, failure, ...

    world = ScriptedWorld(run, monkeypatch, APART, script)
    segments = one_cycle_of(run, run.sampler.social_cycle)
    assert len(segments) == run.args.n_segments == 10
    log = world.log
    i, episodes, failed = 0, 0, []
    while i < len(log):
        assert log[i] == "reset"  # every episode starts from a reset
        episodes += 1
        frontier, mode, ok = log[i + 1]
        assert frontier in frontiers and mode == "det" and ok  # deterministic, along the safest path
        i += 2
        start = frontier
        while i < len(log) and log[i] != "reset":
            beyond, mode, ok = log[i]
            assert mode == "stoch"  # beyond goals: one segment with the stochastic policy
            nbrs = set(og.to_mask(run.sampler.sp.oracle.neighbours(og.from_mask(start, N))).tolist())
            assert beyond in nbrs  # adjacent to where the attempt starts: chaining
            i += 1
            if ok:
                start = beyond
            else:
                failed.append((start, beyond))  # a failure is internalized
                assert i == len(log) or log[i] == "reset"  # ... and the episode ends
    assert episodes >= 2 and failed and len(beyond_tries) > len(failed)  # beyond goals, reached and failed
    assert run.sampler.internalization_buffer == list(dict.fromkeys(failed))  # once each
    assert run.sampler.stats["sp_frontier_C1"] + run.sampler.stats["sp_frontier_S2"] == episodes


@pytest.mark.parametrize("picks", PICKERS, ids=["uniform", "novelty", "zpd"])
def test_frontier_strategy_goes_to_the_frontier_deterministically_then_resets_and_stores_nothing(monkeypatch, picks):
    run = hme_run(strategy="frontier", learner_picks=picks)
    assert (type(run.sampler.sp).__name__ == "LearnerPicks") == bool(picks)
    run.learner.graph = agent_graph([(APART, C01), (APART, M(close=[(0, 1)], above=[(0, 1)]))])
    frontiers = set(og.to_mask(run.sampler.sp.oracle.neighbours(og.from_mask(APART, N))).tolist())
    tries = []

    def script(goal, deterministic):
        tries.append(goal)
        return len(tries) % 3 != 0  # every third frontier leg fails

    world = ScriptedWorld(run, monkeypatch, APART, script)
    assert len(one_cycle_of(run, run.sampler.social_cycle)) == 10
    # SPEC §7, --strategy frontier: reset, the frontier goal along the safest path with the
    # deterministic policy (here one small step), then reset again; no beyond goal, nothing stored.
    assert world.log[0::2] == ["reset"] * 10
    assert all(goal in frontiers and mode == "det" for goal, mode, _ in world.log[1::2])
    assert not run.sampler.internalization_buffer
    assert run.sampler.stats["sp_frontier_C1"] + run.sampler.stats["sp_frontier_S2"] == 10
    assert not any(k.startswith("sp_beyond") for k in run.sampler.stats)


@pytest.mark.parametrize("picks", PICKERS, ids=["uniform", "novelty", "zpd"])
def test_frontier_strategy_never_proposes_the_frontier_the_agent_stands_on(monkeypatch, picks):
    # SPEC §7, --strategy frontier: its goal is the journey, so the stepping stone where the agent stands
    # (here, after every reset: the close pair C01) is not offered; every other one it can reach is.
    run = hme_run(strategy="frontier", learner_picks=picks)
    run.learner.graph = agent_graph([(APART, C01), (APART, M(close=[(0, 1)], above=[(0, 1)])), (C01, APART)])
    stones = set(run.sampler.sp.frontier_candidates(run.learner.graph, C01).tolist())
    assert C01 in stones and len(stones) > 2
    world = ScriptedWorld(run, monkeypatch, C01, lambda goal, deterministic: True)
    assert len(one_cycle_of(run, run.sampler.social_cycle)) == 10
    legs = []  # each episode's goals, after its reset
    for e in world.log:
        if e == "reset":
            legs.append([])
        else:
            legs[-1].append(e[0])
    assert len(legs) == 5 and all(len(leg) == 2 and leg[0] == APART for leg in legs)  # C01 -> APART -> a stone
    assert all(leg[-1] in stones - {C01} for leg in legs)
    assert all(e == "reset" or e[0] != C01 for e in world.log)  # never proposed, never gone to


@pytest.mark.parametrize("picks", PICKERS, ids=["uniform", "novelty", "zpd"])
def test_beyond_strategy_retries_one_goal_beyond_a_hidden_frontier_without_reset_until_reached(monkeypatch, sp, picks):
    run = hme_run(strategy="beyond", learner_picks=picks)
    assert (type(run.sampler.sp).__name__ == "LearnerPicks") == bool(picks)
    run.learner.graph = agent_graph([(APART, C01), (APART, M(close=[(0, 1)], above=[(0, 1)]))])
    stones = brute_force_stones(sp, run.learner.graph) & reachable(run.learner.graph, APART)
    agent_edges = {(run.learner.graph.masks[u], run.learner.graph.masks[v]) for u, v, _ in run.learner.graph.edge_log}
    neighbours = {m: og.to_mask(sp.oracle.neighbours(og.from_mask(m, N))).tolist() for m in stones}
    beyond = {c for m in stones for c in neighbours[m] if (m, c) not in agent_edges}
    tries = []

    def script(goal, deterministic):
        tries.append(goal)
        return len(tries) % 3 == 0  # each goal is reached at the third attempt

    world = ScriptedWorld(run, monkeypatch, APART, script)
    assert len(one_cycle_of(run, run.sampler.social_cycle)) == 10
    # SPEC §7, --strategy beyond: reset, one goal beyond a frontier the agent is not shown, attempted
    # directly with the stochastic policy, again and again without reset until reached; nothing stored.
    episodes = " ".join("R" if e == "reset" else ("+" if e[2] else "-") for e in world.log).split("R")[1:]
    assert [e.split() for e in episodes] == [["-", "-", "+"]] * 3 + [["-"]]
    goals = [[e[0] for e in world.log[i + 1 : i + 4]] for i in (0, 4, 8)]
    assert all(len(set(g)) == 1 and g[0] in beyond for g in goals)  # one goal per episode, beyond a frontier
    assert all(e == "reset" or e[1] == "stoch" for e in world.log)
    assert not run.sampler.internalization_buffer
    assert not any(k.startswith("sp_frontier") for k in run.sampler.stats)
    assert sum(v for k, v in run.sampler.stats.items() if k.startswith("sp_beyond_") and "reached" not in k) == 4
    assert sum(v for k, v in run.sampler.stats.items() if k.startswith("sp_beyond_reached_")) == 3  # the third tries


C01_BEYOND = [M(close=[(0, 1)], above=[(0, 1)]), M(close=[(0, 1)], above=[(1, 0)]), M(close=[(0, 1), (1, 2)]),
              M(close=[(0, 1), (0, 2)])]  # fmt: skip


def rehearsed_goals(run, monkeypatch, cycles):
    """The beyond goals attempted over `cycles` rehearsal cycles, every frontier reached."""
    world = ScriptedWorld(run, monkeypatch, APART, lambda g, det: det)
    for _ in range(cycles):
        one_cycle_of(run, run.sampler.rehearsal_cycle)
    return [e[0] for e in world.log if e != "reset" and e[1] == "stoch"]


def test_a_pair_failed_again_and_again_is_stored_once_and_rehearsed_as_often_as_any_other(monkeypatch):
    run = hme_run(sp_ratio=0.0)
    run.learner.graph = agent_graph([(APART, C01)])
    failures = [C01_BEYOND[0]] * 10 + [C01_BEYOND[1]] + [C01_BEYOND[2]] * 3
    for beyond in failures:
        run.sampler.internalize(run.workers[0], C01, beyond)
    run.sampler.after_cycle()
    assert run.sampler.internalization_buffer == [(C01, b) for b in C01_BEYOND[:3]]  # SPEC §7: a set
    counts = np.unique(rehearsed_goals(run, monkeypatch, 300), return_counts=True)[1]
    assert len(counts) == 3 and counts.sum() == 1500  # 5 draws a cycle: frontier leg, beyond attempt
    assert uniform_pvalue(counts) > 1e-3  # uniform over pairs, not 10 : 1 : 3


@pytest.mark.parametrize("rank", [0, 1])
def test_pairs_stored_by_two_workers_merge_into_one_set_drawn_uniformly(monkeypatch, rank):
    a, b, c, d = ((C01, g) for g in C01_BEYOND)
    stored = {0: [b, a, c, b], 1: [c, d, d, a]}  # each worker's failures this cycle; `a` was stored before
    run = hme_run(sp_ratio=0.0, internalization_prob=0.0)
    run.learner.graph = agent_graph([(APART, C01)])
    run.sampler.internalization_buffer = [a]

    def cycle(w):
        for pair in stored[rank]:
            run.sampler.internalize(w, *pair)
        yield from ()  # a cycle program that runs no segment

    local = {0: np.array([b, c]), 1: np.array([c, d])}  # what each worker keeps: its new distinct pairs

    def all_gather_rows(rows):
        np.testing.assert_array_equal(rows, local[rank])
        return np.concatenate([local[0], local[1]])  # rank order

    monkeypatch.setattr(run.sampler, "autotelic_cycle", cycle)
    monkeypatch.setattr(gh, "all_gather_rows", all_gather_rows)
    monkeypatch.setattr(plumbing, "check_budgets", lambda run: None)  # a cycle of no segment, on purpose
    gh.run_cycle(run)
    run.sampler.after_cycle()
    # The same distinct pairs in the same order on every worker (so a seeded draw agrees): the old
    # ones, then the new ones in rank order.
    assert run.sampler.internalization_buffer == [a, b, c, d]
    monkeypatch.setattr(gh, "all_gather_rows", lambda rows: rows)  # one worker from here on
    counts = np.unique(rehearsed_goals(run, monkeypatch, 200), return_counts=True)[1]
    assert len(counts) == 4 and uniform_pvalue(counts) > 1e-3


def test_rehearsal_goes_to_the_stored_frontier_then_attempts_the_stored_beyond_goal(monkeypatch):
    run = hme_run(sp_ratio=0.0)
    run.learner.graph = agent_graph([(APART, C01)])
    stack = M(close=[(0, 1)], above=[(0, 1)])
    run.sampler.internalization_buffer = [(C01, stack)]
    world = ScriptedWorld(run, monkeypatch, APART, lambda g, det: det)  # beyond attempts fail
    segments = one_cycle_of(run, run.sampler.rehearsal_cycle)
    assert len(segments) == 10
    # One attempt per drawn pair (no reset between frontier and beyond), then reset and draw again.
    assert world.log == ["reset", (C01, "det", True), (stack, "stoch", False)] * 5


def test_a_partner_with_nothing_to_propose_leaves_the_cycle_autotelic(monkeypatch, sp):
    run = hme_run()
    everything = [(int(sp.edge_heads[k]), int(sp.edge_tails[k])) for k in range(len(sp.edge_heads))]
    run.learner.graph = agent_graph(everything)
    world = ScriptedWorld(run, monkeypatch, APART, lambda g, det: False)
    assert len(one_cycle_of(run, run.sampler.social_cycle)) == 10
    assert not any(k.startswith("sp_") for k in run.sampler.stats) and not run.sampler.internalization_buffer
    assert all(e == "reset" or e[1] == "stoch" for e in world.log)  # autotelic goals, training policy


def test_cycle_kinds_follow_sp_ratio_and_internalization_prob(monkeypatch):
    run = hme_run(sp_ratio=0.3, internalization_prob=0.4, n_segments=1)
    run.learner.graph = agent_graph([(APART, C01)])
    run.sampler.internalization_buffer = [(C01, M(close=[(0, 1)], above=[(0, 1)]))]
    ScriptedWorld(run, monkeypatch, APART, lambda g, det: False)
    for _ in range(3000):
        gh.run_cycle(run)
    social = run.sampler.stats["social_cycles"] / 3000
    rehearsal = run.sampler.stats["rehearsal_cycles"] / 3000
    assert abs(social - 0.3) < 4 * np.sqrt(0.3 * 0.7 / 3000)
    assert abs(rehearsal - 0.28) < 4 * np.sqrt(0.28 * 0.72 / 3000)  # 40% of the non-social cycles


# ------------------------------------------------------------------------------------------------
# 3, 5. Every strategy and ablation runs from the command line; the logged social share
# ------------------------------------------------------------------------------------------------
TINY = ["--n-blocks", "3", "--n-epochs", "1", "--n-cycles", "3", "--n-segments", "4", "--n-updates", "2",
        "--batch-size", "16", "--segment-len", "8", "--stable-steps", "3", "--eval-goals-per-class", "1",
        "--threads", "1"]  # fmt: skip


@pytest.mark.parametrize(
    "flags",
    [
        ["--sp-ratio", "0.5", "--strategy", "frontier-and-beyond"],
        ["--sp-ratio", "0.5", "--strategy", "frontier"],
        ["--sp-ratio", "0.5", "--strategy", "beyond"],
        ["--sp-ratio", "0.5", "--internalization-prob", "0"],  # NI
        ["--sp-ratio", "0.5", "--max-path-len", "2"],  # NG
        ["--sp-ratio", "1"],  # SP-100%
        ["--sp-ratio", "0.5", "--strategy", "frontier", "--learner-picks", "zpd"],  # SPEC §7.1, in each strategy
        ["--sp-ratio", "0.5", "--strategy", "beyond", "--learner-picks", "novelty"],
    ],
    ids=["frontier-and-beyond", "frontier", "beyond", "NI", "NG", "SP-100", "frontier-zpd", "beyond-novelty"],
)
def test_every_strategy_and_ablation_runs_end_to_end(tmp_path, flags):
    out = inprocess.run_script("gangstr_hme.py", *flags, *TINY, runs_dir=tmp_path)
    assert out.returncode == 0, out.stderr
    (run_dir,) = tmp_path.iterdir()
    (row,) = csv.DictReader((run_dir / "progress.csv").open())
    for column in ("stepping_stones", "internalized_pairs", "social_share", "sp_frontier_C1", "sp_beyond_S2"):
        assert column in row
    if "--internalization-prob" in flags:
        assert float(row["rehearsal_share"]) == 0.0


def test_logged_social_share_matches_sp_ratio(tmp_path):
    flags = ["--sp-ratio", "0.25", "--n-cycles", "400", "--n-segments", "1", "--segment-len", "2",
             "--stable-steps", "1", "--n-updates", "0", "--n-epochs", "1", "--n-blocks", "3",
             "--eval-goals-per-class", "1", "--threads", "1"]  # fmt: skip
    out = inprocess.run_script("gangstr_hme.py", *flags, runs_dir=tmp_path)
    assert out.returncode == 0, out.stderr
    (run_dir,) = tmp_path.iterdir()
    (row,) = csv.DictReader((run_dir / "progress.csv").open())
    assert abs(float(row["social_share"]) - 0.25) < 4 * np.sqrt(0.25 * 0.75 / 400)


def test_frontier_arrivals_and_beyond_goals_reached_are_counted_in_their_class(monkeypatch, sp):
    run = hme_run()
    run.learner.graph = agent_graph([(APART, C01), (APART, M(close=[(0, 1)], above=[(0, 1)]))])
    tries = []

    def script(goal, deterministic):
        tries.append(goal)
        return len(tries) % 3 != 0  # every third segment fails, frontier legs and beyond goals alike

    world = ScriptedWorld(run, monkeypatch, APART, script)
    for _ in range(3):
        one_cycle_of(run, run.sampler.social_cycle)
    # From the world's log: each episode's first segment (deterministic) is its frontier leg, the rest
    # (stochastic) beyond goals; a reached one counts in the class of its goal, a failed one nowhere.
    want = Counter()
    for goal, mode, ok in (entry for entry in world.log if entry != "reset"):
        kind = "frontier_arrived" if mode == "det" else "beyond_reached"
        want[f"sp_{kind}_{sp.oracle.class_of(og.from_mask(goal, N)) or 'other'}"] += ok
    got = {k: v for k, v in run.sampler.stats.items() if v and ("_arrived_" in k or "_reached_" in k)}
    assert got == {k: v for k, v in want.items() if v}
    legs = sum(mode == "det" for _, mode, _ in (entry for entry in world.log if entry != "reset"))
    assert 0 < sum(v for k, v in got.items() if "arrived" in k) < legs  # some legs failed: not every proposal
    assert 0 < sum(v for k, v in got.items() if "reached" in k)


# ------------------------------------------------------------------------------------------------
# Beyond the paper: the learner asks for help (SPEC §7.1)
# ------------------------------------------------------------------------------------------------
def answers(run, growth: list[int], asks_per_cycle: int = 1) -> list[bool]:
    """The learner's answer to "is this cycle help?" for each cycle, the graph having gained growth[i]
    new nodes just before cycle i (as learn_from adds them); asked asks_per_cycle times a cycle (workers)."""
    fresh = iter(range(2 ** og.config_dim(N)))  # every +-1 vector's mask: some not yet in the graph
    said = []
    for grow in growth:
        target = run.learner.graph.n_nodes + grow
        while run.learner.graph.n_nodes < target:
            run.learner.graph.add_config(next(fresh))
        run.learner.segments += run.args.n_segments  # a cycle's segments: the learner's clock
        said.append({run.sampler.query is not None and run.sampler.query.asks() for _ in range(asks_per_cycle)})
    assert all(len(s) == 1 for s in said)  # every worker of a cycle gets the same answer
    return [s.pop() for s in said]


def test_the_learner_asks_for_help_when_its_graph_stops_growing_and_not_while_it_grows():
    stuck = answers(hme_run(sp_ratio=0.0, ask_after=3, help_cycles=2), [0] * 12, asks_per_cycle=3)
    # 3 cycles without a new node, then a query; the help cycle adds nothing, so the help stops at once
    assert stuck == [False, False, True, False] * 3
    growing = answers(hme_run(sp_ratio=0.0, ask_after=3, help_cycles=2), [1] * 12)
    assert not any(growing)
    never = answers(hme_run(sp_ratio=0.0, ask_after=0), [0] * 12)  # --ask-after 0: the learner never asks
    assert not any(never)


def test_help_goes_on_while_each_social_cycle_adds_a_node_for_help_cycles_at_most():
    run = hme_run(sp_ratio=0.0, ask_after=2, help_cycles=3)
    said = answers(run, [0, 0, 1, 1, 1, 1, 0, 0, 0, 5, 0, 0])
    # asks at cycle 2; cycles 2 and 3 added nodes, so 3 and 4 are help too; 4 is the third: the help is over
    # at 5 (which still grew: the count of cycles without a new node starts again after it)
    assert said == [False, True, True, True, False, False, False, True, False, False, False, True]
    assert run.sampler.query.state["stalled"] == 2


def test_queries_help_cycles_and_help_with_nothing_proposed_are_counted(monkeypatch):
    run = hme_run(sp_ratio=0.0, ask_after=2, help_cycles=3, n_segments=2, num_envs=2, n_updates=0)
    ScriptedWorld(run, monkeypatch, APART, lambda g, det: False)  # nothing the agent tries works: no growth
    monkeypatch.setattr(run.sampler.sp, "frontier_goal", lambda *a, **k: None)  # and the partner has nothing
    monkeypatch.setattr(run.sampler.sp, "beyond_goal", lambda *a, **k: None)
    for _ in range(21):
        gh.one_cycle(run)
    # the graph grows once (the first cycle's configs), then never: queries at cycles 4, 7, ..., 19 (from 1),
    # each answered by one social cycle on each of the 2 workers, with nothing proposed; cycle 20 ends the
    # help, and cycle 21 is one without a new node
    s = run.sampler.stats
    assert (s["queries"], s["help_cycles"], s["help_nothing"], s["social_cycles"]) == (6, 12, 12, 12)
    row = run.sampler.epoch_stats()
    assert (row["queries"], row["help_cycles"], row["help_nothing"], row["stalled_cycles"]) == (6, 12, 12, 1)


def cycle_before_the_query(self, w):
    """GoalSampler.cycle as it was before the learner could ask (commit 1a90e36), verbatim."""
    args = self.args
    self.stats["cycles"] += 1
    if args.sp_ratio > 0 and w.rng.random() < args.sp_ratio:  # --sp-ratio
        self.stats["social_cycles"] += 1
        yield from self.social_cycle(w)
    elif self.internalization_buffer and w.rng.random() < args.internalization_prob:  # --internalization-prob
        self.stats["rehearsal_cycles"] += 1
        yield from self.rehearsal_cycle(w)
    else:
        yield from self.autotelic_cycle(w)


def test_a_run_with_the_coin_alone_is_the_run_of_the_code_before_the_query(tmp_path, monkeypatch):
    flags = [*TINY, "--n-epochs", "2", "--n-cycles", "6", "--sp-ratio", "0.4", "--seed", "5"]
    assert gh.main([*flags, "--runs-dir", str(tmp_path / "now")]) == 0
    monkeypatch.setattr(gh.GoalSampler, "cycle", cycle_before_the_query)
    assert gh.main([*flags, "--runs-dir", str(tmp_path / "before")]) == 0
    (now,), (before,) = (tmp_path / "now").iterdir(), (tmp_path / "before").iterdir()
    rows_now, rows_before = (list(csv.DictReader((r / "progress.csv").open())) for r in (now, before))
    timing = ("time_", "steps_per_second")
    for a, b in zip(rows_now, rows_before, strict=True):
        assert {k: v for k, v in a.items() if not k.startswith(timing)} == {
            k: v for k, v in b.items() if not k.startswith(timing)
        }
        assert float(a["social_share"]) > 0 and float(a["help_cycles"]) == float(a["queries"]) == 0
