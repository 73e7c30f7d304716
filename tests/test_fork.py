"""What a fork of a training script may change without silently breaking the run: a goal sampler that spends
too few or too many of a cycle's segments is stopped at once, naming itself and the worker (Sampler's
contract); a changed MLP takes the update off speed.py's fast nets, which implement the nets as written; a
changed optimizer keeps every parameter group, setting and moment under Adam's fused step, or is kept as built,
said in one line, where that step cannot stand in for it; --plain turns every speed trick off. The README's
example sampler, forked as the README says, trains and resumes, and the README names every hook of Sampler."""

import csv
import inspect
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


@pytest.mark.parametrize("kinked", [{1}, {1, 2}], ids=["first-batch-alone", "every-batch"])
def test_a_gradient_sent_the_other_way_on_one_batch_alone_is_a_kinks_rounding_and_leaves_the_fast_nets_on(
    monkeypatch, capsys, kinked
):
    """Within float rounding of a kink (a ReLU's 0, a max's tie), a sample's gradient goes one way in the plain
    nets and the other in the fast ones, on one batch: the probe's second batch tells that from a fork's net,
    which differs on every batch. The kink is made here (a loss of the same value, a gradient moved), so that it
    does not hang on a CPU's rounding; the weights are seeded, since a kink of their own on the second batch
    too (1 seed in 150 here, 107) would be a kink on every batch."""
    torch.manual_seed(0)
    agent = gh.SAC(gh.Args(n_blocks=N, plain=True), 10 + 15 * N, torch.device("cpu"))
    losses, fast_batches, w = agent.losses, [], next(agent.critic.parameters())

    def losses_with_a_kink(batch):
        critic_loss, *rest = losses(batch)
        if gh.MLP.forward is speed.fast_forward:  # within fast_nets
            fast_batches.append(batch)
            if len(fast_batches) in kinked:
                critic_loss = critic_loss + 1e-2 * (w - w.detach()).flatten()[0]  # the same value, moved gradient
        return critic_loss, *rest

    monkeypatch.setattr(agent, "losses", losses_with_a_kink)
    same = speed.fast_nets_compute(agent, gh, kernels=True)
    assert len(fast_batches) == 2 and not torch.equal(fast_batches[0]["obs"], fast_batches[1]["obs"])
    assert same == (kinked == {1}) and ("fast nets off" in capsys.readouterr().out) == (not same)


def test_a_value_off_on_one_batch_alone_is_no_kink_and_turns_the_fast_nets_off(monkeypatch, capsys):
    """A kink moves a gradient, never a value: a loss or TD target that differs on the probe's first batch
    alone (a fork's net that differs on some inputs) turns the fast nets off, as it did before the second
    batch."""
    agent = gh.SAC(gh.Args(n_blocks=N, plain=True), 10 + 15 * N, torch.device("cpu"))
    losses, fast_batches = agent.losses, []

    def losses_off_on_one_batch(batch):
        critic_loss, *rest = losses(batch)
        if gh.MLP.forward is speed.fast_forward:  # within fast_nets
            fast_batches.append(batch)
            if len(fast_batches) == 1:
                critic_loss = critic_loss + 1e-2  # another value, the same gradient
        return critic_loss, *rest

    monkeypatch.setattr(agent, "losses", losses_off_on_one_batch)
    assert not speed.fast_nets_compute(agent, gh, kernels=True)
    assert len(fast_batches) == 1 and "fast nets off" in capsys.readouterr().out


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
# A fork's optimizer: Adam's fused step keeps its groups and settings, or leaves it as built
# ------------------------------------------------------------------------------------------------
def forked_agent(critic_opt=torch.optim.AdamW, second_group: dict | None = None, **critic_settings):
    """A SAC whose optimizers a fork changed, before the fast path: the actor's and critic's weights in two
    parameter groups, the second at its own rate, betas and weight decay (defaults: the fork's rate, betas,
    eps and weight decay); the critic's optimizer `critic_opt`, by default AdamW with amsgrad, its second
    group with the settings `second_group` besides."""
    agent = gh.SAC(gh.Args(n_blocks=N, plain=True), 10 + 15 * N, torch.device("cpu"))

    def two_groups(net, adam, second=None, **settings):
        params = list(net.parameters())
        second = dict(params=params[2:], lr=3e-3, betas=(0.5, 0.9), weight_decay=0.2, **(second or {}))
        return adam([dict(params=params[:2]), second], lr=1e-4, betas=(0.8, 0.99), eps=1e-6, weight_decay=0.1,
                    **settings)  # fmt: skip

    agent.actor_opt = two_groups(agent.actor, torch.optim.Adam)
    agent.critic_opt = two_groups(agent.critic, critic_opt, second_group, **(critic_settings or dict(amsgrad=True)))
    return agent


def settings(opt, but: tuple[str, ...] = ("fused",)) -> list[dict]:
    """The optimizer's defaults, then each parameter group's settings and weights (by id), all but those named
    in `but` (by default, whether the fused step steps them)."""
    groups = [{**g, "params": [id(p) for p in g.get("params", ())]} for g in (opt.defaults, *opt.param_groups)]
    return [{k: v for k, v in g.items() if k not in but} for g in groups]


def test_a_fork_that_changes_adams_groups_and_settings_keeps_them_all_under_the_fused_step(capsys):
    agent = forked_agent()
    opts = agent.actor_opt, agent.critic_opt
    built = [settings(opt) for opt in opts]
    speed.fast_update(agent)  # as the fork's SAC.__init__ ends, without --plain
    assert [settings(opt) for opt in (agent.actor_opt, agent.critic_opt)] == built
    assert all(g["fused"] for opt in opts for g in (opt.defaults, *opt.param_groups))
    assert agent.actor_opt is opts[0] and agent.critic_opt is opts[1]  # whatever holds them still steers them
    assert "fused Adam off" not in capsys.readouterr().out
    second = [p for opt in opts for p in opt.param_groups[1]["params"]]
    before = [p.detach().clone() for p in second]
    agent.update(random_batch(agent))
    assert all(not torch.equal(p, b) for p, b in zip(second, before, strict=True))  # the second groups train


def test_a_forks_optimizer_keeps_its_moments_under_the_fused_step_and_resumes_into_it():
    agent = forked_agent()
    agent.update(random_batch(agent))  # moments taken before the fast path
    moments = {k: v.clone() for k, v in agent.critic_opt.state_dict()["state"][0].items()}
    speed.fast_update(agent)
    state = agent.critic_opt.state_dict()
    assert state["state"][0].keys() == moments.keys()
    assert all(torch.equal(state["state"][0][k], v) for k, v in moments.items())
    agent.update(random_batch(agent, seed=1))
    assert int(agent.critic_opt.state_dict()["state"][0]["step"]) == 2
    resumed = forked_agent()  # --resume: the checkpoint's optimizer loaded after the fast path (plumbing.load_state)
    speed.fast_update(resumed)
    resumed.critic_opt.load_state_dict(agent.critic_opt.state_dict())
    resumed.update(random_batch(resumed, seed=2))
    state = resumed.critic_opt.state_dict()
    assert int(state["state"][0]["step"]) == 3
    assert state["param_groups"] == agent.critic_opt.state_dict()["param_groups"]  # the fork's groups, fused
    assert all(g["fused"] for g in resumed.critic_opt.param_groups)


@pytest.mark.parametrize("saved_plain", [True, False], ids=["plain saved, fast resumed", "fast saved, plain resumed"])
def test_a_resumed_runs_adam_steps_as_its_own_command_line_says_not_as_the_checkpoints(saved_plain):
    args = dict(n_blocks=N, segment_len=4, stable_steps=2)
    state = plumbing.save_state(gh.Run(gh.Args(**args, plain=saved_plain), "cpu"))
    resumed = gh.Run(gh.Args(**args, plain=not saved_plain), "cpu")
    plumbing.load_state(resumed, state)
    for opt in (resumed.learner.agent.actor_opt, resumed.learner.agent.critic_opt):
        assert [bool(g["fused"]) for g in opt.param_groups] == [saved_plain]  # --plain: torch's default step


@pytest.mark.parametrize("fused", [None, True], ids=["plain", "fused"])
def test_a_resumed_adams_step_counts_are_where_its_own_step_keeps_them_not_where_the_checkpoints_did(fused):
    # the meta device stands in for a GPU: a fused step keeps its counts on the parameters' device, torch's
    # default on the CPU (where a count on the GPU would cost a read back at every update)
    saved = torch.optim.Adam([torch.nn.Parameter(torch.zeros(3))], fused=True).state_dict()
    saved["state"] = {0: dict(step=torch.tensor(5.0), exp_avg=torch.zeros(3), exp_avg_sq=torch.zeros(3))}
    param = torch.nn.Parameter(torch.zeros(3, device="meta"))
    opt = torch.optim.Adam([param])
    opt.param_groups[0]["fused"] = fused  # as this run's command line said: --plain, or speed.fuse_adams
    plumbing.load_adam(opt, saved)
    assert opt.param_groups[0]["fused"] is fused and opt.state[param]["step"].device.type == (
        "meta" if fused else "cpu"
    )


@pytest.mark.parametrize(
    "opt, kwargs, why",
    [(torch.optim.NAdam, dict(decoupled_weight_decay=True), "is NAdam, not torch's Adam or AdamW"),
     (type("ForkAdam", (torch.optim.Adam,), {}), {}, "is ForkAdam, not torch's Adam or AdamW"),  # a subclass
     (torch.optim.Adam, dict(differentiable=True), "sets differentiable=True"),
     (torch.optim.AdamW, dict(foreach=True), "sets foreach=True"),
     (torch.optim.Adam, dict(fused=False), "sets fused=False")],
    ids=["another-class", "a-subclass", "differentiable", "foreach", "unfused"],
)  # fmt: skip
def test_a_forks_optimizer_that_the_fused_step_cannot_stand_in_for_is_kept_as_built_said_in_one_line(
    capsys, opt, kwargs, why
):
    agent = forked_agent(opt, **kwargs)
    built = agent.critic_opt, settings(agent.critic_opt, but=())
    speed.fast_update(agent)
    assert (agent.critic_opt, settings(agent.critic_opt, but=())) == built  # fused as the fork set it
    assert all(g["fused"] for g in agent.actor_opt.param_groups)  # the actor's Adam: fused all the same
    out = capsys.readouterr().out.strip()
    assert len(out.splitlines()) == 1 and out.startswith("fused Adam off") and f"the critic's optimizer {why}" in out


@pytest.mark.parametrize("key, value", [("differentiable", True), ("foreach", True), ("fused", False)])
def test_a_setting_on_a_forks_second_parameter_group_alone_keeps_its_optimizer_as_built_said_in_one_line(
    capsys, key, value
):
    agent = forked_agent(torch.optim.Adam, second_group={key: value})
    built = agent.critic_opt, settings(agent.critic_opt, but=())
    assert agent.critic_opt.param_groups[0].get(key) is not value  # the first group leaves the step free
    speed.fast_update(agent)
    assert (agent.critic_opt, settings(agent.critic_opt, but=())) == built
    out = capsys.readouterr().out.strip()
    assert len(out.splitlines()) == 1 and f"the critic's optimizer sets {key}={value}" in out


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


# ------------------------------------------------------------------------------------------------
# The fork's contract: Sampler's docstring names every hook the run reaches it by, and holds
# ------------------------------------------------------------------------------------------------
def contract_hooks(module) -> set[str]:
    """The names Sampler's docstring lists as its contract: the first name of each of its entries."""
    return set(re.findall(r"^      (?:Args\.)?(\w+)", module.Sampler.__doc__, flags=re.MULTILINE))


def reached_by_the_run(module) -> set[str]:
    """What the script and plumbing.py reach a goal sampler by: its attributes (run.sampler.x), its class
    (GoalSampler(...)), the check beside it, the Args field plumbing reads; and the hooks the base calls."""
    code = Path(module.__file__).read_text() + (ROOT / "plumbing.py").read_text()
    names = set(re.findall(r"\bsampler\.(\w+)", code))
    names |= {n for n in ("GoalSampler", "check_sampler_args") if re.search(rf"\b{n}\(", code)}
    names |= {n for n in ("RESUMABLE", "NEEDS", "SAME") if f'"{n}"' in code}  # the Args fields plumbing reads
    own = {name for name, f in vars(module.Sampler).items() if callable(f) and not name.startswith("_")}
    return names | {n for n in own if re.search(rf"self\.{n}\(", inspect.getsource(module.Sampler))}


@pytest.mark.parametrize("module", SCRIPTS, ids=lambda m: m.__name__)
def test_samplers_docstring_names_every_hook_the_run_reaches_it_by_and_lists_no_other(module):
    listed, reached = contract_hooks(module), reached_by_the_run(module)
    assert {"cycle", "after_cycle", "state_dict", "load_state_dict", "goal_outcome", "RESUMABLE"} <= reached
    unnamed = reached - set(re.findall(r"\w+", module.Sampler.__doc__))
    assert not unnamed, f"the run reaches a sampler by these, which its contract does not name: {sorted(unnamed)}"
    stale = listed - reached
    assert not stale, f"in the contract but reached by nothing: {sorted(stale)}"


def test_specs_list_of_a_samplers_hooks_is_the_contract():
    spec = (ROOT / "docs/SPEC.md").read_text()
    (bullet,) = re.findall(r"^- A goal sampler provides the hooks.*?(?=^- )", spec, flags=re.MULTILINE | re.DOTALL)
    left_out = contract_hooks(gh) - {"GoalSampler"} - set(re.findall(r"`(?:Args\.)?(\w+)", bullet))
    assert not left_out, f"hooks of Sampler's contract that SPEC's list leaves out: {sorted(left_out)}"


def test_state_dict_is_called_at_cycle_boundaries_after_after_cycle(tmp_path, monkeypatch):
    events = []
    for hook in ("cycle", "after_cycle", "state_dict"):
        real = getattr(gh.GoalSampler, hook)
        monkeypatch.setattr(gh.GoalSampler, hook, lambda self, *a, _h=hook, _r=real: events.append(_h) or _r(self, *a))
    assert gh.main([*TINY, "--n-blocks", "3", "--n-epochs", "2", "--sp-ratio", "0.5", "--runs-dir", str(tmp_path)]) == 0
    saves = [i for i, e in enumerate(events) if e == "state_dict"]
    assert saves and events.count("cycle") == 2 * 2  # 2 epochs of TINY's 2 cycles, on 1 worker
    for i in saves:  # the last hook before each save closes a cycle, and every cycle begun has been closed
        last = next(e for e in reversed(events[:i]) if e != "state_dict")
        assert last == "after_cycle" and events[:i].count("cycle") == events[:i].count("after_cycle"), events[: i + 1]


def test_resume_gives_the_graph_back_with_its_nodes_in_their_saved_order():
    graph = gh.SemanticGraph(N, gh.Args(n_blocks=N))
    masks = og.OracleGraph(N).masks
    rng = np.random.default_rng(0)
    for m in rng.permutation(masks)[:40]:  # nodes added in no sorted order (each with its permutations)
        graph.add_config(int(m))
    restored = gh.SemanticGraph(N, gh.Args(n_blocks=N))
    restored.load_state_dict(graph.state_dict())
    assert restored.masks == graph.masks and restored.masks != sorted(graph.masks)
    draws = [np.random.default_rng(1), np.random.default_rng(1)]
    assert [graph.sample_node(draws[0]) for _ in range(50)] == [restored.sample_node(draws[1]) for _ in range(50)]
