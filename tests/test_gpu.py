"""What a --cuda user meets, checked on a CPU: the device probes are monkeypatched, and the `meta`
device stands in for a GPU where a tensor must cross to one. What only a GPU can show is in
benchmarks/gpu_smoke.py (docs/scaling.md); its one line on a machine without CUDA is checked here."""

import dataclasses
import datetime
import json
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import torch

import gangstr_hme as gh
import plumbing
import speed

ROOT = Path(__file__).resolve().parent.parent


def one_gpu(monkeypatch, capability=(9, 0)):
    """This machine, as torch would see one with a single GPU of this compute capability. Probing it must make
    no CUDA context (torchrun processes make theirs on their own GPU): the probes that would, raise."""
    monkeypatch.setattr(torch.cuda, "is_available", lambda: True)
    monkeypatch.setattr(torch.cuda, "device_count", lambda: 1)
    monkeypatch.setattr(torch.version, "hip", None)
    monkeypatch.setattr(torch.cuda, "get_device_capability", lambda device=None: {0: capability}[device])

    def makes_a_context(*args, **kwargs):
        raise AssertionError("this probe makes a CUDA context on GPU 0")

    monkeypatch.setattr(torch.cuda, "is_bf16_supported", makes_a_context)
    monkeypatch.setattr(torch.cuda, "current_device", makes_a_context)


# ------------------------------------------------------------------------------------------------
# 1. A bf16 run is evaluated anywhere: acting never computes in bf16
# ------------------------------------------------------------------------------------------------
@pytest.mark.parametrize("flags", [[], ["--precision", "fp32"]], ids=["checkpoint's flags", "--precision fp32"])
def test_a_bf16_checkpoint_is_evaluated_in_fp32_where_bf16_is_slow(monkeypatch, tmp_path, flags):
    run = gh.Run(gh.Args(n_blocks=3, buffer_size=400, precision="bf16"), torch.device("cpu"))
    plumbing.save_checkpoint(plumbing.save_state(run), tmp_path / "agent.pt")
    monkeypatch.setattr(speed, "fast_bf16", lambda cuda: False)  # a laptop: no AMX, no AVX512-BF16
    argv = ["--eval-only", "--checkpoint", str(tmp_path / "agent.pt"), "--eval-goals-per-class", "1", *flags]
    args, _, _ = plumbing.parse_command_line(gh.Args, gh.check_sampler_args, argv)
    assert speed.precision_of(args)[0] == "fp32" and args.n_blocks == 3
    assert gh.main(argv) == 0
    (result,) = tmp_path.glob("eval_agent_*.json")
    assert set(json.loads(result.read_text())["sr"]) == {*run.classes, "global"}


def test_a_bf16_checkpoint_still_resumes_in_bf16_only_where_bf16_is_fast(monkeypatch, capsys):
    """Training does compute in bf16: --resume keeps refusing it where it is slow (test_update.py), and keeps
    the checkpoint's bf16 where it is fast."""
    state = {"args": dataclasses.asdict(gh.Args(precision="bf16", n_blocks=3))}
    monkeypatch.setattr(speed, "fast_bf16", lambda cuda: True)
    assert plumbing.args_from_checkpoint(gh.Args(resume="run.pt"), {"resume"}, state, "--resume").precision == "bf16"
    monkeypatch.setattr(speed, "fast_bf16", lambda cuda: False)
    with pytest.raises(SystemExit):
        plumbing.args_from_checkpoint(gh.Args(resume="run.pt"), {"resume"}, state, "--resume")
    assert "--precision bf16" in capsys.readouterr().err


# ------------------------------------------------------------------------------------------------
# 2. One process per GPU
# ------------------------------------------------------------------------------------------------
def test_torchrun_with_more_processes_than_gpus_exits_2_naming_the_rule_before_anything_is_written(
    monkeypatch, capsys, tmp_path
):
    one_gpu(monkeypatch)
    monkeypatch.setenv("WORLD_SIZE", "2")
    monkeypatch.setenv("LOCAL_RANK", "1")  # the second process, on a machine with one GPU
    with pytest.raises(SystemExit) as e:
        plumbing.parse_args(gh.Args, gh.check_sampler_args, ["--cuda", "--runs-dir", str(tmp_path / "runs")])
    err = capsys.readouterr().err
    assert e.value.code == 2 and len(err.strip().splitlines()) == 1
    assert "LOCAL_RANK 1" in err and "one process per GPU" in err
    assert not (tmp_path / "runs").exists()
    monkeypatch.setenv("LOCAL_RANK", "0")  # the first process has its GPU
    assert plumbing.check_args(gh.Args(cuda=True), gh.check_sampler_args) is None


# ------------------------------------------------------------------------------------------------
# 3. No host-device wait per update: the batch crosses in one copy; the statistics are read once a cycle
# ------------------------------------------------------------------------------------------------
def batch_and_agent():
    """A 3-block batch of 16 from a replay of random segments, and an agent whose normalizer is fitted to them."""
    agent = gh.SAC(gh.Args(n_blocks=3), 55, torch.device("cpu"))
    rng = np.random.default_rng(0)
    obs = rng.normal(size=(1, 20, 11, 55)).astype(np.float32) * 3
    agent.normalizer.update(obs)
    buf = gh.ReplayBuffer(1, 20, 10, 55, 9)
    buf.store(obs, rng.choice(np.int8([-1, 1]), (1, 20, 11, 9)), np.ones((1, 20, 9), np.int8),
              rng.uniform(-1, 1, (1, 20, 10, 4)).astype(np.float32))  # fmt: skip
    return buf.sample(16, [rng], 0.8, "final"), agent


def test_a_batch_crosses_to_the_gpu_in_one_copy_holding_the_normalized_observations_and_not_the_raw_ones(
    monkeypatch,
):
    batch, agent = batch_and_agent()
    copies = []
    to = torch.Tensor.to

    def recorded_to(self, *args, **kwargs):
        out = to(self, *args, **kwargs)
        if out.device != self.device:
            copies.append((self.clone(), kwargs.get("non_blocking", False)))
        return out

    monkeypatch.setattr(torch.Tensor, "to", recorded_to)
    gpu = type("GPU", (), dict(device=torch.device("meta"), normalizer=agent.normalizer))()  # a SAC on a GPU
    on_gpu = gh.SAC.to_tensors(gpu, batch)
    ((sent, non_blocking),) = copies  # one copy, which the CPU does not wait for
    normalized = dict(obs=agent.normalizer(batch["obs"]), obs_next=agent.normalizer(batch["obs_next"]))
    assert non_blocking
    assert np.array_equal(sent.numpy(), np.concatenate([normalized.get(k, v).ravel() for k, v in batch.items()]))
    assert {k: (t.shape, t.device.type) for k, t in on_gpu.items()} == {k: (v.shape, "meta") for k, v in batch.items()}
    on_cpu = agent.to_tensors(batch)  # on a CPU: no copy at all
    assert len(copies) == 1 and on_cpu["action"].data_ptr() == batch["action"].ctypes.data
    assert np.array_equal(on_cpu["obs"].numpy(), normalized["obs"])


def test_a_cycle_reads_its_updates_statistics_once_and_logs_their_means(monkeypatch):
    """Reading a tensor waits for the GPU to finish all the work before it: an update that read its losses would
    keep the CPU from drawing the next batch meanwhile. The updates return tensors; Learner.train reads them in
    one transfer, and logs the mean of each update's numbers."""
    batch, fitted = batch_and_agent()
    learner = gh.Learner(gh.Args(n_blocks=3, n_updates=4, batch_size=16, num_envs=2), torch.device("cpu"))
    learner.buffer.size, learner.buffer.sample = 1, lambda *args: {k: np.concatenate([v, v]) for k, v in batch.items()}
    learner.agent.normalizer = fitted.normalizer
    infos, update = [], learner.agent.update
    monkeypatch.setattr(learner.agent, "update", lambda b: infos.append(update(b)) or infos[-1])
    reads = []
    for name in ("item", "tolist", "cpu", "__float__"):  # a transfer to the host (numpy() refuses a GPU tensor)
        method = getattr(torch.Tensor, name)
        monkeypatch.setattr(
            torch.Tensor, name, lambda self, *a, _m=method, _n=name, **k: reads.append(_n) or _m(self, *a, **k)
        )
    logged = learner.train([np.random.default_rng(0)] * 2)
    assert len(infos) == 4 and all(isinstance(v, torch.Tensor) for i in infos for v in i.values())
    assert len(reads) == 1  # the cycle's one read
    monkeypatch.undo()
    expected = {k: np.mean([float(i[k]) for i in infos]) for k in infos[0]}
    assert logged == expected and set(logged) == {"critic_loss", "actor_loss", "target", "q", "entropy"}


# ------------------------------------------------------------------------------------------------
# 4. Fast bf16 on a GPU: bf16 tensor cores on this process's own GPU, asked without making a context
# ------------------------------------------------------------------------------------------------
@pytest.mark.parametrize(
    "capability, fast", [((7, 0), False), ((7, 5), False), ((8, 0), True), ((9, 0), True)], ids=str
)
def test_bf16_is_fast_on_a_gpu_of_compute_capability_8_and_not_where_it_is_emulated(monkeypatch, capability, fast):
    """V100 (7.0) and T4 (7.5) run bf16 through emulation, which torch.cuda.is_bf16_supported() counts; A100 (8.0)
    and H100 (9.0) have bf16 tensor cores."""
    one_gpu(monkeypatch, capability)
    assert speed.fast_bf16(cuda=True) == fast
    assert (plumbing.check_args(gh.Args(cuda=True, precision="bf16"), gh.check_sampler_args) is None) == fast


def test_a_torchrun_process_asks_its_own_gpu_whether_bf16_is_fast(monkeypatch):
    capabilities = {0: (7, 0), 1: (8, 0)}  # a mixed machine: GPU 0 is a V100, GPU 1 an A100
    one_gpu(monkeypatch)
    monkeypatch.setattr(torch.cuda, "device_count", lambda: 2)
    monkeypatch.setattr(torch.cuda, "get_device_capability", lambda device=None: capabilities[device])
    monkeypatch.setenv("LOCAL_RANK", "1")
    assert speed.fast_bf16(cuda=True)
    monkeypatch.setenv("LOCAL_RANK", "0")
    assert not speed.fast_bf16(cuda=True)


# ------------------------------------------------------------------------------------------------
# 5 and 6. The process's GPU settings: bf16 sums in fp32; collectives wait as long as gloo's
# ------------------------------------------------------------------------------------------------
def cuda_process(monkeypatch, calls: list) -> None:
    """init_workers on a (pretend) GPU: what it asks of torch.cuda and torch.distributed, recorded in `calls`."""
    one_gpu(monkeypatch)
    monkeypatch.setattr(torch.cuda, "current_device", lambda: 0)
    monkeypatch.setattr(torch.cuda, "set_device", lambda device: calls.append(("set_device", device)))
    monkeypatch.setattr(
        plumbing.dist, "init_process_group", lambda backend, **kw: calls.append((backend, kw.get("timeout")))
    )


@pytest.mark.parametrize("precision, reduced", [("bf16", False), ("fp32", True)])
def test_a_bf16_run_on_a_gpu_sums_its_bf16_products_in_fp32_as_on_the_cpu(monkeypatch, precision, reduced):
    """cuBLAS may sum bf16 products in bf16 by default; test_update.py's bf16 bounds were measured with fp32 sums
    (oneDNN's). An fp32 run leaves torch's default alone."""
    matmul = torch.backends.cuda.matmul
    monkeypatch.setattr(matmul, "allow_bf16_reduced_precision_reduction", True)  # torch's default, restored after
    cuda_process(monkeypatch, [])
    device = plumbing.init_workers(gh.Args(cuda=True, precision=precision))
    assert device == torch.device("cuda", 0)
    assert matmul.allow_bf16_reduced_precision_reduction == reduced


@pytest.mark.parametrize("cuda, backend", [(False, "gloo"), (True, "nccl")])
def test_every_torchrun_process_waits_30_minutes_at_a_collective_on_a_gpu_as_on_a_cpu(monkeypatch, cuda, backend):
    """While process 0 saves a checkpoint (a replay of several GB), the others wait at the next collective: nccl's
    default timeout, 10 minutes, would abort them; gloo's is 30 (torch's default_pg_timeout)."""
    calls = []
    cuda_process(monkeypatch, calls)
    monkeypatch.setenv("WORLD_SIZE", "2")
    monkeypatch.setenv("LOCAL_RANK", "0")
    plumbing.init_workers(gh.Args(cuda=cuda))
    assert calls[-1] == (backend, datetime.timedelta(minutes=30))
    assert calls[:-1] == ([("set_device", 0)] if cuda else [])


# ------------------------------------------------------------------------------------------------
# The prepared GPU smoke check (benchmarks/gpu_smoke.py)
# ------------------------------------------------------------------------------------------------
def test_the_gpu_smoke_check_says_in_one_line_that_there_is_no_gpu_here_and_exits_0():
    env = os.environ | {"CUDA_VISIBLE_DEVICES": ""}  # on a GPU machine too: no GPU for this process
    out = subprocess.run([sys.executable, "benchmarks/gpu_smoke.py"], cwd=ROOT, capture_output=True, text=True,
                         timeout=120, env=env)  # fmt: skip
    assert out.returncode == 0, out.stderr
    assert out.stdout.strip().splitlines() == [out.stdout.strip()] and "no CUDA" in out.stdout
