"""Distributed runs (SPEC §11): two CPU workers launched by torchrun behave as one learner, and as two
workers in one process (--num-envs 2).

One torchrun launch and one single-process launch of tests/dist_worker.py serve every test here: each
process makes one SAC update on its workers' fixed batches, trains a few cycles with the social partner,
then (under torchrun) runs a tiny gangstr_hme.main."""

import csv
import json
import subprocess
import sys
from pathlib import Path

import inprocess
import pytest
import torch
from dist_worker import TINY

import gangstr_hme as gh

pytestmark = pytest.mark.xdist_group("torchrun")  # under -n 2, on one worker: one torchrun launch for the module
ROOT = Path(__file__).resolve().parent.parent


@pytest.fixture(scope="module")
def workers(tmp_path_factory):
    out = tmp_path_factory.mktemp("dist")
    torchrun = [sys.executable, "-m", "torch.distributed.run"]  # what the torchrun command runs
    cmd = [*torchrun, "--standalone", "--nproc-per-node", "2", "tests/dist_worker.py", str(out)]
    proc = subprocess.run(cmd, cwd=ROOT, capture_output=True, text=True, timeout=300)
    assert proc.returncode == 0, proc.stdout[-3000:] + proc.stderr[-3000:]
    ranks = [torch.load(out / f"rank{r}.pt", weights_only=True) for r in (0, 1)]
    return out, ranks, proc.stdout


@pytest.fixture(scope="module")
def lockstep(workers):
    out = workers[0]
    cmd = [sys.executable, "tests/dist_worker.py", str(out), "--num-envs", "2"]
    proc = subprocess.run(cmd, cwd=ROOT, capture_output=True, text=True, timeout=300)
    assert proc.returncode == 0, proc.stdout[-3000:] + proc.stderr[-3000:]
    return torch.load(out / "lockstep0.pt", weights_only=True)


def test_workers_start_from_the_same_parameters_and_stay_identical_after_updates(workers):
    _, (r0, r1), _ = workers
    assert r0["world"] == r1["world"] == 2
    for net in ("actor", "critic"):
        for name, t in r0["initial"][net].items():
            assert torch.equal(t, r1["initial"][net][name]), name
    assert torch.equal(r0["params"], r1["params"])


def test_an_update_sums_both_workers_gradients_like_one_process_on_both_batches(workers):
    _, ranks, _ = workers
    r0, r1 = ranks
    (b0,), (b1,) = r0["batches"], r1["batches"]
    assert not torch.equal(b0["obs"], b1["obs"])  # two different batches
    sac = gh.SAC(gh.Args(**TINY), 55, torch.device("cpu"))
    sac.actor.load_state_dict(r0["initial"]["actor"])
    sac.critic.load_state_dict(r0["initial"]["critic"])
    sac.critic_target.load_state_dict(r0["initial"]["critic"])
    actor_params = list(sac.actor.parameters())
    actor_grads = [torch.zeros_like(p) for p in actor_params]
    for batch in (b0, b1):  # one process, one worker, both batches (the noise of their policy samples included)
        critic_loss, actor_loss, _, _ = sac.losses(sac.to_tensors({k: v.numpy() for k, v in batch.items()}))
        critic_loss.backward()  # accumulates: the sum of the two workers' critic gradients
        for acc, g in zip(actor_grads, torch.autograd.grad(actor_loss, actor_params), strict=True):
            acc += g
    for p, g in zip(actor_params, actor_grads, strict=True):
        p.grad = g
    for net in ("actor", "critic"):
        for name, p in getattr(sac, net).named_parameters():
            for data in ranks:
                torch.testing.assert_close(data["grads"][net][name], p.grad, rtol=1e-5, atol=1e-6)
    sac.critic_opt.step()
    sac.actor_opt.step()
    for net in ("actor", "critic"):
        for name, t in getattr(sac, net).state_dict().items():
            for data in ranks:
                torch.testing.assert_close(data["after_one"][net][name], t, rtol=1e-5, atol=1e-6)


def test_two_workers_in_one_process_run_what_two_processes_run(workers, lockstep):
    """--num-envs 2 in one process and torchrun --nproc-per-node 2, same seeds (SPEC §11)."""
    _, (r0, r1), _ = workers
    assert lockstep["world"] == 1 and r0["world"] == 2
    for net in ("actor", "critic"):  # the same networks to start with ...
        for name, t in r0["initial"][net].items():
            assert torch.equal(t, lockstep["initial"][net][name]), name
    # ... the same segments in the first cycle: worker i of the process is worker i of torchrun ...
    assert lockstep["first_cycle"].shape == (2, TINY["n_segments"], 4)
    assert torch.equal(lockstep["first_cycle"], torch.cat([r0["first_cycle"], r1["first_cycle"]]))
    assert len(set(lockstep["first_cycle"][:, :, 0].reshape(-1).tolist())) > 2  # goals that vary
    # ... the same semantic graph, internalized pairs and configs met after a few cycles ...
    assert len(lockstep["graph"]["masks"]) > 1 and len(lockstep["internalization"]) > 0
    for key in ("masks", "edges", "class_keys", "sr"):
        assert torch.equal(r0["graph"][key], lockstep["graph"][key]), key
    assert torch.equal(r0["internalization"], lockstep["internalization"])
    assert torch.equal(r0["encountered"], lockstep["encountered"])
    assert lockstep["segments"] == r0["segments"] and lockstep["buffer_size"] == r0["buffer_size"]
    # ... the same help the learner asked for (decided from the shared graph), given to both workers ...
    assert torch.equal(lockstep["query"], r0["query"]) and torch.equal(r0["query"], r1["query"])
    assert lockstep["help_cycles"] == r0["help_cycles"] + r1["help_cycles"] > 0
    # ... the same goals in every cycle, the learner's picks among the partner's candidates included ...
    assert torch.equal(lockstep["goals"], torch.cat([r0["goals"], r1["goals"]]))
    assert lockstep["proposed"] == r0["proposed"] + r1["proposed"] > 0
    # ... the same normalizer statistics: as many observations, their sums to float tolerance (one forward pass acts
    # for both workers, which rounds differently from two; the physics grows it, as the trajectories go on: 1e-5
    # relatively after the first cycle, 1e-4 after the third, on an Intel Xeon; a worker's observations missing or
    # counted twice would move them by far more) ...
    assert lockstep["normalizer"][-1] == r0["normalizer"][-1]
    torch.testing.assert_close(lockstep["normalizer"], r0["normalizer"], rtol=1e-3, atol=1e-6)
    # ... and, from the same fixed batches, the same parameters after one update.
    pairs = zip(lockstep["batches"], r0["batches"] + r1["batches"], strict=True)
    assert all(torch.equal(a["obs"], b["obs"]) for a, b in pairs)
    for net in ("actor", "critic"):
        for name, t in lockstep["after_one"][net].items():
            torch.testing.assert_close(r0["after_one"][net][name], t, rtol=1e-5, atol=1e-6)
    # ... and the same parameters after the cycles' updates, on batches from both workers' replays (up to
    # rounding, which Adam can blow up to about its step, 1e-3, where a gradient is near 0: a few parameters).
    apart = (lockstep["params"] - r0["params"]).abs() > 1e-4
    assert apart.float().mean() < 1e-3, f"{int(apart.sum())} of {len(apart)} parameters differ"


def test_the_logged_losses_are_the_mean_over_every_workers_batches_in_one_process_or_two(workers, lockstep):
    """A row's critic_loss (and every value the updates log) is one number for one run: torchrun's processes
    log the mean over both workers' batches, as --num-envs 2 does, not process 0's own batch's (SPEC §10)."""
    _, (r0, r1), _ = workers
    assert set(lockstep["losses"]) >= {"critic_loss", "actor_loss", "q", "target", "entropy"}
    for k, values in lockstep["losses"].items():
        assert torch.equal(r0["losses"][k], r1["losses"][k]), k  # every process logs the same row
        torch.testing.assert_close(r0["losses"][k], values, rtol=1e-4, atol=1e-5, msg=k)


def test_semantic_graphs_normalizers_and_internalization_buffers_are_identical_on_both_workers(workers):
    _, (r0, r1), _ = workers
    assert len(r0["graph"]["masks"]) > 1 and len(r0["graph"]["edges"]) > 0  # the graph did grow
    for key in ("masks", "edges", "class_keys", "sr"):
        assert torch.equal(r0["graph"][key], r1["graph"][key]), key
    assert torch.equal(r0["internalization"], r1["internalization"])
    assert torch.equal(r0["normalizer"], r1["normalizer"])
    assert torch.equal(r0["encountered"], r1["encountered"])


def test_each_worker_keeps_its_own_replay_while_counters_cover_both(workers):
    _, (r0, r1), _ = workers
    own = TINY["n_cycles"] * TINY["n_segments"]
    assert r0["buffer_size"] == r1["buffer_size"] == own
    assert r0["segments"] == r1["segments"] == 2 * own
    assert r0["normalizer"][-1] == 2 * own * (TINY["segment_len"] + 1)  # observations of both workers


def test_init_learning_starts_waits_in_every_process_until_the_smallest_replay_holds_enough(workers):
    # process 1's replay holds 1 segment of 3, process 0's all 3: neither updates, and both say so alike
    assert [r["waiting"].tolist() for r in workers[1]] == [[1, 3], [1, 3]]


def test_only_worker_0_writes_the_run_folder_and_its_checkpoint_once(workers):
    out, _, stdout = workers
    runs = list((out / "runs").iterdir())
    assert len(runs) == 1
    files = sorted(p.name for p in runs[0].iterdir() if not p.name.startswith("events"))
    assert files == ["checkpoint.pt", "config.json", "progress.csv"]
    with (runs[0] / "progress.csv").open() as f:
        rows = list(csv.DictReader(f))
    assert [int(r["env_steps"]) for r in rows] == [120, 240]  # 2 workers x 2 cycles x 3 segments x 10 steps
    assert stdout.count("epoch   1 |") == 1  # worker 0 speaks for both
    state = torch.load(runs[0] / "checkpoint.pt", weights_only=True)
    assert state["counters"]["epoch"] == 2


def test_a_torchrun_run_of_two_workers_learns_at_three_tenths_of_the_papers_rates_and_says_so(workers):
    out, _, stdout = workers  # its command line gives no rate (SPEC §12: below 24 workers, x0.3)
    assert "| 2 worker(s) on cpu | rates 0.0003 / 0.0003 (x0.3 of the paper's: below 24 workers)" in stdout
    (run,) = (out / "runs").iterdir()
    state = torch.load(run / "checkpoint.pt", weights_only=True)
    rates = [state[o]["param_groups"][0]["lr"] for o in ("actor_opt", "critic_opt")]
    assert rates == pytest.approx([3e-4, 3e-4], rel=1e-12) and state["args"]["lr_actor"] == rates[0]  # the run's own
    assert json.loads((run / "config.json").read_text())["adam_rates"] == rates


def test_a_single_process_needs_no_launcher():
    proc = subprocess.run([sys.executable, "-c", "import gangstr_hme as g; print(g.world(), g.rank())"], cwd=ROOT,
                          capture_output=True, text=True, timeout=60)  # fmt: skip
    assert proc.stdout.split() == ["1", "0"]


@pytest.mark.parametrize("script", ["lp_baseline.py", "vds_baseline.py"])
def test_the_baselines_train_with_two_workers(tmp_path, script):
    argv = ["--n-blocks", "3", "--n-epochs", "1", "--n-cycles", "2", "--n-segments", "3", "--n-updates", "2",
            "--batch-size", "16", "--segment-len", "10", "--stable-steps", "3", "--eval-goals-per-class", "2",
            "--threads", "1", "--runs-dir", str(tmp_path)]  # fmt: skip
    cmd = [sys.executable, "-m", "torch.distributed.run", "--standalone", "--nproc-per-node", "2", script, *argv]
    proc = subprocess.run(cmd, cwd=ROOT, capture_output=True, text=True, timeout=300)
    assert proc.returncode == 0, proc.stdout[-2000:] + proc.stderr[-2000:]
    (run,) = tmp_path.iterdir()
    with (run / "progress.csv").open() as f:
        (row,) = list(csv.DictReader(f))
    assert int(row["env_steps"]) == 2 * 2 * 3 * 10 and "2 worker(s)" in proc.stdout


# ------------------------------------------------------------------------------------------------
# Several workers in one process (--num-envs): resume, evaluation, logs
# ------------------------------------------------------------------------------------------------
TWO = ["--n-blocks", "3", "--n-cycles", "2", "--n-segments", "4", "--n-updates", "3", "--batch-size", "16",
       "--segment-len", "10", "--stable-steps", "3", "--eval-goals-per-class", "3", "--threads", "1", "--seed", "3",
       "--num-envs", "2"]  # fmt: skip
HME = ["--sp-ratio", "0.3", "--ask-after", "1", "--learner-picks", "zpd"]  # the coin, the learner's query and picks
TIMING = ("time_", "steps_per_second")


def run(*argv, runs: Path, script="gangstr_hme.py") -> subprocess.CompletedProcess:
    proc = inprocess.run_script(script, *argv, runs_dir=runs)  # one process: this one (see there)
    assert proc.returncode == 0, proc.stdout[-2000:] + proc.stderr[-2000:]
    return proc


def rows_of(runs: Path) -> list[dict]:
    (folder,) = runs.iterdir()
    with (folder / "progress.csv").open() as f:
        return [{k: v for k, v in r.items() if not k.startswith(TIMING)} for r in csv.DictReader(f)]


def test_a_two_worker_process_resumed_after_an_epoch_reproduces_the_uninterrupted_run(tmp_path):
    run(*TWO, *HME, "--n-epochs", "3", runs=tmp_path / "a")
    run(*TWO, *HME, "--n-epochs", "1", runs=tmp_path / "b")
    (folder,) = (tmp_path / "b").iterdir()
    state = torch.load(folder / "checkpoint.pt", weights_only=True)
    assert len(state["rng"]) == 2 and [len(x) for x in state["buffer"]["obs"]] == [8, 8]  # each worker's own
    assert (folder / "checkpoint.pt").stat().st_size < 5e6  # the segments collected, not the replays' capacity
    run("--resume", str(folder / "checkpoint.pt"), "--n-epochs", "3", runs=tmp_path / "b")
    a, b = rows_of(tmp_path / "a"), rows_of(tmp_path / "b")
    assert len(a) == 3 and a == b
    assert sum(float(r["queries"]) for r in a) > 0  # the learner asked (shared state, kept by the checkpoint)


def test_per_worker_counts_are_summed_in_the_logs(tmp_path):
    proc = run(*TWO, *HME, "--n-epochs", "1", runs=tmp_path)
    (row,) = rows_of(tmp_path)
    assert int(row["segments"]) == 2 * 2 * 4 and int(row["env_steps"]) == 2 * 2 * 4 * 10  # both workers'
    assert int(row["goals"]) >= 2 * 2  # at least one goal per cycle and worker
    assert "2 worker(s)" in proc.stdout


def test_evaluation_goals_are_split_between_the_workers_of_a_process():
    two = gh.Run(gh.Args(n_blocks=3, num_envs=2, eval_goals_per_class=3, segment_len=4, stable_steps=2,
                         buffer_size=400), torch.device("cpu"))  # fmt: skip
    resets = []
    for w in two.workers:
        reset = w.env.reset
        w.env.reset = lambda w=w, reset=reset, **kw: resets.append(w.index) or reset(**kw)
    sr = gh.evaluate(two)
    classes = len(two.classes)
    assert resets.count(0) == 2 * classes and resets.count(1) == classes  # goal i of each class to worker i mod 2
    assert set(sr) == {*two.classes, "global"}


@pytest.mark.parametrize("num_envs", ["1", "3"])
def test_eval_only_runs_any_number_of_workers_on_a_two_worker_checkpoint(tmp_path, num_envs):
    run(*TWO, *HME, "--n-epochs", "1", runs=tmp_path)
    (folder,) = tmp_path.iterdir()
    argv = ["--eval-only", "--checkpoint", str(folder / "checkpoint.pt"), "--num-envs", num_envs, "--threads", "1"]
    out = run(*argv, runs=tmp_path)
    assert "global  SR" in out.stdout and len(list(folder.glob("eval_*.json"))) == 1


@pytest.mark.parametrize("script", ["lp_baseline.py", "vds_baseline.py"])
def test_the_baselines_train_with_two_workers_in_one_process(tmp_path, script):
    run(*TWO, "--n-epochs", "1", runs=tmp_path, script=script)
    (row,) = rows_of(tmp_path)
    assert int(row["env_steps"]) == 2 * 2 * 4 * 10
