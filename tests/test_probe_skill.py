"""benchmarks/probe_skill.py: what a checkpoint's policy does with the blocks, one segment from a reset."""

import dataclasses
import sys
from pathlib import Path

import numpy as np
import pytest
import torch

import fetch5_env
import gangstr_hme as gh
import plumbing

sys.path.insert(0, str(Path(__file__).resolve().parent.parent / "benchmarks"))
import probe_skill  # noqa: E402


@pytest.fixture
def checkpoint(tmp_path):
    """A fresh 3-block agent saved as a run's checkpoint holds it (the keys load_checkpoint reads)."""
    torch.manual_seed(0)
    args = gh.Args(n_blocks=3, plain=True)
    agent = gh.SAC(args, fetch5_env.obs_size(3), "cpu")
    agent.normalizer.update(np.random.default_rng(0).normal(size=(10, fetch5_env.obs_size(3))))
    n = agent.normalizer
    state = dict(script="gangstr_hme", env_version=plumbing.ENV_VERSION, args=dataclasses.asdict(args), counters={},
                 actor=agent.actor.state_dict(), critic=agent.critic.state_dict(),
                 normalizer=dict(sum=torch.tensor(n.sum), sumsq=torch.tensor(n.sumsq), count=n.count))  # fmt: skip
    torch.save(state, tmp_path / "checkpoint.pt")
    return str(tmp_path / "checkpoint.pt")


def test_lifted_and_reached_are_counted_from_the_blocks_heights_and_the_segments_last_step(checkpoint, monkeypatch):
    # From the 5th step of each segment the env reports block 1 4 cm above its rest, and a reward on the
    # segment's last step in the 1st and 3rd episodes of each class and policy, on a middle step in the 2nd:
    # every episode counts a block lifted, its highest block at rest + 4 cm; 2 of 3 goals count as reached.
    step, positions = fetch5_env.FetchManipulateEnv.step, fetch5_env.FetchManipulateEnv.block_positions
    calls = {"steps": 0}

    def stepped(self, action):
        obs, _, *rest = step(self, action)
        calls["steps"] += 1
        t, episode = (calls["steps"] - 1) % 40, (calls["steps"] - 1) // 40
        return obs, float(t == (20 if episode % 3 == 1 else 39)), *rest

    def raised(self):
        z = positions(self)
        z[:, 2] = probe_skill.REST_Z
        z[1, 2] += 0.04 * ((calls["steps"] - 1) % 40 >= 4)
        return z

    monkeypatch.setattr(fetch5_env.FetchManipulateEnv, "step", stepped)
    monkeypatch.setattr(fetch5_env.FetchManipulateEnv, "block_positions", raised)
    state = plumbing.load_checkpoint(gh.Args, checkpoint, "checkpoint")
    rows = probe_skill.probe(state, checkpoint, ["C1", "S2"], 3, 0)
    assert [(cls, policy) for cls, policy, *_ in rows] == [(c, p) for c in ("C1", "S2") for p in
                                                           ("deterministic", "stochastic")]  # fmt: skip
    assert all(reached == 2 and lifted == 3 for _, _, reached, lifted, _ in rows)
    assert all(top == pytest.approx(probe_skill.REST_Z + 0.04) for *_, top in rows)


def test_both_policies_pursue_the_same_goals_and_only_the_stochastic_one_draws_noise(checkpoint, monkeypatch):
    goals, noises = [], []
    reset, act = fetch5_env.FetchManipulateEnv.reset, gh.SAC.act
    monkeypatch.setattr(fetch5_env.FetchManipulateEnv, "reset",
                        lambda self, seed=None, options=None: goals.append(options["goal"].copy()) or
                        reset(self, seed=seed, options=options))  # fmt: skip
    monkeypatch.setattr(
        gh.SAC, "act", lambda self, o, ag, g, noise=None: noises.append(noise) or act(self, o, ag, g, noise)
    )
    state = plumbing.load_checkpoint(gh.Args, checkpoint, "checkpoint")
    state["args"]["segment_len"] = 3  # the segment's length is the checkpoint's own
    probe_skill.probe(state, checkpoint, ["C2"], 4, 0)
    assert len(goals) == 8 and all((a == b).all() for a, b in zip(goals[:4], goals[4:], strict=True))
    assert len(noises) == 24 and all(n is None for n in noises[:12]) and all(n is not None for n in noises[12:])


def test_an_untrained_agent_lifts_no_block_and_the_rows_count_within_the_episodes(checkpoint, capsys):
    assert probe_skill.main([checkpoint, "--episodes", "2", "--classes", "S2"]) == 0
    out = capsys.readouterr().out.splitlines()
    assert out[2].split()[:4] == ["S2", "deterministic", "0/2", "0/2"] and out[3].split()[:2] == ["S2", "stochastic"]


@pytest.mark.parametrize(("argv", "named"), [(["--episodes", "0"], "0"), (["--classes", "S4"], "'S4'")])
def test_bad_arguments_exit_2_naming_the_value(checkpoint, argv, named, capsys):
    with pytest.raises(SystemExit) as e:
        probe_skill.main([checkpoint, *argv])
    err = capsys.readouterr().err.strip().splitlines()
    assert e.value.code == 2 and len(err) == 1 and named in err[0]
