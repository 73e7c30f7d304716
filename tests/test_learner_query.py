"""learner_query.py, beyond the paper (SPEC §7.1): the learner picks among the social partner's candidates
(--learner-picks), and what its query counts as progress (--ask-progress)."""

import csv
import dataclasses
import itertools

import numpy as np
import pytest
import torch
from chisquare import uniform_pvalue
from test_hme import APART, C01, TINY, M, agent_graph, answers, hme_run, random_agent_graph, stream

import gangstr_hme as gh
import learner_query as lq
import oracle_graph as og
import plumbing

N = 3
SIGNALS = list(lq.PICKS)


def picks_on(graph, signal: str, **kw):
    """The learner's picks over the partner of a 3-block run (its critic: the run's fresh one)."""
    run = hme_run(learner_picks=signal, **kw)
    run.learner.graph = graph
    return run.sampler.sp, run


def brute_novelty(graph, candidate: int) -> int:
    """The unordered pairs of the candidate's true predicates (one with itself included) that no node of
    the agent's graph holds together, in plain Python."""
    true = np.flatnonzero(og.from_mask(candidate, N) > 0)
    nodes = [set(np.flatnonzero(og.from_mask(m, N) > 0)) for m in graph.masks]
    pairs = itertools.combinations_with_replacement(true, 2)
    return sum(not any(i in n and j in n for n in nodes) for i, j in pairs)


def safest_cost(graph, start: int, goal: int) -> float:
    """The sum of -log SR along gangstr_hme's safest path (its Dijkstra), 0 when start is goal."""
    path = gh.safest_path(graph, start, goal, np.random.default_rng(0)) or [start]
    cost = -np.log(np.clip(graph.sr, 1e-12, 1.0))
    return sum(cost[graph.edge_class(u, v)] for u, v in zip(path, path[1:], strict=False))


@pytest.mark.parametrize("elsewhere", [False, True], ids=["current included", "elsewhere"])
@pytest.mark.parametrize("signal", SIGNALS)
@pytest.mark.parametrize("seed", range(3))
def test_a_pick_is_always_one_of_the_offered_candidates(signal, seed, elsewhere):
    # elsewhere (--strategy frontier): the partner offers no frontier goal at the agent's own config
    sp = gh.SocialPartner(N)
    graph = random_agent_graph(sp, seed, p_node=0.4, p_edge=0.3)
    picks, run = picks_on(graph, signal)
    w = run.workers[0]
    for here in graph.masks[:: max(1, graph.n_nodes // 12)]:
        frontier = sp.frontier_candidates(graph, here, elsewhere)
        beyond = sp.beyond_candidates(graph, here)
        f, b = picks.frontier_goal(graph, here, w, elsewhere=elsewhere), picks.beyond_goal(graph, here, w)
        assert (f is None) == (len(frontier) == 0) and (f is None or f in frontier)
        assert not (elsewhere and f == here)
        assert (b is None) == (len(beyond) == 0) and (b is None or b in beyond)


@pytest.mark.parametrize("signal", SIGNALS)
def test_the_same_state_gives_the_same_pick(signal):
    sp = gh.SocialPartner(N)
    graph = random_agent_graph(sp, 5, p_node=0.4, p_edge=0.3)
    picks, run = picks_on(graph, signal)
    w, said = run.workers[0], []
    for _ in range(2):  # the same graph, critic, place and stream: the same picks
        w.rng = np.random.default_rng(9)
        said.append([(picks.frontier_goal(graph, m, w), picks.beyond_goal(graph, m, w)) for m in graph.masks[:20]])
    assert said[0] == said[1]


def test_novelty_counts_the_pairs_of_facts_the_agent_has_seen_together_as_the_graph_grows():
    sp = gh.SocialPartner(N)
    graph = gh.SemanticGraph(N, gh.Args(n_blocks=N))
    graph.add_config(int(og.to_mask(og.make_config(N))))  # all apart: no fact held yet
    picks, _ = picks_on(graph, "novelty")
    candidates = sp.oracle.masks
    for grow in range(4):  # the counts follow the graph as it grows between picks
        got = picks.novelty(graph, candidates)
        assert got.tolist() == [brute_novelty(graph, int(c)) for c in candidates]
        held = (og.from_mask(np.asarray(graph.masks), N) > 0).astype(np.int64)
        assert np.array_equal(picks.pairs, held.T @ held)  # each node counted once
        for m in sp.oracle.masks[grow * 5 : grow * 5 + 5]:
            graph.add_config(int(m))


def test_novelty_changes_its_pick_with_what_the_agent_has_seen():
    here = int(og.to_mask(og.make_config(N, close=[(0, 1)])))
    offered = gh.SocialPartner(N).beyond_candidates(gh.SemanticGraph(N, gh.Args(n_blocks=N)), here)
    classes = og.evaluation_classes(N)
    picked = {}
    for known in ("S2", "C2"):  # an agent that has stacked two blocks, or put three blocks close
        graph = gh.SemanticGraph(N, gh.Args(n_blocks=N))
        for m in [here, *og.to_mask(classes[known]).tolist()]:
            graph.add_config(int(m))
        picks, run = picks_on(graph, "novelty")
        picked[known] = picks.beyond_goal(graph, here, run.workers[0])
        brute = np.array([brute_novelty(graph, int(c)) for c in offered])
        assert picked[known] in offered[brute == brute.max()]
    assert og.from_mask(picked["C2"], N)[3:].max() > 0  # a stack: "above" holds in none of its nodes
    assert og.from_mask(picked["S2"], N)[3:].max() < 0  # blocks close together, none on another


def test_beyond_goals_are_new_configs_first_then_the_most_novel_and_for_zpd_the_hardest(monkeypatch):
    sp = gh.SocialPartner(N)
    graph = gh.SemanticGraph(N, gh.Args(n_blocks=N))
    here = int(og.to_mask(og.make_config(N, close=[(0, 1)])))
    graph.add_config(here)  # a beginner: stacks hold more new pairs than moves of a block close to another
    offered = sp.beyond_candidates(graph, here)
    picks = {signal: picks_on(graph, signal) for signal in SIGNALS}
    novelty = picks["novelty"][0].novelty(graph, offered)
    assert len(set(novelty.tolist())) >= 3
    w = picks["zpd"][1].workers[0]
    value = np.arange(len(offered), dtype=np.float64)  # the first candidate hardest, by the critic
    monkeypatch.setattr(picks["zpd"][0], "values", lambda w, c: value)
    most = np.flatnonzero(novelty == novelty.max())
    assert picks["novelty"][0].beyond_goal(graph, here, w) in offered[most]
    assert picks["zpd"][0].beyond_goal(graph, here, w) == offered[most[0]]  # the hardest of the most novel
    value[:] = value[::-1].copy()  # now the last is hardest
    assert picks["zpd"][0].beyond_goal(graph, here, w) == offered[most[-1]]
    for m in offered[most]:  # the agent has now been in the most novel ones: the others are new configs
        graph.add_config(int(m))
    still_new = ~np.isin(offered, np.asarray(graph.masks))
    assert still_new.any()
    for signal in SIGNALS:
        assert still_new[list(offered).index(picks[signal][0].beyond_goal(graph, here, w))]


def test_zpd_values_are_the_smaller_twin_of_the_deterministic_action_from_where_the_agent_stands():
    sp = gh.SocialPartner(N)
    picks, run = picks_on(gh.SemanticGraph(N, gh.Args(n_blocks=N)), "zpd")
    w, agent = run.workers[0], run.learner.agent
    w.env.reset()
    for p in agent.critic.parameters():  # a critic whose value depends on the goal (biases are 0 at init)
        torch.nn.init.normal_(p, std=0.3)
    here = gh.current_config(w.env)
    offered = sp.beyond_candidates(gh.SemanticGraph(N, gh.Args(n_blocks=N)), here)
    value = picks.values(w, offered)
    now = w.env.set_goal(w.env.goal)
    goals = og.from_mask(offered, N).astype(np.float32)
    k = len(goals)
    obs, ag = np.repeat(now["observation"][None], k, 0), np.repeat(now["achieved_goal"][None], k, 0)
    action = agent.act(obs, ag.astype(np.float32), goals)  # the deterministic policy's action
    o = torch.from_numpy(agent.normalizer(obs.astype(np.float32)))
    body, blocks = gh.split_obs(o, N)
    with torch.no_grad():
        msg = agent.critic.messages(agent.gi, blocks, torch.from_numpy(goals - ag.astype(np.float32)))
        q1, q2 = agent.critic.q(body, blocks, torch.from_numpy(action), msg)
    want = torch.minimum(q1, q2).numpy()
    np.testing.assert_allclose(value, want, rtol=1e-5, atol=1e-5)
    assert len(set(np.round(value, 4))) > 1  # the candidates' values differ


@pytest.mark.parametrize("signal", SIGNALS)
def test_ties_are_drawn_uniformly_from_the_workers_stream(signal, monkeypatch):
    graph = gh.SemanticGraph(N, gh.Args(n_blocks=N))  # no node: every candidate a new config
    picks, run = picks_on(graph, signal)
    offered = np.arange(5, dtype=np.int64) * 3 + 1
    monkeypatch.setattr(picks.partner, "beyond_candidates", lambda g, config: offered)
    monkeypatch.setattr(picks, "novelty", lambda g, c: np.zeros(len(c)))  # equally novel ...
    if signal == "zpd":
        monkeypatch.setattr(picks, "values", lambda w, c: np.ones(len(c)))  # ... and equally hard
    np.random.seed(0)  # noqa: NPY002 (numpy's global stream, seeded: a pick must not draw from it)
    w, uniform = stream(0), stream(0)
    drawn = [picks.beyond_goal(graph, 0, w) for _ in range(1000)]
    # one draw from the worker's stream, the uniform partner's: the same goals from the same stream
    assert drawn == [run.sampler.sp.partner.choose(uniform, offered) for _ in range(1000)]
    counts = np.array([drawn.count(int(c)) for c in offered])
    assert uniform_pvalue(counts) > 1e-4


@pytest.mark.parametrize("seed", range(3))
def test_zpd_goes_to_the_stepping_stone_its_graph_is_surest_to_arrive_at(seed):
    sp = gh.SocialPartner(N)
    graph = random_agent_graph(sp, seed, p_node=0.5, p_edge=0.4)
    rng = np.random.default_rng(seed)
    graph.sr = rng.uniform(0.05, 1.0, len(graph.sr)).tolist()  # success estimates that differ
    picks, run = picks_on(graph, "zpd")
    w = run.workers[0]
    for here in graph.masks[:: max(1, graph.n_nodes // 8)]:
        offered = sp.frontier_candidates(graph, here)
        if not len(offered):
            continue
        want = np.array([-safest_cost(graph, here, int(c)) for c in offered])
        np.testing.assert_allclose(picks.arrival(graph, here, offered), want, atol=1e-9)
        assert picks.frontier_goal(graph, here, w) in offered[want >= want.max() - 1e-9]


def test_zpd_changes_its_frontier_when_the_success_estimates_change():
    stack = M(close=[(0, 1)], above=[(0, 1)])
    graph = agent_graph([(APART, C01), (APART, stack)])  # two kinds of first step, each with its SR
    picks, run = picks_on(graph, "zpd")
    w, close_edge, stack_edge = run.workers[0], graph.edge_class(APART, C01), graph.edge_class(APART, stack)
    offered = picks.frontier_candidates(graph, APART, True)
    assert {graph.edge_class(APART, int(c)) for c in offered} == {close_edge, stack_edge}

    def frontier_kinds(sr_close: float, sr_stack: float) -> set[int]:
        graph.sr[close_edge], graph.sr[stack_edge] = sr_close, sr_stack
        goals = [picks.frontier_goal(graph, APART, w, elsewhere=True) for _ in range(30)]
        return {graph.edge_class(APART, g) for g in goals}

    assert frontier_kinds(0.9, 0.2) == {close_edge}  # the step it is surest of ...
    assert frontier_kinds(0.2, 0.9) == {stack_edge}  # ... and, once the estimates turn, the other


def renamed_classes(monkeypatch):
    """Every evaluation class under another name, and each name given to another class's configs."""
    real = og.evaluation_classes(N)
    names = list(real)
    fake = {f"class{i}": real[names[(i + 1) % len(names)]] for i in range(len(names))}
    monkeypatch.setattr(og, "evaluation_classes", lambda n: fake if n == N else real)
    monkeypatch.setattr(gh.og, "evaluation_classes", lambda n: fake if n == N else real)


@pytest.mark.parametrize("signal", SIGNALS)
def test_no_signal_reads_a_class_table_renaming_the_evaluation_classes_changes_no_pick(signal, monkeypatch):
    def goals() -> list[int]:
        torch.manual_seed(0)  # the same critic
        run, said = hme_run(learner_picks=signal, n_segments=6, segment_len=6, stable_steps=2, seed=4), []
        for _ in range(6):
            per_worker = gh.run_cycle(run)
            run.sampler.after_cycle()
            run.learner.learn_from(per_worker)
            said += [og.to_mask(s.g) for s in run.workers[0].segments]
        return said, run

    before, run_before = goals()
    renamed_classes(monkeypatch)
    after, run_after = goals()
    assert before == after
    assert run_after.sampler.partner_counts != run_before.sampler.partner_counts  # the classes were renamed


class OnlyTheOffers:
    """A social partner that offers the candidates it is given, and answers nothing else."""

    def __init__(self, offers: dict):
        self.offers = offers

    def frontier_candidates(self, graph, current: int, elsewhere: bool = False) -> np.ndarray:
        return self.offers[current, elsewhere]

    def beyond_candidates(self, graph, config: int) -> np.ndarray:
        return self.offers[config, "beyond"]

    def __getattr__(self, name):
        raise AssertionError(f"a pick read the partner's {name}: the oracle beyond the offered candidates")


def oracle_closed(monkeypatch):
    """Every read of an oracle graph (any instance: the partner's, or one a pick builds itself), and the
    oracle's own searches, raise: what a pick may still use of oracle_graph are its encodings (from_mask...)."""

    def closed(name):
        def read(*args, **kwargs):
            raise AssertionError(f"a pick read the oracle's {name}: beyond the offered candidates")

        return read

    for name, value in vars(og.OracleGraph).items():
        if not name.startswith("_") or name in ("__init__", "__contains__"):
            monkeypatch.setattr(og.OracleGraph, name, property(closed(name)) if isinstance(value, property)
                                else closed(name))  # fmt: skip
    for name in ("evaluation_classes", "is_small_step", "bfs_hops", "summary"):
        monkeypatch.setattr(og, name, closed(name))


@pytest.mark.parametrize("signal", SIGNALS)
def test_no_signal_reads_the_oracle_beyond_the_offered_candidates(signal, monkeypatch):
    # Renaming the classes catches a read keyed by class name; this, any other read of the partner or of an
    # oracle graph (stepping stones, neighbours, classes), its own or one the pick builds: the same picks when
    # nothing answers but the offers.
    sp = gh.SocialPartner(N)
    graph = random_agent_graph(sp, 2, p_node=0.4, p_edge=0.3)
    picks, run = picks_on(graph, signal)
    here = graph.masks[:: max(1, graph.n_nodes // 8)]
    offers = {(h, e): sp.frontier_candidates(graph, h, e) for h in here for e in (False, True)}
    offers |= {(h, "beyond"): sp.beyond_candidates(graph, h) for h in here}

    w = run.workers[0]  # zpd's critic reads where its worker stands
    w.env.reset()

    def all_picks() -> list:
        w.rng = np.random.default_rng(0)
        return [(picks.frontier_goal(graph, h, w, e), picks.beyond_goal(graph, h, w)) for h in here for e in (0, 1)]

    with_the_oracle = all_picks()
    picks.partner = OnlyTheOffers(offers)
    with monkeypatch.context() as m:
        oracle_closed(m)
        assert all_picks() == with_the_oracle
    assert sum(f is not None for f, _ in with_the_oracle) and sum(b is not None for _, b in with_the_oracle)


def test_learner_picks_change_what_the_partner_proposes_toward_what_novelty_promises(tmp_path, monkeypatch):
    # Each beyond goal proposed, scored as novelty promises (a config that is no node yet first, then the pairs of
    # facts no node holds together, brute force), against the best and the mean of what was offered.
    proposed = []

    def recorded(real):
        def beyond_goal(self, graph, config: int, w):
            offered = self.beyond_candidates(graph, config)
            goal = real(self, graph, config, w)
            if goal is not None:
                score = {int(c): (int(c) not in graph.masks, brute_novelty(graph, int(c))) for c in offered}
                proposed.append((score[goal], max(score.values()), sorted(score.values())))
            return goal

        return beyond_goal

    monkeypatch.setattr(gh.SocialPartner, "beyond_goal", recorded(gh.SocialPartner.beyond_goal))
    monkeypatch.setattr(lq.LearnerPicks, "beyond_goal", recorded(lq.LearnerPicks.beyond_goal))
    rows, scores = {}, {}
    for signal in ("", "novelty"):
        proposed.clear()
        flags = [*TINY, "--sp-ratio", "1", "--n-cycles", "4", "--seed", "2", "--learner-picks", signal]
        assert gh.main([*flags, "--runs-dir", str(tmp_path / (signal or "uniform"))]) == 0
        (folder,) = (tmp_path / (signal or "uniform")).iterdir()
        (rows[signal],) = csv.DictReader((folder / "progress.csv").open())
        scores[signal] = list(proposed)
    logged = {s: [r[k] for k in r if k.startswith("sp_beyond_") and "_reached_" not in k] for s, r in rows.items()}
    assert sum(map(float, logged["novelty"])) == len(scores["novelty"]) > 0 and logged[""] != logged["novelty"]
    assert all(score == best for score, best, _ in scores["novelty"])  # always the most novel offered ...
    assert any(score < best for score, best, _ in scores[""])  # ... where the uniform draw is not
    assert any(score > min(offered) for score, _, offered in scores["novelty"])  # and a choice was made


def test_the_query_counts_sr_classes_as_progress_with_ask_progress_classes():
    # nodes come, but no new kind of transition: with 'classes' the learner asks, with 'nodes' it does not
    for progress, want in (("classes", True), ("nodes", False)):
        run = hme_run(sp_ratio=0.0, ask_after=3, help_cycles=2, ask_progress=progress)
        assert any(answers(run, [1] * 8)) == want
    run = hme_run(sp_ratio=0.0, ask_after=3, help_cycles=2, ask_progress="classes")
    graph, fresh = run.learner.graph, iter(range(1, 2 ** og.config_dim(N)))
    graph.add_config(0)
    said = []
    for _ in range(8):  # a new SR class every cycle: never stalled
        classes = len(graph.sr)
        while len(graph.sr) == classes:  # (a permutation of an earlier edge is no new class)
            m = next(fresh)
            graph.add_config(m)
            graph.edge_class(0, m)
        run.learner.segments += run.args.n_segments
        said.append(run.sampler.query.asks())
    assert not any(said)


@pytest.mark.parametrize(
    "flags, says",
    [
        (["--learner-picks", "best"], "--learner-picks must be one of novelty, zpd"),
        (["--ask-progress", "edges"], "--ask-progress must be one of nodes, classes"),
        (["--ask-progress", "classes"], "--ask-progress classes does nothing without --ask-after"),
        (["--ask-progress", "nodes"], "--ask-progress nodes does nothing without --ask-after"),  # as the default
        (["--ask-progress", ""], "--ask-progress '' does nothing without --ask-after (the learner never asks)"),
        (["--help-cycles", "5"], "--help-cycles 5 does nothing without --ask-after (the learner never asks)"),
        (["--help-cycles", "3"], "--help-cycles 3 does nothing without --ask-after"),  # the default's value, given
        (["--learner-picks", "zpd", "--sp-ratio", "0"], "--learner-picks needs social cycles"),
        (["--learner-picks", "zpd", "--sp-ratio", "0.2", "--partner", "person"], "give one of them"),
    ],
)
def test_bad_learner_options_exit_2_naming_the_value_before_anything_is_written(tmp_path, capsys, flags, says):
    with pytest.raises(SystemExit) as e:
        gh.main([*TINY, *flags, "--runs-dir", str(tmp_path / "runs")])
    assert e.value.code == 2 and says in capsys.readouterr().err and not (tmp_path / "runs").exists()


def test_resume_takes_a_value_that_means_what_the_checkpoints_does_and_refuses_one_that_does_not(capsys):
    saved = {"args": dataclasses.asdict(gh.Args(n_blocks=3, ask_after=5))}  # --ask-progress '': nodes
    given = {"ask_progress", "resume"}
    args = gh.Args(n_blocks=3, ask_after=5, ask_progress="nodes", resume="checkpoint.pt")
    assert plumbing.args_from_checkpoint(args, given, saved, "--resume").ask_progress == ""  # the run's own
    with pytest.raises(SystemExit) as e:
        plumbing.args_from_checkpoint(dataclasses.replace(args, ask_progress="classes"), given, saved, "--resume")
    assert e.value.code == 2 and "--ask-progress 'classes' (checkpoint: '')" in capsys.readouterr().err
