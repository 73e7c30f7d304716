"""Distributed runs (SPEC §11): two CPU workers launched by torchrun behave as one learner.

One torchrun launch (tests/dist_worker.py) serves every test here: each worker makes one SAC update on
its own fixed batch, trains a few cycles with the social partner, then runs a tiny gangstr_hme.main."""

import csv
import subprocess
import sys
from pathlib import Path

import pytest
import torch
from dist_worker import TINY

import gangstr_hme as gh

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
    assert not torch.equal(r0["batch"]["obs"], r1["batch"]["obs"])  # two different batches
    sac = gh.SAC(gh.Args(**TINY), 55, torch.device("cpu"))
    sac.actor.load_state_dict(r0["initial"]["actor"])
    sac.critic.load_state_dict(r0["initial"]["critic"])
    sac.critic_target.load_state_dict(r0["initial"]["critic"])
    actor_params = list(sac.actor.parameters())
    actor_grads = [torch.zeros_like(p) for p in actor_params]
    for r, data in enumerate(ranks):  # one process, both batches, with each worker's random draws
        torch.manual_seed(7 + r)
        critic_loss, actor_loss, _ = sac.losses(sac.to_tensors({k: v.numpy() for k, v in data["batch"].items()}))
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
