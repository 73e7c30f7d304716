"""--overlap (speed.overlapped_cycle, SPEC §12): a cycle's SAC updates in a thread beside its collection, on
the replay as it was before the cycle; the same run whatever the machine's load, resumed exactly; off by one
flag, and for a goal sampler whose cycle reads the networks. (Stops and resumes at any moment of an overlapped
run: tests/test_gangstr.py's stop tests, which run with it by default.)"""

import copy
import csv
import dataclasses
import json
import subprocess
import sys
import threading
import time
from pathlib import Path

import inprocess
import numpy as np
import pytest
import torch

import gangstr_hme as gh
import lp_baseline as lp
import oracle_graph as og
import plumbing
import speed
import vds_baseline as vds

ROOT = Path(__file__).resolve().parent.parent
COMMON = ["--n-blocks", "3", "--n-epochs", "2", "--n-cycles", "2", "--n-segments", "3", "--n-updates", "2",
          "--batch-size", "16", "--segment-len", "10", "--stable-steps", "3", "--eval-goals-per-class", "1",
          "--threads", "1"]  # fmt: skip
TINY = [*COMMON, "--sp-ratio", "0.5"]  # gangstr_hme.py's
WAIT = 30  # seconds an event is waited for: far more than it takes


def tiny_run(module, *argv, tmp_path) -> object:
    """A run of `module` built from its TINY command line and argv (no folder, no training yet)."""
    argv = [*(TINY if module is gh else COMMON), *argv, "--runs-dir", str(tmp_path)]
    return module.Run(plumbing.parse_args(module.Args, module.check_sampler_args, argv), "cpu")


def rows(folder: Path) -> list[dict]:
    (run,) = folder.iterdir()
    with (run / "progress.csv").open() as f:
        return list(csv.DictReader(f))


def untimed(table: list[dict]) -> list[dict]:
    return [{k: v for k, v in r.items() if not k.startswith(("time_", "steps_per_second"))} for r in table]


def test_the_updates_run_in_a_thread_while_the_cycle_collects(tmp_path, monkeypatch):
    run, began, threads = tiny_run(gh, tmp_path=tmp_path), threading.Event(), {}
    train, run_cycle = run.learner.train, gh.run_cycle

    def train_beside(*a):
        threads["updates"] = threading.get_ident()
        began.set()
        return train(*a)

    def cycle_that_waits_for_the_updates(run):  # one after the other, it would wait for ever
        threads["cycle"] = threading.get_ident()
        assert began.wait(WAIT), "the updates did not begin while the cycle collected"
        return run_cycle(run)

    monkeypatch.setattr(run.learner, "train", train_beside)
    monkeypatch.setattr(gh, "run_cycle", cycle_that_waits_for_the_updates)
    speed.overlapped_cycle(run, gh)
    assert threads["cycle"] == threading.get_ident() != threads["updates"] and run.cycle == 1


def test_the_collection_acts_with_the_weights_as_the_cycle_began_while_the_updates_change_them(tmp_path, monkeypatch):
    run = tiny_run(gh, tmp_path=tmp_path)
    for _ in range(2):  # the first cycle's updates find the replay empty, the second's change the weights
        speed.overlapped_cycle(run, gh)
    agent, done, acted = run.learner.agent, threading.Event(), []
    as_it_began = gh.SAC(run.args, agent.normalizer.sum.shape[0], "cpu")
    for name in ("actor", "critic"):
        getattr(as_it_began, name).load_state_dict(copy.deepcopy(getattr(agent, name).state_dict()))
    as_it_began.normalizer = agent.normalizer
    rng = np.random.default_rng(0)
    obs = rng.normal(size=(4, agent.normalizer.sum.shape[0])).astype(np.float32)
    ag, g = (rng.choice(np.float32([-1, 1]), size=(4, og.config_dim(3))) for _ in range(2))
    train, run_cycle = run.learner.train, gh.run_cycle
    monkeypatch.setattr(run.learner, "train", lambda *a: (train(*a), done.set())[0])

    def cycle_after_the_updates(run):
        assert done.wait(WAIT)
        # the collection's acting; with the weights as the cycle began; with the live weights
        acted.append((agent.act(obs, ag, g), as_it_began.act(obs, ag, g), gh.SAC.act(agent, obs, ag, g)))
        return run_cycle(run)

    monkeypatch.setattr(gh, "run_cycle", cycle_after_the_updates)
    speed.overlapped_cycle(run, gh)
    ((collection, began, live),) = acted
    assert agent.n_updates == 2 * run.args.n_updates
    np.testing.assert_array_equal(collection, began)
    assert not np.array_equal(collection, live)  # the updates had changed the agent's


def test_the_updates_draw_their_batches_from_each_workers_own_stream_for_them(tmp_path, monkeypatch):
    run, given = tiny_run(gh, "--num-envs", "2", tmp_path=tmp_path), []
    monkeypatch.setattr(run.learner, "train", lambda rngs, after_update: given.append(rngs) or {})
    speed.overlapped_cycle(run, gh)
    ((rngs,),) = [given]
    assert [id(r) for r in rngs] == [id(w.batch_rng) for w in run.workers]
    assert all(w.batch_rng is not w.rng for w in run.workers)
    first = [w.batch_rng.random() for w in tiny_run(gh, "--num-envs", "2", tmp_path=tmp_path).workers]
    assert len({*first, *(w.rng.random() for w in tiny_run(gh, "--num-envs", "2", tmp_path=tmp_path).workers)}) == 4


def test_a_net_run_in_another_thread_while_an_update_is_within_fast_nets_is_the_scripts_own(tmp_path, monkeypatch):
    """speed.fast_nets swaps the script's nets for its own while an update runs: acting beside it, in another
    thread, must not compute with the update's kernels, nor its large nets in the update's bf16."""
    agent = tiny_run(gh, tmp_path=tmp_path).learner.agent
    calls, inside, leave = [], threading.Event(), threading.Event()
    for name in ("NodeNet", "EdgeMax", "Head"):
        kernel = getattr(speed, name)
        monkeypatch.setattr(kernel, "apply", lambda *a, _apply=kernel.apply, _n=name: calls.append(_n) or _apply(*a))

    def update_held_open():
        with speed.fast_nets(gh, torch.bfloat16):
            inside.set()
            leave.wait(WAIT)

    thread = threading.Thread(target=update_held_open)
    thread.start()
    try:
        assert inside.wait(WAIT) and gh.MLP.forward is speed.fast_forward  # the script's nets swapped
        rng = np.random.default_rng(0)
        obs = rng.normal(size=(2, agent.normalizer.sum.shape[0])).astype(np.float32)
        ag, g = (rng.choice(np.float32([-1, 1]), size=(2, og.config_dim(3))) for _ in range(2))
        acted = agent.act(obs, ag, g)
    finally:
        leave.set()
        thread.join()
    assert calls == [] and gh.MLP.forward is not speed.fast_forward
    np.testing.assert_array_equal(acted, agent.act(obs, ag, g))  # what the own nets compute, outside the block


def test_with_several_envs_stepping_in_threads_the_collection_leaves_torchs_threads_alone(tmp_path, monkeypatch):
    """Acting beside the updates: speed.physics_first would set torch's (and MKL's, process-wide) threads while the
    envs step, under the updates' feet."""
    run, set_in_this_thread = tiny_run(gh, "--num-envs", "2", "--threads", "2", tmp_path=tmp_path), []
    monkeypatch.setattr(speed, "physics_threads", lambda n_envs: 2)  # whatever this machine's cores
    set_threads = torch.set_num_threads
    monkeypatch.setattr(torch, "set_num_threads", lambda n: (set_in_this_thread.append(n)
                                                             if threading.current_thread() is threading.main_thread()
                                                             else None, set_threads(n))[1])  # fmt: skip
    speed.overlapped_cycle(run, gh)
    assert set_in_this_thread == []
    gh.one_cycle(run)  # one after the other, the envs step with torch on one thread
    assert set_in_this_thread == [1, torch.get_num_threads()]


def test_two_overlapped_runs_are_one_run_and_resuming_one_reproduces_it(tmp_path):
    for name in ("a", "b", "c"):
        argv = [*TINY, "--n-epochs", "1"] if name == "c" else TINY
        out = inprocess.run_script("gangstr_hme.py", *argv, runs_dir=tmp_path / name)
        assert out.returncode == 0, out.stderr
        assert "| updates beside collecting (--overlap)" in out.stdout.splitlines()[0]
    ((run_c,),) = [list((tmp_path / "c").iterdir())]
    out = inprocess.run_script("gangstr_hme.py", "--resume", str(run_c / "checkpoint.pt"), "--n-epochs", "2",
                               runs_dir=tmp_path / "c")  # fmt: skip
    assert out.returncode == 0, out.stderr
    a, b, c = (untimed(rows(tmp_path / name)) for name in "abc")
    assert len(a) == 2 and a == b == c and a[1]["critic_loss"] != "nan"
    no_overlap = inprocess.run_script("gangstr_hme.py", *TINY, "--no-overlap", runs_dir=tmp_path / "d")
    assert no_overlap.returncode == 0 and untimed(rows(tmp_path / "d")) != a  # the updates' order differs


@pytest.mark.parametrize(
    "module, argv, says",
    [
        (gh, [], "updates beside collecting (--overlap)"),
        (lp, [], "updates beside collecting (--overlap)"),
        (gh, ["--no-overlap"], "updates after collecting (--no-overlap)"),
        (gh, ["--learner-picks", "novelty"], "updates beside collecting (--overlap)"),  # reads the graph alone
        (gh, ["--learner-picks", "zpd"], "updates after collecting (its cycle reads the networks)"),  # the critic
        (vds, [], "updates after collecting (its cycle reads the networks)"),  # the heads the updates train
        (
            gh,
            ["--partner", "person", "--person-port", "0"],
            "updates after collecting (a person's cycles may be given up)",
        ),  # fmt: skip
    ],
    ids=["default", "lp", "no-overlap", "novelty", "zpd", "vds", "person"],
)
def test_the_first_line_says_whether_the_updates_run_beside_collecting_and_why_not(tmp_path, capsys, module, argv,
                                                                                    says):  # fmt: skip
    run = tiny_run(module, *argv, tmp_path=tmp_path)
    capsys.readouterr()
    with plumbing.RunFolder(run, None) as out:
        assert out.overlap == says.startswith("updates beside")
    assert capsys.readouterr().out.splitlines()[0].endswith(f"| {says}")


def test_without_threads_given_the_overlap_gives_torch_one_thread_a_core_each(tmp_path):
    torch.set_num_threads(2)
    run = tiny_run(gh, tmp_path=tmp_path)
    run.args = dataclasses.replace(run.args, threads=0)
    assert speed.overlap_of(run)[0] and torch.get_num_threads() == 1
    run.args = dataclasses.replace(run.args, overlap=False)
    torch.set_num_threads(2)
    assert not speed.overlap_of(run)[0] and torch.get_num_threads() == 2


def test_a_run_begun_before_overlap_resumes_with_its_updates_after_collecting(tmp_path):
    """A checkpoint whose args predate --overlap (none saved, no batch_rng): the run goes on as it began."""
    one = inprocess.run_script("gangstr_hme.py", *TINY, "--n-epochs", "1", "--no-overlap", runs_dir=tmp_path / "a")
    assert one.returncode == 0, one.stderr
    ((run,),) = [list((tmp_path / "a").iterdir())]
    state = torch.load(run / "checkpoint.pt", weights_only=True)
    state["args"].pop("overlap")
    del state["batch_rng"]
    torch.save(state, run / "checkpoint.pt")
    out = inprocess.run_script("gangstr_hme.py", "--resume", str(run / "checkpoint.pt"), "--n-epochs", "2",
                               runs_dir=tmp_path / "a")  # fmt: skip
    assert out.returncode == 0, out.stderr
    assert "| updates after collecting (--no-overlap)" in out.stdout
    whole = inprocess.run_script("gangstr_hme.py", *TINY, "--no-overlap", runs_dir=tmp_path / "b")
    assert whole.returncode == 0 and untimed(rows(tmp_path / "a")) == untimed(rows(tmp_path / "b"))


def test_resume_refuses_to_change_the_overlap_of_a_run(tmp_path):
    out = inprocess.run_script("gangstr_hme.py", *TINY, "--n-epochs", "1", runs_dir=tmp_path)
    ((run,),) = [list(tmp_path.iterdir())]
    out = inprocess.run_script("gangstr_hme.py", "--resume", str(run / "checkpoint.pt"), "--n-epochs", "2",
                               "--no-overlap", runs_dir=tmp_path)  # fmt: skip
    assert out.returncode == 2 and "--overlap False (checkpoint: True)" in out.stderr


@pytest.mark.parametrize("overlap", [True, False], ids=["overlap", "no-overlap"])
def test_time_epoch_is_the_epochs_wall_time_less_than_its_parts_when_they_overlap(tmp_path, monkeypatch, overlap):
    """Each cycle's collection and updates take 0.2 s here: one after the other 0.4 s a cycle, beside each other
    0.2 s. time_epoch is the wall's; steps_per_second counts it."""
    train, run_cycle = gh.Learner.train, gh.run_cycle
    monkeypatch.setattr(gh.Learner, "train", lambda self, *a: (time.sleep(0.2), train(self, *a))[1])
    monkeypatch.setattr(gh, "run_cycle", lambda run: (time.sleep(0.2), run_cycle(run))[1])
    argv = [*TINY, "--n-epochs", "1", "--n-cycles", "4", *([] if overlap else ["--no-overlap"]), "--runs-dir",
            str(tmp_path)]  # fmt: skip
    assert gh.main(argv) == 0
    (row,) = rows(tmp_path)
    epoch, parts = float(row["time_epoch"]), float(row["time_collect"]) + float(row["time_update"])
    assert epoch > float(row["time_eval"]) + 4 * 0.2
    cycles = epoch - float(row["time_eval"])
    assert (cycles < parts - 4 * 0.1) if overlap else (cycles >= parts)
    assert float(row["steps_per_second"]) == pytest.approx(4 * 3 * 10 / epoch)


def test_an_error_in_the_updates_beside_ends_the_run_with_it_and_keeps_the_last_checkpoint(tmp_path, monkeypatch):
    calls = []

    def after_update_that_fails(self, batch, target):  # in epoch 1: its first cycle's updates
        calls.append(threading.get_ident())
        if len(calls) == 2 * 2 + 1:
            raise RuntimeError("an update failed")
        return {}

    monkeypatch.setattr(gh.GoalSampler, "after_update", after_update_that_fails)
    with pytest.raises(RuntimeError, match="an update failed"):
        gh.main([*TINY, "--n-cycles", "3", "--runs-dir", str(tmp_path)])
    assert threading.get_ident() not in calls  # it ran beside the collection
    ((run,),) = [list(tmp_path.iterdir())]
    state = torch.load(run / "checkpoint.pt", weights_only=True)
    assert state["counters"]["epoch"] == 1 and len(rows(tmp_path)) == 1 and state["rows"][0]["epoch"] == 0
    assert not (run / "checkpoint.pt.tmp").exists()


HANGS = """
import sys, threading
import gangstr_hme as gh
calls = []
def after_update(self, batch, target):  # epoch 1's first update never ends
    calls.append(1)
    if len(calls) == 5:
        print("hanging", flush=True)
        threading.Event().wait()
    return {}
gh.GoalSampler.after_update = after_update
sys.exit(gh.main(sys.argv[1:]))
"""


def test_updates_that_hang_leave_the_run_to_a_second_ctrl_c_and_the_last_checkpoint_as_it_was(tmp_path):
    cmd = [sys.executable, "-u", "-c", HANGS, *TINY, "--n-cycles", "3", "--runs-dir", str(tmp_path)]
    proc = subprocess.Popen(cmd, cwd=ROOT, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
    for line in proc.stdout:
        if line.startswith("hanging"):
            break
    proc.send_signal(2)
    time.sleep(0.5)
    assert proc.poll() is None  # the first waits for the cycle boundary, which the updates never reach
    proc.send_signal(2)
    said = proc.communicate(timeout=WAIT)[0]
    assert proc.returncode == 130 and "aborted by a second SIGINT: the last checkpoint is kept as it was" in said
    ((run,),) = [list(tmp_path.iterdir())]
    assert torch.load(run / "checkpoint.pt", weights_only=True)["counters"]["epoch"] == 1
    assert len(rows(tmp_path)) == 1 and json.loads((run / "config.json").read_text())["overlap"] is True
