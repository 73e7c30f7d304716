"""--overlap (speed.overlapped_cycle, SPEC §12): a cycle's SAC updates in a process of their own, beside its
collection, on the replay as it was before the cycle; the same run whatever the machine's load, resumed exactly; off
by one flag, under torchrun, and for a goal sampler that learns from each update. (Stops and resumes at any moment
of an overlapped run: tests/test_gangstr.py's stop tests, which run with it by default.)"""

import csv
import dataclasses
import multiprocessing
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import inprocess
import pytest
import torch

import gangstr_hme as gh
import lp_baseline as lp
import plumbing
import speed
import vds_baseline as vds

ROOT = Path(__file__).resolve().parent.parent
COMMON = ["--n-blocks", "3", "--n-epochs", "2", "--n-cycles", "2", "--n-segments", "3", "--n-updates", "2",
          "--batch-size", "16", "--segment-len", "10", "--stable-steps", "3", "--eval-goals-per-class", "1",
          "--threads", "1"]  # fmt: skip
TINY = [*COMMON, "--sp-ratio", "0.5"]  # gangstr_hme.py's
WAIT = 60  # seconds a run or an answer is waited for: far more than it takes


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


def state_of(agent) -> list:
    """What the updates change, as tensors: the networks' weights, the optimizers' moments, step counts and
    rates, the update count."""
    tensors = [t.clone() for k in ("actor", "critic", "critic_target") for t in getattr(agent, k).state_dict().values()]
    for opt in (agent.actor_opt, agent.critic_opt):
        tensors += [t.clone() for state in opt.state_dict()["state"].values() for t in state.values()]
        tensors += [torch.tensor([g["lr"] for g in opt.param_groups])]
    return [*tensors, torch.tensor(agent.n_updates)]


def same(a: list, b: list) -> bool:
    return len(a) == len(b) and all(torch.equal(x, y) for x, y in zip(a, b, strict=True))


def test_an_overlapped_cycle_computes_the_updates_on_the_replay_before_it_in_another_process(tmp_path):
    """Its emulation in this process, one step after the other: the cycle's collection, then its updates (the
    batches from each worker's batch_rng) on the replay and normalizer as the cycle before left them, then the
    merge and learning. The overlapped run's agent, replay and streams are the emulation's, cycle after cycle."""
    torch.set_num_threads(1)  # the updates' process takes this process's count: the same float sums
    torch.manual_seed(0)
    overlapped = tiny_run(gh, "--num-envs", "2", tmp_path=tmp_path)
    torch.manual_seed(0)
    emulated = tiny_run(gh, "--num-envs", "2", tmp_path=tmp_path)
    try:
        for cycle in range(4):
            speed.overlapped_cycle(overlapped, gh)
            per_worker = gh.run_cycle(emulated)  # acting as the cycle began
            emulated.learner.train([w.batch_rng for w in emulated.workers])  # on the replay without its segments
            emulated.sampler.after_cycle()
            emulated.learner.learn_from(per_worker)
            assert overlapped.learner.agent.n_updates == 2 * cycle  # the first cycle's updates find the replay empty
            assert same(state_of(overlapped.learner.agent), state_of(emulated.learner.agent)), cycle
            streams = [[w.batch_rng.bit_generator.state for w in run.workers] for run in (overlapped, emulated)]
            assert streams[0] == streams[1]
        assert overlapped.updates.process.pid != os.getpid() and overlapped.updates.process.is_alive()
    finally:
        speed.close_updates(overlapped)
    assert not multiprocessing.active_children()


def test_the_collection_acts_with_the_agent_as_the_cycle_began(tmp_path, monkeypatch):
    run, seen = tiny_run(gh, tmp_path=tmp_path), []
    run_cycle = gh.run_cycle
    monkeypatch.setattr(gh, "run_cycle", lambda run: (seen.append(state_of(run.learner.agent)), run_cycle(run))[1])
    try:
        for _ in range(3):
            before = state_of(run.learner.agent)
            speed.overlapped_cycle(run, gh)
            assert same(seen[-1], before)  # the updates were another process's
        assert run.learner.agent.n_updates == 2 * 2 and not same(state_of(run.learner.agent), seen[0])
    finally:
        speed.close_updates(run)


def test_two_overlapped_runs_are_one_run_and_resuming_one_reproduces_it(tmp_path):
    for name in ("a", "b", "c"):
        argv = [*TINY, "--n-epochs", "1"] if name == "c" else TINY
        out = inprocess.run_script("gangstr_hme.py", *argv, runs_dir=tmp_path / name)
        assert out.returncode == 0, out.stderr
        assert "| updates beside collecting, in a process of their own (--overlap)" in out.stdout.splitlines()[0]
        assert not multiprocessing.active_children()  # its process ended with the run
    ((run_c,),) = [list((tmp_path / "c").iterdir())]
    out = inprocess.run_script("gangstr_hme.py", "--resume", str(run_c / "checkpoint.pt"), "--n-epochs", "2",
                               runs_dir=tmp_path / "c")  # fmt: skip
    assert out.returncode == 0, out.stderr
    a, b, c = (untimed(rows(tmp_path / name)) for name in "abc")
    assert len(a) == 2 and a == b == c and a[1]["critic_loss"] != "nan"
    no_overlap = inprocess.run_script("gangstr_hme.py", *TINY, "--no-overlap", runs_dir=tmp_path / "d")
    assert no_overlap.returncode == 0 and untimed(rows(tmp_path / "d")) != a  # the updates' order differs


def test_a_stop_while_an_overlapped_run_evaluates_resumes_into_the_uninterrupted_run(tmp_path, monkeypatch):
    """Ctrl-C in epoch 1's evaluation, after its first segment, ends it at once: the checkpoint holds the state from
    before it (epoch 1, its cycles done, no row for it yet), and --resume evaluates again, then trains on, into the
    uninterrupted run's rows."""
    argv = [*TINY, "--n-epochs", "3"]
    assert gh.main([*argv, "--runs-dir", str(tmp_path / "whole")]) == 0
    run_segments, evaluate, stops = gh.run_segments, gh.evaluate, []

    def stopping(*a):  # the evaluation's first segment run (its goal and path drawn), then Ctrl-C, handled at once
        segments = run_segments(*a)
        if not stops:
            stops.append(1)
            os.kill(os.getpid(), signal.SIGINT)
        return segments

    def evaluate_stopped_once(run, *a, **kw):
        monkeypatch.setattr(gh, "run_segments", stopping if run.epoch == 1 else run_segments)
        try:
            return evaluate(run, *a, **kw)
        finally:
            monkeypatch.setattr(gh, "run_segments", run_segments)

    monkeypatch.setattr(gh, "evaluate", evaluate_stopped_once)
    assert gh.main([*argv, "--runs-dir", str(tmp_path / "stopped")]) == 130 and stops
    ((run,),) = [list((tmp_path / "stopped").iterdir())]
    counters = torch.load(run / "checkpoint.pt", weights_only=True)["counters"]
    assert (counters["epoch"], counters["cycle"]) == (1, 2)
    assert len(rows(tmp_path / "stopped")) == 1 and not multiprocessing.active_children()
    assert gh.main(["--resume", str(run / "checkpoint.pt")]) == 0
    assert untimed(rows(tmp_path / "stopped")) == untimed(rows(tmp_path / "whole"))


NOT = "updates after collecting (not --overlap: "


@pytest.mark.parametrize(
    "module, argv, world, says",
    [
        (gh, [], 1, "updates beside collecting, in a process of their own (--overlap)"),
        (lp, [], 1, "updates beside collecting, in a process of their own (--overlap)"),
        (gh, ["--learner-picks", "zpd"], 1, "updates beside collecting, in a process of their own (--overlap)"),
        (gh, ["--no-overlap"], 1, "updates after collecting"),
        (vds, [], 1, NOT + "its goal sampler learns from each update)"),  # its heads learn from the TD targets
        (gh, ["--partner", "person", "--person-port", "0"], 1, NOT + "a person's cycles may be given up)"),
        (gh, [], 2, NOT + "torchrun: its processes take the cores)"),
        (gh, ["--num-envs", "2"], 1, "updates beside collecting, in a process of their own (--overlap)"),
        (gh, ["--num-envs", "24"], 1, "updates beside collecting, in a process of their own (--overlap)"),
    ],
    ids=["default", "lp", "zpd", "no-overlap", "vds", "person", "torchrun", "2-workers", "24-workers"],
)
def test_the_first_line_says_whether_the_updates_run_beside_collecting_and_why_not(
    tmp_path, capsys, monkeypatch, module, argv, world, says
):
    monkeypatch.setenv("WORLD_SIZE", str(world))  # torchrun's processes, counted; none joins here
    run = tiny_run(module, *argv, tmp_path=tmp_path)
    capsys.readouterr()
    with plumbing.RunFolder(run, None) as out:
        assert out.overlap == says.startswith("updates beside")
    assert capsys.readouterr().out.splitlines()[0].endswith(f"| {says}")


def test_without_threads_given_the_overlap_gives_torch_one_thread_in_each_process(tmp_path):
    torch.set_num_threads(2)
    run = tiny_run(gh, tmp_path=tmp_path)
    run.args = dataclasses.replace(run.args, threads=0)
    assert speed.overlap_of(run)[0] and torch.get_num_threads() == 1
    run.args = dataclasses.replace(run.args, overlap=False)
    torch.set_num_threads(2)
    assert not speed.overlap_of(run)[0] and torch.get_num_threads() == 2


def test_the_overlap_is_off_with_cuda_the_gpu_being_this_processs(tmp_path):
    run = tiny_run(gh, tmp_path=tmp_path)
    run.args = dataclasses.replace(run.args, cuda=True)  # parse_args refuses --cuda without a GPU
    assert speed.overlap_of(run) == (False, NOT + "--cuda: the GPU is this process's)")


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
    assert out.stdout.splitlines()[1].endswith("| updates after collecting")
    whole = inprocess.run_script("gangstr_hme.py", *TINY, "--no-overlap", runs_dir=tmp_path / "b")
    assert whole.returncode == 0 and untimed(rows(tmp_path / "a")) == untimed(rows(tmp_path / "b"))


def test_resume_refuses_to_change_the_overlap_of_a_run(tmp_path):
    out = inprocess.run_script("gangstr_hme.py", *TINY, "--n-epochs", "1", runs_dir=tmp_path)
    ((run,),) = [list(tmp_path.iterdir())]
    out = inprocess.run_script("gangstr_hme.py", "--resume", str(run / "checkpoint.pt"), "--n-epochs", "2",
                               "--no-overlap", runs_dir=tmp_path)  # fmt: skip
    assert out.returncode == 2 and "--overlap False (checkpoint: True)" in out.stderr


def test_time_epoch_is_the_epochs_wall_time_less_than_its_parts_when_they_overlap(tmp_path, monkeypatch):
    """Each cycle collects for at least 0.3 s here, and runs 40 updates: beside each other, the epoch's cycles
    take less than their collecting and updating seconds summed, by about the smaller of the two."""
    run_cycle = gh.run_cycle
    monkeypatch.setattr(gh, "run_cycle", lambda run: (time.sleep(0.3), run_cycle(run))[1])
    argv = [*TINY, "--n-cycles", "4", "--n-updates", "40", "--batch-size", "64"]
    assert gh.main([*argv, "--runs-dir", str(tmp_path)]) == 0
    _, row = rows(tmp_path)  # the second epoch's (the first's waits for the updates' process to start)
    epoch, collect, update = (float(row[f"time_{k}"]) for k in ("epoch", "collect", "update"))
    cycles = epoch - float(row["time_eval"])
    assert collect > 4 * 0.3 and update > 0 and cycles < collect + update - 0.5 * min(collect, update)
    assert float(row["steps_per_second"]) == pytest.approx(4 * 3 * 10 / epoch)


def test_time_epoch_is_the_sum_of_the_parts_one_after_the_other(tmp_path, monkeypatch):
    train, run_cycle = gh.Learner.train, gh.run_cycle
    monkeypatch.setattr(gh.Learner, "train", lambda self, *a: (time.sleep(0.2), train(self, *a))[1])
    monkeypatch.setattr(gh, "run_cycle", lambda run: (time.sleep(0.2), run_cycle(run))[1])
    assert gh.main([*TINY, "--n-epochs", "1", "--n-cycles", "4", "--no-overlap", "--runs-dir", str(tmp_path)]) == 0
    (row,) = rows(tmp_path)
    epoch = float(row["time_epoch"])
    assert epoch - float(row["time_eval"]) >= float(row["time_collect"]) + float(row["time_update"]) > 8 * 0.2
    assert float(row["steps_per_second"]) == pytest.approx(4 * 3 * 10 / epoch)


# A fork of gangstr_hme.py whose Learner.train does `what` at its third call: in the updates' process (which loads
# the fork's file), epoch 1's first cycle, after epoch 0's checkpoint.
FORK = """
_train, _calls = Learner.train, []


def _train_that_fails(self, *a, **kw):
    _calls.append(1)
    if __name__ == "overlapped_script" and len(_calls) == 1:
        print(f"updates' process {os.getpid()}", flush=True)
    if len(_calls) == 3:
        {what}
    return _train(self, *a, **kw)


Learner.train = _train_that_fails
"""


def run_fork(tmp_path, what: str, also: str = "") -> subprocess.Popen:
    """The fork, run on TINY's command line; `also`: top-level code of the fork's (in both processes)."""
    text = (ROOT / "gangstr_hme.py").read_text()
    main = 'if __name__ == "__main__":'
    fork = tmp_path / "fork.py"
    fork.write_text(
        text.replace(main, FORK.replace("{what}", what) + also + "\n\n" + main).replace(
            "import math", "import math\nimport os"
        )
    )
    env = dict(os.environ, PYTHONPATH=str(ROOT))
    cmd = [sys.executable, "-u", str(fork), *TINY, "--runs-dir", str(tmp_path / "runs")]
    return subprocess.Popen(cmd, cwd=tmp_path, env=env, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)


def the_last_checkpoint_holds_epoch_0(tmp_path):
    ((run,),) = [list((tmp_path / "runs").iterdir())]
    assert torch.load(run / "checkpoint.pt", weights_only=True)["counters"]["epoch"] == 1
    assert len(rows(tmp_path / "runs")) == 1 and not (run / "checkpoint.pt.tmp").exists()


@pytest.mark.parametrize(
    "what, said",
    [
        (
            'raise RuntimeError("an update failed")',
            "error: the SAC updates failed in their process (RuntimeError: an "
            "update failed: its traceback above); the last checkpoint holds the "
            "run as it was",
        ),  # fmt: skip
        (
            "os._exit(3)",
            "error: the SAC updates' process ended (exit code 3) in epoch 1, cycle 1 of 2; the last "
            "checkpoint holds the run as it was",
        ),  # fmt: skip
    ],
    ids=["fails", "dies"],
)
def test_updates_that_fail_or_die_end_the_run_in_one_line_and_the_last_checkpoint_holds_it(tmp_path, what, said):
    proc = run_fork(tmp_path, what)
    out = proc.communicate(timeout=WAIT)[0]
    assert proc.returncode == 1 and out.strip().splitlines()[-1] == said, out
    the_last_checkpoint_holds_epoch_0(tmp_path)


def test_updates_that_hang_end_the_run_in_one_line_once_they_answer_nothing_and_the_last_checkpoint_holds_it(
    tmp_path,
):
    proc = run_fork(tmp_path, "time.sleep(3600)", also="\nspeed.HUNG = 2.0")
    try:
        out = proc.communicate(timeout=WAIT)[0]
    finally:  # if it never ends, not left behind
        proc.kill()
    said = ("error: the SAC updates' process answered nothing for 2 s (hung) and was stopped in epoch 1, cycle 1 "
            "of 2; the last checkpoint holds the run as it was")  # fmt: skip
    assert proc.returncode == 1 and out.strip().splitlines()[-1] == said, out
    assert "Traceback" not in out
    the_last_checkpoint_holds_epoch_0(tmp_path)
    ends_within_10_s(int(next(x for x in out.splitlines() if x.startswith("updates' process ")).split()[-1]))


def test_updates_that_hang_leave_the_run_to_a_second_ctrl_c_and_their_process_ends_with_it(tmp_path):
    proc = run_fork(tmp_path, "time.sleep(3600)")
    for line in proc.stdout:
        if line.startswith("updates' process "):
            pid = int(line.split()[-1])
        if line.startswith("epoch   0 |"):
            break
    time.sleep(1.0)  # into epoch 1's first cycle, whose updates never end
    proc.send_signal(signal.SIGINT)
    time.sleep(0.5)
    assert proc.poll() is None  # the first waits for the cycle boundary, which the updates never reach
    proc.send_signal(signal.SIGINT)
    said = proc.communicate(timeout=WAIT)[0]
    assert proc.returncode == 130 and "aborted by a second SIGINT: the last checkpoint is kept as it was" in said
    the_last_checkpoint_holds_epoch_0(tmp_path)
    ends_within_10_s(pid)  # with the run (speed.orphaned)


def ends_within_10_s(pid: int):
    """The updates' process `pid` is gone within 10 s (killed, if not, and the test failed)."""
    deadline = time.monotonic() + 10
    while time.monotonic() < deadline:
        try:
            os.kill(pid, 0)
        except ProcessLookupError:
            return
        time.sleep(0.1)
    os.kill(pid, signal.SIGKILL)
    pytest.fail(f"the updates' process {pid} outlived the run")
