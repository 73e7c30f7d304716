"""lp_baseline.py and vds_baseline.py: the same learner as gangstr_hme.py with another goal sampler
(SPEC §8): the LP arithmetic, the VDS scoring, and that nothing but the goal sampler differs."""

import csv
import difflib
import re
from pathlib import Path

import inprocess
import numpy as np
import pytest
import torch

import lp_baseline as lp
import oracle_graph as og
import plumbing
import vds_baseline as vds

ROOT = Path(__file__).resolve().parent.parent
TINY = ["--n-epochs", "1", "--n-cycles", "2", "--n-segments", "4", "--n-updates", "2", "--batch-size", "16",
        "--segment-len", "8", "--stable-steps", "3", "--eval-goals-per-class", "1", "--threads", "1"]  # fmt: skip


# ------------------------------------------------------------------------------------------------
# 1. Smoke
# ------------------------------------------------------------------------------------------------
@pytest.mark.parametrize("script", ["lp_baseline.py", "vds_baseline.py"])
@pytest.mark.parametrize("n_blocks", [3, 5])
def test_baseline_runs_end_to_end(tmp_path, script, n_blocks):
    out = inprocess.run_script(script, "--n-blocks", n_blocks, *TINY, runs_dir=tmp_path)
    assert out.returncode == 0, out.stderr
    (run_dir,) = tmp_path.iterdir()
    assert run_dir.name.startswith(script.removesuffix(".py"))
    (row,) = csv.DictReader((run_dir / "progress.csv").open())
    assert "global_sr" in row and (run_dir / "checkpoint.pt").exists()
    assert ("lp_prob_C1" in row) if script.startswith("lp") else ("vds_disagreement" in row and "vds_loss" in row)
    assert "sp_frontier_C1" not in row and "social_share" not in row


# ------------------------------------------------------------------------------------------------
# 2. Only the goal sampler differs
# ------------------------------------------------------------------------------------------------
BANNER = "# " + "-" * 96 + "\n"
GOAL_SAMPLER = [  # the goal sampler's three places in a script, each found once
    r"(?s)\A.*?(?=^from __future__)",  # 1. the header comment and module docstring
    r"(?s)^    # --- the goal sampler: .*?(?=^    # --- )",  # 2. its Args group
    rf"(?s)^{BANNER}# The goal sampler[^\n]*\n{BANNER}.*?(?=^{BANNER})",  # 3. its section
]


def without_goal_sampler(text: str) -> str:
    """The file minus its goal sampler, which has one home in each script: (1) the module docstring and
    header comment (all before `from __future__`), (2) the Args group from its `    # --- the goal
    sampler: ... ---` line to the next group's, (3) the section from the banner `# The goal sampler...`
    to the next banner. Three substitutions, each matching once; nothing else."""
    for pattern in GOAL_SAMPLER:
        text, n = re.subn(pattern, "", text, flags=re.MULTILINE)
        assert n == 1, f"{pattern!r} matched {n} times"
    return text


@pytest.mark.parametrize("script", ["lp_baseline.py", "vds_baseline.py"])
def test_a_baseline_differs_from_gangstr_hme_only_in_its_goal_sampler(script):
    reference = without_goal_sampler((ROOT / "gangstr_hme.py").read_text())
    assert "class SocialPartner" not in reference and "def social_cycle" not in reference
    assert without_goal_sampler((ROOT / script).read_text()) == reference


@pytest.mark.parametrize("script", ["lp_baseline.py", "vds_baseline.py"])
def test_diff_u_of_gangstr_hme_and_a_baseline_has_at_most_3_hunks(script):
    """The README's promise (forking a sampler): `diff -u gangstr_hme.py <baseline>` shows 3 hunks, the
    module docstring, the Args sampler group and the goal-sampler section. Counted as difflib.unified_diff
    prints them (3 lines of context: changes closer than 7 lines share a hunk), as diff -u does."""
    ours, theirs = ((ROOT / name).read_text().splitlines() for name in ("gangstr_hme.py", script))
    groups = difflib.SequenceMatcher(None, ours, theirs, autojunk=False).get_grouped_opcodes(3)
    hunks = [f"@@ -{g[0][1] + 1},{g[-1][2] - g[0][1]} +{g[0][3] + 1},{g[-1][4] - g[0][3]} @@" for g in groups]
    assert len(hunks) <= 3, hunks


# ------------------------------------------------------------------------------------------------
# 3. LP arithmetic
# ------------------------------------------------------------------------------------------------
def test_lp_is_the_gap_between_the_newer_and_the_older_half_of_the_window():
    tracker = lp.LearningProgress(3, window=200, min_outcomes=20, uniform_prob=0.1)
    for _ in range(30):
        tracker.record(0, False)
    for _ in range(30):
        tracker.record(0, True)  # 0 0 ... 0 1 1 ... 1: halves 0 and 1
    for reached in [True, False] * 10:
        tracker.record(1, reached)  # halves of 10 with 5 successes each: no progress
    np.testing.assert_allclose(tracker.progress(), [1.0, 0.0, 0.0])
    np.testing.assert_allclose(tracker.competence()[:2], [0.5, 0.5])
    assert np.isnan(tracker.competence()[2])


def test_lp_needs_20_outcomes_and_keeps_only_the_last_200():
    tracker = lp.LearningProgress(1, window=200, min_outcomes=20, uniform_prob=0.1)
    for _ in range(19):
        tracker.record(0, True)
    assert tracker.progress()[0] == 0.0  # 19 outcomes: not yet
    tracker.record(0, False)
    assert tracker.progress()[0] == pytest.approx(abs(9 / 10 - 1.0))  # 20: halves of 10
    for _ in range(300):
        tracker.record(0, False)
    for _ in range(100):
        tracker.record(0, True)
    assert len(tracker.outcomes[0]) == 200  # the window: the older half is the last 100 failures
    assert tracker.progress()[0] == pytest.approx(1.0)


def test_bucket_probabilities_mix_10_percent_uniform_with_lp_and_fall_back_to_uniform():
    tracker = lp.LearningProgress(4, window=200, min_outcomes=20, uniform_prob=0.1)
    nonempty = np.array([True, True, True, False])
    np.testing.assert_allclose(tracker.probabilities(nonempty), [1 / 3, 1 / 3, 1 / 3, 0])  # all LP 0
    for reached in [False] * 10 + [True] * 10:
        tracker.record(0, reached)  # LP 1
    for reached in [False] * 15 + [True] * 5 + [False] * 10 + [True] * 10:
        tracker.record(1, reached)  # halves: 5/20 and 10/20, LP 0.25
    for reached in [False] * 10 + [True] * 10:
        tracker.record(3, reached)  # LP 1 but empty: never drawn
    p = tracker.probabilities(nonempty)
    np.testing.assert_allclose(p, 0.1 * np.array([1, 1, 1, 0]) / 3 + 0.9 * np.array([1.0, 0.25, 0, 0]) / 1.25)
    assert p.sum() == pytest.approx(1.0)


def test_lp_goals_come_from_discovered_configs_of_the_drawn_class():
    run = lp.Run(lp.Args(n_blocks=3, n_segments=1, segment_len=5, stable_steps=2), torch.device("cpu"))
    graph, sampler = run.learner.graph, run.sampler
    apart = int(og.to_mask(og.make_config(3)))
    graph.add_config(apart)
    (w,) = run.workers
    assert sampler.autotelic_goal(w) == apart and w.drawn_from is None  # no bucket yet: autotelic
    c01 = int(og.to_mask(og.make_config(3, close=[(0, 1)])))
    graph.add_config(c01)  # the 3 configs of C1 are discovered
    goals = {sampler.autotelic_goal(w) for _ in range(50)}
    assert goals == set(og.to_mask(og.evaluation_classes(3)["C1"]).tolist())
    sampler.goal_outcome(w, c01, True)
    sampler.goal_outcome(w, c01, False)
    assert w.attempts == [(0, True), (0, False)] and w.drawn_from == 0
    sampler.after_cycle()  # the cycle's outcomes are recorded at its end (with every worker's, SPEC §11)
    assert list(sampler.lp.outcomes[0]) == [1.0, 0.0] and w.attempts == []


# ------------------------------------------------------------------------------------------------
# 4. VDS scoring and learning
# ------------------------------------------------------------------------------------------------
def vds_run(**kw):
    run = vds.Run(vds.Args(n_blocks=3, **kw), torch.device("cpu"))
    run.learner.agent.normalizer.add(np.zeros(55), np.ones(55) * 4, 4)
    return run


def test_disagreement_is_the_std_of_the_heads_q_values_for_each_candidate():
    run = vds_run()
    agent, sampler = run.learner.agent, run.sampler
    candidates = og.to_mask(og.evaluation_classes(3)["S2"])
    (w,) = run.workers
    score = sampler.disagreement(w, candidates)
    obs = w.env.set_goal(w.env.goal)
    with torch.no_grad():
        for c, s in zip(candidates, score, strict=True):
            o = torch.as_tensor(agent.normalizer(obs["observation"])[None])
            ag, g = torch.as_tensor(obs["achieved_goal"][None]), torch.as_tensor(og.from_mask(c, 3)[None])
            body, blocks = vds.split_obs(o, 3)
            a = torch.tanh(agent.actor(body, blocks, agent.critic.messages(agent.gi, blocks, g - ag))[0])
            q = torch.stack([h(sampler.readout(o, ag, g, a)) for h in sampler.vds.heads]).squeeze()
            assert s == pytest.approx(q.std().item(), rel=1e-4)  # fmt: skip
    assert score.std() > 0  # goals differ


@pytest.mark.parametrize("temperature", [1.0, 0.25])
def test_goals_are_drawn_in_proportion_to_softmax_of_disagreement_over_temperature(monkeypatch, temperature):
    run = vds_run(vds_temperature=temperature)
    for c in og.to_mask(og.evaluation_classes(3)["C1"]):
        run.learner.graph.add_config(int(c))
    nodes = np.asarray(run.learner.graph.masks)
    scores = dict(zip(nodes.tolist(), [0.0, 0.5, 1.0], strict=True))
    monkeypatch.setattr(run.sampler, "disagreement", lambda w, cand: np.array([scores[int(c)] for c in cand]))
    draws = [run.sampler.autotelic_goal(run.workers[0]) for _ in range(6000)]
    freq = np.array([draws.count(m) for m in nodes]) / len(draws)
    weights = np.exp(np.array([0.0, 0.5, 1.0]) / temperature)  # SPEC §8: softmax(score / temperature)
    expected = weights / weights.sum()
    np.testing.assert_allclose(freq, expected, atol=0.02)


def test_a_tiny_temperature_draws_the_most_disputed_goal_instead_of_failing(monkeypatch):
    run = vds_run(vds_temperature=1e-300)  # scores / 1e-300 overflow: softmax must shift them first
    for c in og.to_mask(og.evaluation_classes(3)["C1"]):
        run.learner.graph.add_config(int(c))
    nodes = np.asarray(run.learner.graph.masks)
    scores = dict(zip(nodes.tolist(), [0.0, 0.5, 1.0], strict=True))
    monkeypatch.setattr(run.sampler, "disagreement", lambda w, cand: np.array([scores[int(c)] for c in cand]))
    assert {run.sampler.autotelic_goal(run.workers[0]) for _ in range(50)} == {int(nodes[2])}


@pytest.mark.parametrize(
    "script, argv, named",
    [
        ("lp_baseline.py", ["--lp-min-outcomes", "300", "--lp-window", "200"], "300"),
        ("vds_baseline.py", ["--vds-temperature", "0"], "0"),
        ("vds_baseline.py", ["--vds-temperature", "nan"], "nan"),
    ],
)
def test_a_bad_sampler_value_exits_2_naming_it(script, argv, named, capsys):
    module = lp if script.startswith("lp") else vds
    with pytest.raises(SystemExit) as e:
        plumbing.parse_args(module.Args, module.check_sampler_args, argv)
    err = capsys.readouterr().err
    assert e.value.code == 2 and named in err and len(err.strip().splitlines()) == 1


def test_at_most_1000_candidates_are_scored_all_from_the_agent_graph(monkeypatch):
    run = vds_run()
    assert run.learner.graph.n_nodes == 0
    for i in range(2500):
        run.learner.graph._add_node(i)  # plain ids as configs
    seen = []
    monkeypatch.setattr(run.sampler, "disagreement", lambda w, cand: seen.append(cand) or np.zeros(len(cand)))
    run.sampler.autotelic_goal(run.workers[0])
    assert len(seen[0]) == 1000 and len(set(seen[0].tolist())) == 1000 and seen[0].max() < 2500


def test_vds_heads_regress_the_critics_td_targets():
    run = vds_run()
    agent, rng = run.learner.agent, np.random.default_rng(0)
    from test_gangstr import filled_buffer  # noqa: PLC0415

    buf = filled_buffer()
    sampler, losses = run.sampler, []
    for _ in range(60):
        agent.update(buf.sample(64, [rng], 0.8, "final"))
        batch, target = agent.last_batch, agent.last_target
        with torch.no_grad():  # SPEC §8: each head's squared error to the critic's TD target, summed over heads
            heads = sampler.vds(sampler.readout(batch["obs"], batch["ag"], batch["g"], batch["action"]))
            by_hand = ((heads - target[None]) ** 2).mean(1).sum().item()
        assert float(sampler.train_vds(batch, target)["vds_loss"]) == pytest.approx(by_hand, rel=1e-5)
        losses.append(by_hand)
    assert np.mean(losses[-10:]) < 0.5 * np.mean(losses[:10])


@pytest.mark.parametrize("argv, heads, critic", [([], 3e-4, 3e-4), (["--lr-critic", "5e-4"], 5e-4, 5e-4),
                                                 (["--init-from", "{file}"], 1e-3, 1e-4)])  # fmt: skip
def test_vds_heads_learn_at_the_critics_rate_but_not_at_init_froms_share_of_it(monkeypatch, tmp_path, argv, heads,
                                                                               critic):  # fmt: skip
    monkeypatch.delenv("WORLD_SIZE", raising=False)
    (tmp_path / "agent.pt").write_bytes(b"")  # only its path is read here
    argv = [a.format(file=tmp_path / "agent.pt") for a in argv]
    args = plumbing.parse_args(vds.Args, vds.check_sampler_args, ["--n-blocks", "3", "--buffer-size", "400", *argv])
    run = vds.Run(args, "cpu")  # the heads start untrained beside a trained critic (SPEC §8)
    assert run.sampler.vds_opt.param_groups[0]["lr"] == pytest.approx(heads, rel=1e-12)
    assert run.learner.agent.critic_opt.param_groups[0]["lr"] == pytest.approx(critic, rel=1e-12)
