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
    args = gh.Args(n_blocks=3, plain=True)
    agent = gh.SAC(args, fetch5_env.obs_size(3), "cpu")
    agent.normalizer.update(np.random.default_rng(0).normal(size=(10, fetch5_env.obs_size(3))))
    n = agent.normalizer
    state = dict(script="gangstr_hme", env_version=plumbing.ENV_VERSION, args=dataclasses.asdict(args), counters={},
                 actor=agent.actor.state_dict(), critic=agent.critic.state_dict(),
                 normalizer=dict(sum=torch.tensor(n.sum), sumsq=torch.tensor(n.sumsq), count=n.count))  # fmt: skip
    torch.save(state, tmp_path / "checkpoint.pt")
    return str(tmp_path / "checkpoint.pt")


def test_a_block_lifted_is_counted_from_each_blocks_height_in_the_observation(checkpoint, monkeypatch):
    # The env reports block 1 (the second block: its height at 10 + 15 + 2) 4 cm above the table from the
    # 5th step on: every episode counts a block lifted, its highest block at 0.465; the others stay at rest.
    step = fetch5_env.FetchManipulateEnv.step
    calls = {"n": 0}

    def raised(self, action):
        obs, *rest = step(self, action)
        calls["n"] += 1
        obs["observation"][10 + 2 :: 15] = probe_skill.REST_Z
        if calls["n"] % 40 >= 5:
            obs["observation"][10 + 15 + 2] = probe_skill.REST_Z + 0.04
        return obs, *rest

    monkeypatch.setattr(fetch5_env.FetchManipulateEnv, "step", raised)
    state = plumbing.load_checkpoint(gh.Args, checkpoint, "checkpoint")
    rows = probe_skill.probe(state, checkpoint, ["C1", "S2"], 3, 0)
    assert [(cls, policy) for cls, policy, *_ in rows] == [(c, p) for c in ("C1", "S2") for p in
                                                           ("deterministic", "stochastic")]  # fmt: skip
    assert all(lifted == 3 and top == pytest.approx(0.465) for *_, lifted, top in rows)


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
