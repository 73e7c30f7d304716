"""What a fork of a training script may change without silently breaking the run: a goal sampler that spends
too few or too many of a cycle's segments is stopped at once, naming itself and the worker (Sampler's
contract); a changed MLP takes the update off speed.py's fast nets, which implement the nets as written;
--plain turns every speed trick off. The README's example sampler, forked as the README says, trains and
resumes, and the README names every hook of Sampler."""

import csv
import math
import os
import re
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import torch
import torch.nn.functional as F
from test_baselines import BANNER, GOAL_SAMPLER, TINY

import gangstr_hme as gh
import lp_baseline as lp
import oracle_graph as og
import plumbing
import speed
import vds_baseline as vds

ROOT = Path(__file__).resolve().parent.parent
N = 3
SCRIPTS = [gh, lp, vds]


# ------------------------------------------------------------------------------------------------
# A cycle spends exactly its worker's budget
# ------------------------------------------------------------------------------------------------
def run_with_cycle(module, monkeypatch, segments_of_worker: dict[int, int]):
    """A two-worker run whose sampler's cycle asks worker i for segments_of_worker[i] segments, whatever its
    budget (2); segments are made up (no physics, no network)."""
    run = module.Run(module.Args(n_blocks=N, segment_len=4, stable_steps=2, n_segments=2, num_envs=2), "cpu")
    goal = int(og.OracleGraph(N).masks[1])

    def cycle(w):
        asked = 0
        while asked < segments_of_worker[w.index]:
            asked += 1
            yield module.Request(goal, deterministic=False)

    def segments(agent, workers, requests):
        ag = [np.tile(og.from_mask(r.goal, N), (5, 1)) for r in requests]
        return [module.Segment(np.zeros((5, 10 + 15 * N), np.float32), a, a[-1], np.zeros((4, 4), np.float32),
                               True, True) for a in ag]  # fmt: skip

    monkeypatch.setattr(run.sampler, "cycle", cycle)
    monkeypatch.setattr(module, "run_segments", segments)
    return run


@pytest.mark.parametrize("module", SCRIPTS, ids=lambda m: m.__name__)
@pytest.mark.parametrize(
    "spent, said",
    [(1, "spent 1 of worker 1's 2 segments"), (3, "asked for more than worker 1's segments"),
     (math.inf, "asked for more than worker 1's segments")],  # a cycle that never ends: stopped at once
    ids=["too-few", "too-many", "endless"],
)  # fmt: skip
def test_a_cycle_that_does_not_spend_its_budget_stops_the_run_naming_the_sampler_and_the_worker(
    module, monkeypatch, spent, said
):
    run = run_with_cycle(module, monkeypatch, {0: 2, 1: spent})
    with pytest.raises(SystemExit) as e:
        module.run_cycle(run)
    message = str(e.value.code)
    assert len(message.splitlines()) == 1
    assert f"GoalSampler.cycle {said} this cycle" in message


@pytest.mark.parametrize("module", SCRIPTS, ids=lambda m: m.__name__)
def test_a_cycle_that_spends_its_budget_passes_the_check(module, monkeypatch):
    run = run_with_cycle(module, monkeypatch, {0: 2, 1: 2})
    assert [len(segments) for segments in module.run_cycle(run)] == [2, 2]


# ------------------------------------------------------------------------------------------------
# The fast nets (speed.py: the CPU kernels, the large nets' products) implement MLP as written; --plain
# ------------------------------------------------------------------------------------------------
def spy_on_kernels(monkeypatch) -> list[str]:
    """The names of speed.py's CPU kernels as the update calls them."""
    calls = []
    for name in ("NodeNet", "EdgeMax", "Head"):
        kernel = getattr(speed, name)
        monkeypatch.setattr(kernel, "apply", lambda *a, _apply=kernel.apply, _n=name: calls.append(_n) or _apply(*a))
    return calls


def random_batch(agent, seed: int = 0) -> dict:
    """A HER batch of 32 from a replay of 4 made-up segments; the agent's normalizer fitted to them."""
    rng = np.random.default_rng(seed)
    dim, obs_dim, T = og.config_dim(N), 10 + 15 * N, 6
    buf = gh.ReplayBuffer(1, 4, T, obs_dim, dim)
    configs = lambda *shape: rng.choice(np.int8([-1, 1]), size=shape)  # noqa: E731
    obs = rng.normal(size=(1, 4, T + 1, obs_dim)).astype(np.float32)
    buf.store(obs, configs(1, 4, T + 1, dim), configs(1, 4, dim), rng.uniform(-1, 1, (1, 4, T, 4)))
    agent.normalizer.update(obs)
    return buf.sample(32, [rng], 0.8, "final")


def one_update(module, args) -> torch.nn.Module:
    agent = module.SAC(args, 10 + 15 * N, torch.device("cpu"))
    agent.update(random_batch(agent))
    return agent


def tanh_mlp(self, x):
    """A fork's MLP: tanh in place of the first ReLU (its update, off the kernels, runs this too)."""
    x = F.linear(torch.tanh(F.linear(x, self.hidden.weight, self.hidden.bias)), self.out.weight, self.out.bias)
    return F.relu(x) if self.out_relu else x


@pytest.mark.parametrize("module", SCRIPTS, ids=lambda m: m.__name__)
def test_the_update_runs_the_cpu_kernels_on_the_nets_they_implement(module, monkeypatch):
    calls = spy_on_kernels(monkeypatch)
    agent = one_update(module, module.Args(n_blocks=N))
    assert agent.fast_nets and {"NodeNet", "EdgeMax", "Head"} <= set(calls)


@pytest.mark.parametrize("module", SCRIPTS, ids=lambda m: m.__name__)
def test_a_fork_that_changes_mlp_gets_the_plain_nets_said_in_one_line(module, monkeypatch, capsys):
    monkeypatch.setattr(module.MLP, "forward", tanh_mlp)
    calls = spy_on_kernels(monkeypatch)
    agent = one_update(module, module.Args(n_blocks=N))
    out = capsys.readouterr().out
    assert not agent.fast_nets and len(out.strip().splitlines()) == 1 and "fast nets off" in out
    calls.clear()
    agent.update(random_batch(agent, seed=1))
    assert calls == []  # the update ran the fork's nets, not the kernels


def test_a_fork_that_changes_an_aggregation_gets_the_plain_nets(monkeypatch, capsys):
    def mean_over_edges(net, edges, n):  # a fork's message passing: mean in place of max
        m = net(edges)
        return m.reshape(len(m), n, n - 1, m.shape[-1]).mean(dim=2)

    monkeypatch.setattr(gh, "edge_max", mean_over_edges)
    assert not gh.SAC(gh.Args(n_blocks=N), 10 + 15 * N, torch.device("cpu")).fast_nets
    assert "fast nets off" in capsys.readouterr().out


def test_a_fork_whose_mlp_computes_the_same_values_but_other_gradients_gets_the_plain_nets(monkeypatch, capsys):
    def detached_hidden(self, x):  # the message and node nets' values, but no gradient to their first layers
        w1, b1, w2, b2 = self.params()
        h = F.relu(F.linear(x, w1, b1))
        x = F.linear(h.detach() if self.large else h, w2, b2)
        return F.relu(x) if self.out_relu else x

    monkeypatch.setattr(gh.MLP, "forward", detached_hidden)
    assert not gh.SAC(gh.Args(n_blocks=N), 10 + 15 * N, torch.device("cpu")).fast_nets
    assert "fast nets off" in capsys.readouterr().out


def test_off_the_cpu_kernels_the_probe_still_holds_the_fast_nets_to_mlp(monkeypatch, capsys):
    """On a GPU or under --compile the fast nets are the large nets' products in the update's dtype (speed.py's
    fast_forward, MLP written again): the probe without the kernels finds a changed MLP too."""
    agent = gh.SAC(gh.Args(n_blocks=N, plain=True), 10 + 15 * N, torch.device("cpu"))
    calls = spy_on_kernels(monkeypatch)
    assert speed.fast_nets_compute(agent, gh, kernels=False) and calls == []  # the products alone, no kernel
    monkeypatch.setattr(gh.MLP, "forward", tanh_mlp)
    assert not speed.fast_nets_compute(agent, gh, kernels=False)
    assert "fast nets off" in capsys.readouterr().out


@pytest.mark.parametrize("module", SCRIPTS, ids=lambda m: m.__name__)
def test_plain_turns_every_speed_trick_off(module, monkeypatch):
    freed = []
    monkeypatch.setattr(speed, "keep_freed_memory", lambda: freed.append(True))
    calls = spy_on_kernels(monkeypatch)
    agent = one_update(module, module.Args(n_blocks=N, plain=True))
    assert agent.compute_losses == agent.losses and calls == [] and freed == []
    assert not agent.actor_opt.defaults["fused"] and not agent.critic_opt.defaults["fused"]
    fast = one_update(module, module.Args(n_blocks=N))
    assert fast.actor_opt.defaults["fused"] and fast.critic_opt.defaults["fused"] and freed == [True]


@pytest.mark.parametrize("flags, named", [(["--compile"], "--compile"), (["--precision", "bf16"], "--precision bf16")])
def test_plain_refuses_the_speed_flags_in_one_line(monkeypatch, capsys, flags, named):
    monkeypatch.setattr(speed, "fast_bf16", lambda cuda: True)
    with pytest.raises(SystemExit) as e:
        plumbing.parse_args(gh.Args, gh.check_sampler_args, ["--plain", *flags])
    err = capsys.readouterr().err
    assert e.value.code == 2 and len(err.strip().splitlines()) == 1 and "--plain" in err and named in err


# ------------------------------------------------------------------------------------------------
# The README's fork: its example sampler in a copy of gangstr_hme.py trains, checkpoints and resumes
# ------------------------------------------------------------------------------------------------
def readme_fork() -> str:
    """gangstr_hme.py forked as the README's "Forking a goal sampler" says: the Args group `# --- the goal
    sampler` replaced with the fork's options (the example has none) and the section "The goal sampler"
    with the README's example (found as test_baselines finds a baseline's sampler)."""
    readme = (ROOT / "README.md").read_text()
    (section,) = re.findall(r"^## Forking a goal sampler.*?(?=^## )", readme, flags=re.MULTILINE | re.DOTALL)
    (example,) = re.findall(r"^```python\n(.*?)^```", section, flags=re.MULTILINE | re.DOTALL)
    text = (ROOT / "gangstr_hme.py").read_text()
    ours = [
        "    # --- the goal sampler: uniform over the oracle's configs ---\n",
        f"{BANNER}# The goal sampler: uniform over the oracle's configs\n{BANNER}{example}\n\n",
    ]
    for pattern, replacement in zip(GOAL_SAMPLER[1:], ours, strict=True):
        text, n = re.subn(pattern, lambda _, r=replacement: r, text, flags=re.MULTILINE)
        assert n == 1, f"{pattern!r} matched {n} times"
    return text


TIMINGS = ("time_collect", "time_update", "time_eval", "time_plan_and_graph", "steps_per_second")


def test_the_readmes_example_sampler_forked_into_gangstr_hme_trains_checkpoints_and_resumes(tmp_path):
    fork = tmp_path / "uniform_sampler.py"
    fork.write_text(readme_fork())
    assert "class SocialPartner" not in fork.read_text() and "def autotelic_goal" in fork.read_text()
    env = os.environ | {"PYTHONPATH": os.pathsep.join([str(ROOT), *filter(None, [os.environ.get("PYTHONPATH")])])}

    def run(*flags):
        cmd = [sys.executable, str(fork), *flags, "--runs-dir", str(tmp_path / "runs")]
        out = subprocess.run(cmd, cwd=tmp_path, env=env, capture_output=True, text=True, timeout=300)
        assert out.returncode == 0, out.stdout[-2000:] + out.stderr[-2000:]

    run(*TINY, "--n-blocks", "3", "--n-epochs", "2")
    (folder,) = (tmp_path / "runs").iterdir()
    assert folder.name.startswith("uniform_sampler__")
    first = list(csv.DictReader((folder / "progress.csv").open()))
    run("--resume", str(folder / "checkpoint.pt"), "--n-epochs", "3")
    rows = list(csv.DictReader((folder / "progress.csv").open()))
    assert [r["epoch"] for r in rows] == ["0", "1", "2"]
    assert [{k: v for k, v in r.items() if k not in TIMINGS} for r in rows[:2]] == [
        {k: v for k, v in r.items() if k not in TIMINGS} for r in first
    ]  # the resumed run keeps the rows it had, and goes on from them
    steps = [int(r["env_steps"]) for r in rows]
    assert steps == [64, 128, 192]  # 2 cycles x 4 segments x 8 steps an epoch (TINY)
    assert "autotelic_goals_reached" in rows[0] and "social_share" not in rows[0]  # the fork's sampler logged


def test_the_readmes_fork_section_names_every_hook_of_sampler():
    readme = (ROOT / "README.md").read_text()
    (section,) = re.findall(r"^## Forking a goal sampler.*?(?=^## )", readme, flags=re.MULTILINE | re.DOTALL)
    hooks = [name for name, f in vars(gh.Sampler).items() if callable(f) and not name.startswith("_")]
    assert "goal_outcome" in hooks and "after_update" in hooks
    left_out = [h for h in hooks if not re.search(rf"(?:`|`Sampler\.|def ){h}\b", section)]  # in text or the example
    assert not left_out, f"hooks of Sampler the README does not name: {left_out}"
