"""A worker's random streams (SPEC §3, §11: the worker's draws and its env's block placements are
independent streams) and what its attempts record (an attempt the cycle's budget cut off is no outcome,
neither success nor failure: SPEC §6's success rates and §8's competence count attempted goals)."""

import numpy as np
import pytest
import torch

import gangstr_hme as gh
import lp_baseline as lp
import oracle_graph as og
import plumbing
import vds_baseline as vds

N = 3


def overlap(a: np.random.Generator, b: np.random.Generator, words: int = 2000) -> int:
    """How many of the next 64-bit words of two generators are the same words."""
    return len(set(a.bit_generator.random_raw(words).tolist()) & set(b.bit_generator.random_raw(words).tolist()))


def test_a_worker_and_its_env_draw_from_independent_streams():
    # One stream read twice, a few words apart (the env's reset draws the block placements first), would
    # share almost all its words; independent streams share none (2000 of 2**64 values).
    w = gh.Worker(gh.Args(n_blocks=N, seed=7), index=1)
    assert overlap(w.rng, w.env.np_random) == 0


def test_workers_with_neighbouring_seeds_draw_from_independent_streams():
    one, two = gh.Worker(gh.Args(n_blocks=N, seed=7), index=1), gh.Worker(gh.Args(n_blocks=N, seed=7), index=2)
    assert overlap(one.rng, two.rng) == 0 and overlap(one.env.np_random, two.env.np_random) == 0
    assert overlap(one.rng, two.env.np_random) == 0 and overlap(two.rng, one.env.np_random) == 0


def test_eval_only_reseeds_every_worker_and_its_env_from_the_evaluation_seed(monkeypatch, tmp_path):
    run = gh.Run(gh.Args(n_blocks=N, seed=5, num_envs=2, buffer_size=10, segment_len=10), torch.device("cpu"))
    state = plumbing.save_state(run)
    seeded = []
    monkeypatch.setattr(gh.Worker, "seed", lambda w, *words: seeded.append((w.index, words)))
    run.args = gh.Args(n_blocks=N, seed=5, num_envs=2, checkpoint=str(tmp_path / "x.pt"), eval_only=True)
    sr = dict.fromkeys([*run.classes, "global"], 0.0)
    assert plumbing.evaluate_checkpoint(run, state, lambda run, video, planner: sr) == 0
    assert seeded == [(0, (5,)), (1, (6,))]  # Worker.seed: independent streams for the worker and its env


# ------------------------------------------------------------------------------------------------
# An attempt cut off by the cycle's budget
# ------------------------------------------------------------------------------------------------
def scripted_run(module, monkeypatch, path_len: int, success: bool):
    """A run whose planner returns a path of path_len configs (start included) and whose segments all
    succeed or all fail; one worker with a budget of 2 segments."""
    run = module.Run(module.Args(n_blocks=N, segment_len=4, stable_steps=2, n_segments=2), torch.device("cpu"))
    path = [int(m) for m in og.OracleGraph(N).masks[:path_len]]
    monkeypatch.setattr(module, "sample_path", lambda graph, start, goal, rng, explore: path)

    def segments(agent, workers, requests):
        ag = [np.tile(og.from_mask(r.goal, N), (5, 1)) for r in requests]
        return [module.Segment(np.zeros((5, 10 + 15 * N), np.float32), a, a[-1], np.zeros((4, 4), np.float32),
                               success, True) for a in ag]  # fmt: skip

    monkeypatch.setattr(module, "run_segments", segments)
    return run


def autotelic_cycle_of(module, run):
    (w,) = run.workers
    w.left, w.segments = run.args.n_segments, []
    module.drive(run.learner.agent, {w: run.sampler.autotelic_cycle(w)})
    return w


@pytest.mark.parametrize(
    "path_len, success, goals, reached",
    [
        (4, True, 0, 0),  # 3 sub-goals, 2 segments: cut off after 2 successes, no outcome
        (3, True, 1, 1),  # 2 sub-goals, 2 segments: reached
        (4, False, 2, 0),  # each attempt's first sub-goal failed: two failures, however long the paths
    ],
)
def test_an_autotelic_attempt_cut_off_by_the_budget_is_neither_success_nor_failure(
    monkeypatch, path_len, success, goals, reached
):
    run = scripted_run(gh, monkeypatch, path_len, success)
    autotelic_cycle_of(gh, run)
    stats = run.sampler.stats
    assert (stats["autotelic_goals"], stats["autotelic_reached"]) == (goals, reached)
    assert run.sampler.goals >= 1  # the goal was set and pursued all the same


@pytest.mark.parametrize("module", [gh, lp, vds], ids=lambda m: m.__name__)
def test_own_goals_and_those_reached_are_counted_per_evaluation_class_in_progress_rows(module):
    run = module.Run(module.Args(n_blocks=N, buffer_size=40, segment_len=4, stable_steps=2), torch.device("cpu"))
    (w,) = run.workers
    s2, s3 = (int(og.to_mask(og.evaluation_classes(N)[name][i])) for name, i in (("S2", 1), ("S3", 0)))
    start = int(og.to_mask(og.make_config(N)))  # the start config: in no class
    for goal, reached in ((s2, True), (s2, False), (s3, False), (start, True)):
        run.sampler.goal_outcome(w, goal, reached)
    row = run.sampler.epoch_stats()
    own = {k: row[k] for k in row if k.startswith("own_")}
    want = dict.fromkeys(f"own_{kind}{name}" for kind in ("", "reached_") for name in og.evaluation_classes(N))
    assert own == {**dict.fromkeys(want, 0), "own_S2": 2, "own_reached_S2": 1, "own_S3": 1}
    assert row["autotelic_goals_reached"] == 2 / 4  # every own goal, in a class or not


@pytest.mark.parametrize(
    "path_len, success, attempts", [(4, True, []), (3, True, [(0, 1)]), (4, False, [(0, 0), (0, 0)])]
)
def test_lp_credits_no_outcome_to_a_bucket_for_an_attempt_cut_off_by_the_budget(
    monkeypatch, path_len, success, attempts
):
    run = scripted_run(lp, monkeypatch, path_len, success)
    (w,) = run.workers

    def goal_from_bucket_0(worker):
        worker.drawn_from = 0
        return int(og.OracleGraph(N).masks[path_len - 1])

    monkeypatch.setattr(run.sampler, "autotelic_goal", goal_from_bucket_0)
    autotelic_cycle_of(lp, run)
    assert [(b, int(r)) for b, r in w.attempts] == attempts
