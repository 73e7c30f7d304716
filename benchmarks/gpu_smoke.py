"""The GPU smoke check: what a `--cuda` user meets, tried in one command on a machine with a GPU before
any long run; about 3-4 minutes on one GPU. One line per check, PASS, FAIL or INFO (a fact to read, not a verdict),
then a summary; exit code 1 if any check failed. On a machine without CUDA it says so in one line and exits 0 (CI
has no GPU). docs/scaling.md says what each line means and what stays unverified until it has run.

    python benchmarks/gpu_smoke.py [--keep DIR] [--skip-bench]

  versions       torch, CUDA, cuDNN, MuJoCo; the GPU's name, compute capability and memory; fast bf16 here
  no context     the command line's device probes make no CUDA context (a torchrun process makes its first on its
                 own GPU, in init_workers)
  one per GPU    torchrun with one process more than there are GPUs exits 2 with one line (set_device's traceback
                 before)
  run ...        a tiny run (3 blocks, 1 epoch) of each script with --cuda --num-envs 2; gangstr_hme.py also with
                 --precision bf16, with --compile, with both
  checkpoints    a GPU checkpoint resumed on CPU, a CPU one on the GPU; --eval-only of the GPU's on CPU, of the CPU's
                 and of the bf16 run's on the GPU and of the bf16 run's on CPU; --init-from with --cuda
  resume         one epoch, then --resume to two, equals two epochs on the GPU (where two uninterrupted runs differ,
                 the GPU's summation order does: their difference is then the bound)
  update         one SAC update on the same weights and batch on CPU and GPU: fp32 losses, targets and gradients
                 to float tolerance; the GPU's bf16 update against the CPU's fp32 within test_update's bounds
  syncs          host-device synchronizations in one cycle (torch.cuda.set_sync_debug_mode): acting waits once
                 per step, the cycle's updates once in all
  memory         peak GPU memory of the checks run in this process
  bench          bench_scaling.py --skip-scaling --cuda: seconds per 24-worker cycle, its split, peak GPU memory
"""

import argparse
import concurrent.futures
import csv
import os
import re
import shutil
import subprocess
import sys
import tempfile
import time
import warnings
from pathlib import Path

import numpy as np
import torch

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "tests"))
import gangstr_hme as gh  # noqa: E402
import plumbing  # noqa: E402
import speed  # noqa: E402

TINY = ["--n-blocks", "3", "--n-cycles", "2", "--n-segments", "3", "--n-updates", "4", "--batch-size", "32",
        "--segment-len", "10", "--stable-steps", "3", "--eval-goals-per-class", "2", "--buffer-size", "2000",
        "--threads", "1", "--seed", "3"]  # fmt: skip
TIMING = ("time_", "steps_per_second")
results: list[str] = []


def report(verdict: str, name: str, detail: str):
    results.append(verdict)
    print(f"{verdict:4s}  {name:18s}  {detail}", flush=True)


def checked(name: str, fn, *args):
    """fn(*args) -> (passed, detail), reported; an exception is a failure, its last line the detail."""
    try:
        passed, detail = fn(*args)
    except Exception as e:  # noqa: BLE001 (any error is this check's failure, the others still run)
        passed, detail = False, f"{type(e).__name__}: {str(e).strip().splitlines()[-1] if str(e).strip() else ''}"
    report("PASS" if passed else "FAIL", name, detail)


def python(*argv, timeout=420) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, *argv], cwd=ROOT, capture_output=True, text=True, timeout=timeout)


def last_line(out: subprocess.CompletedProcess) -> str:
    lines = (out.stderr.strip() or out.stdout.strip()).splitlines()
    return lines[-1][:200] if lines else ""


def rows(run_dir: Path) -> list[dict]:
    with (run_dir / "progress.csv").open() as f:
        return [{k: v for k, v in r.items() if not k.startswith(TIMING)} for r in csv.DictReader(f)]


def run_folder(runs: Path) -> Path:
    (folder,) = runs.iterdir()
    return folder


# ------------------------------------------------------------------------------------------------
# In this process: versions, the update on CPU and GPU, host-device syncs
# ------------------------------------------------------------------------------------------------
def versions() -> str:
    import mujoco  # noqa: PLC0415

    p = torch.cuda.get_device_properties(0)
    return (f"torch {torch.__version__}, CUDA {torch.version.cuda}, cuDNN {torch.backends.cudnn.version()}, "
            f"MuJoCo {mujoco.__version__}, numpy {np.__version__}; {torch.cuda.device_count()} GPU(s), "
            f"GPU 0: {p.name}, compute capability {p.major}.{p.minor}, {p.total_memory / 2**30:.0f} GiB; "
            f"fast bf16: {speed.fast_bf16(cuda=True)}")  # fmt: skip


def one_update(device: str, precision: str, weights: dict) -> tuple[dict, torch.Tensor, dict]:
    """One update from `weights` on test_update's batch: (losses, TD targets, gradients by name), on the CPU."""
    import test_update as tu  # noqa: PLC0415

    agent = gh.SAC(gh.Args(n_blocks=tu.N_BLOCKS, precision=precision), 10 + 15 * tu.N_BLOCKS, torch.device(device))
    for name, state in weights.items():
        getattr(agent, name).load_state_dict(state)
    info = agent.update(tu.realistic_batch(agent))  # the same batch each time: its own seed, its own normalizer
    nets = dict(actor=agent.actor, critic=agent.critic)
    grads = {f"{net}.{k}": p.grad.cpu() for net, module in nets.items() for k, p in module.named_parameters()}
    return {k: float(v) for k, v in info.items()}, agent.last_target.cpu(), grads


def update_on_cpu_and_gpu() -> tuple[bool, str]:
    import test_update as tu  # noqa: PLC0415

    torch.manual_seed(0)
    start = gh.SAC(gh.Args(n_blocks=tu.N_BLOCKS), 10 + 15 * tu.N_BLOCKS, torch.device("cpu"))
    weights = {name: getattr(start, name).state_dict() for name in ("actor", "critic", "critic_target")}
    ref = one_update("cpu", "fp32", weights)

    def gaps(got) -> tuple[float, float, float]:
        loss = max(abs(got[0][k] - ref[0][k]) / abs(ref[0][k]) for k in ("critic_loss", "actor_loss"))
        return loss, tu.relative(got[1], ref[1]), max(tu.relative(got[2][k], ref[2][k]) for k in ref[2])

    fp32 = gaps(one_update("cuda", "fp32", weights))
    passed = max(fp32) < 1e-4  # float sums in another order; test_update holds the CPU's to 1e-5 of SPEC §5's
    detail = f"fp32 GPU vs CPU: losses {fp32[0]:.1e}, targets {fp32[1]:.1e}, worst gradient {fp32[2]:.1e} (< 1e-4)"
    if speed.fast_bf16(cuda=True):
        plumbing.init_workers(gh.Args(cuda=True, precision="bf16"))  # a bf16 run's settings: cuBLAS sums in fp32
        bf16, bounds = gaps(one_update("cuda", "bf16", weights)), tu.BF16_BOUNDS
        passed &= bf16[0] < bounds["losses"] and bf16[1] < bounds["targets"] and bf16[2] < bounds["gradients"]
        limits = ", ".join(f"{b:.0%}" for b in bounds.values())
        detail += (f"; bf16 GPU vs fp32 CPU: losses {bf16[0]:.1%}, targets {bf16[1]:.1%}, worst gradient "
                   f"{bf16[2]:.1%} (test_update's bounds: {limits})")  # fmt: skip
    else:
        detail += "; bf16: not fast on this GPU (refused by --precision bf16), not compared"
    return passed, detail


def syncs_in_a_cycle() -> tuple[bool, str]:
    """One cycle of a 2-worker run (its replay filled by a first) under set_sync_debug_mode: the syncs of acting
    (one per lockstep step: the actions go to the envs) and of the cycle's SAC updates (one: plumbing.update_means)."""
    args = gh.Args(n_blocks=3, num_envs=2, cuda=True, n_segments=3, segment_len=10, stable_steps=3, n_updates=10,
                   batch_size=64, buffer_size=2000)  # fmt: skip
    torch.manual_seed(0)
    run = gh.Run(args, plumbing.init_workers(args))
    gh.one_cycle(run)
    counts, train = {}, run.learner.train

    def counted_train(*a, **k):
        before = len(caught)
        try:
            return train(*a, **k)
        finally:
            counts["updates"] = len(caught) - before

    run.learner.train = counted_train
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        torch.cuda.set_sync_debug_mode("warn")
        try:
            gh.one_cycle(run)
        finally:
            torch.cuda.set_sync_debug_mode(0)
    steps = args.n_segments * args.segment_len  # lockstep steps of a cycle (at least: longer paths take more)
    detail = (f"{len(caught)} in one cycle of 2 workers: {counts['updates']} in its {args.n_updates} updates "
              f"(expected 1), {len(caught) - counts['updates']} in acting (its copies to and from the GPU, a few "
              f"per lockstep step; {steps} or more steps)")  # fmt: skip
    return counts["updates"] <= 1, detail


# ------------------------------------------------------------------------------------------------
# Subprocesses: the scripts as a user runs them
# ------------------------------------------------------------------------------------------------
NO_CONTEXT = ("import torch, plumbing, gangstr_hme as gh; "
              "plumbing.check_args(gh.Args(cuda=True, precision='bf16'), gh.check_sampler_args); "
              "print([i for i in range(torch.cuda.device_count()) if torch._C._cuda_hasPrimaryContext(i)])"
              )  # fmt: skip


def no_context() -> tuple[bool, str]:
    out = python("-c", NO_CONTEXT)
    made = out.stdout.strip()
    return out.returncode == 0 and made == "[]", f"GPUs with a CUDA context after the probes: {made or last_line(out)}"


def one_per_gpu(tmp: Path) -> tuple[bool, str]:
    n = torch.cuda.device_count()
    out = python("-m", "torch.distributed.run", "--standalone", "--nproc-per-node", str(n + 1), "gangstr_hme.py",
                 "--cuda", *TINY, "--n-epochs", "1", "--runs-dir", str(tmp / "torchrun"), timeout=120)  # fmt: skip
    said = [line.strip()[:160] for line in out.stderr.splitlines() if "one process per GPU" in line]
    traceback = "invalid device ordinal" in out.stderr
    detail = f"--nproc-per-node {n + 1} on {n} GPU(s): exit {out.returncode}; {said[0] if said else last_line(out)}"
    return out.returncode != 0 and bool(said) and not traceback, detail


def tiny_run(tmp: Path, name: str, script: str, *flags: str, epochs: int = 1) -> tuple[bool, str]:
    runs = tmp / name
    out = python(script, *TINY, "--num-envs", "2", "--n-epochs", str(epochs), *flags, "--runs-dir", str(runs))
    if out.returncode != 0:
        return False, f"exit {out.returncode}: {last_line(out)}"
    on, last = re.search(r"worker\(s\) on (\S+)", out.stdout + out.stderr), rows(run_folder(runs))[-1]
    shown = " ".join(f for f in flags if f.startswith("--"))
    return True, (f"{script} {shown}: {int(last['epoch']) + 1} epoch(s) on {on.group(1) if on else '?'}, "
                  f"critic loss {float(last['critic_loss']):.3f}, SR {float(last['global_sr']):.2f}")  # fmt: skip


def bf16_refused(tmp: Path, name: str, *flags: str) -> tuple[bool, str]:
    """Where bf16 is slow (compute capability under 8.0): refused with one line, exit 2."""
    out = python("gangstr_hme.py", *TINY, "--cuda", *flags, "--runs-dir", str(tmp / name))
    lines = out.stderr.strip().splitlines()
    return out.returncode == 2 and len(lines) == 1, f"refused on this GPU (exit {out.returncode}): {last_line(out)}"


def continued(checkpoint: Path, *flags: str) -> tuple[bool, str]:
    out = python("gangstr_hme.py", "--resume", str(checkpoint), "--n-epochs", "2", *flags)
    if out.returncode != 0:
        return False, f"exit {out.returncode}: {last_line(out)}"
    on = re.search(r"worker\(s\) on (\S+)", out.stdout + out.stderr)
    return len(rows(checkpoint.parent)) == 2, f"to epoch 2 on {on.group(1) if on else '?'}"


def evaluated(checkpoint: Path, *flags: str) -> tuple[bool, str]:
    out = python("gangstr_hme.py", "--eval-only", "--checkpoint", str(checkpoint), "--eval-goals-per-class", "2",
                 *flags)  # fmt: skip
    said = [line for line in out.stdout.splitlines() if line.startswith("global")]
    return out.returncode == 0 and bool(said), said[0] if said else f"exit {out.returncode}: {last_line(out)}"


def initialized(checkpoint: Path, tmp: Path) -> tuple[bool, str]:
    return tiny_run(tmp, "init_from", "gangstr_hme.py", "--cuda", "--init-from", str(checkpoint))


def worst_gap(a: list[dict], b: list[dict]) -> tuple[list[str], float]:
    """The columns where two runs' rows differ, and the largest relative difference among them."""
    cols = sorted({k for ra, rb in zip(a, b, strict=True) for k in ra if ra[k] != rb[k]})
    gap = 0.0
    for ra, rb in zip(a, b, strict=True):
        for k in cols:
            x, y = float(ra[k] or "nan"), float(rb[k] or "nan")
            gap = max(gap, abs(x - y) / max(abs(x), abs(y), 1e-12)) if np.isfinite([x, y]).all() else gap
    return cols, gap


def resume_equals_uninterrupted(tmp: Path) -> tuple[bool, str]:
    a, b, resumed = (rows(run_folder(tmp / name)) for name in ("two_epochs", "two_epochs_bis", "one_epoch"))
    if len(resumed) != 2 or len(a) != 2:
        return False, f"{len(resumed)} and {len(a)} epochs"
    if resumed == a:
        return True, "1 epoch + --resume: progress.csv equals the 2-epoch run's (timings aside)"
    cols, gap = worst_gap(resumed, a)
    if a == b:  # the GPU repeats a run exactly: so must a resumed one
        return False, f"differs from the 2-epoch run in {', '.join(cols)} (two uninterrupted runs are identical)"
    counts = [c for c in cols if c in ("epoch", "episodes", "env_steps")]
    noise_cols, noise = worst_gap(b, a)
    passed = not counts and gap <= 10 * noise
    return passed, (f"differs in {len(cols)} columns, at most {gap:.1e} relative; two uninterrupted GPU runs differ "
                    f"in {len(noise_cols)}, at most {noise:.1e} (the GPU's summation order)")  # fmt: skip


def bench() -> tuple[bool, str]:
    out = python("benchmarks/bench_scaling.py", "--skip-scaling", "--cuda", timeout=300)
    if out.returncode != 0:
        return False, f"exit {out.returncode}: {last_line(out)}"
    head = re.search(r"\): ([\d.]+) s per cycle", out.stdout)
    split = re.findall(r"^\s+(.+?)\s+([\d.]+) s\s+([\d.]+)%$", out.stdout, re.MULTILINE)
    memory = re.search(r"peak GPU memory\s+([\d.]+) GiB", out.stdout)
    parts = ", ".join(f"{k} {v} s ({p}%)" for k, v, p in split)
    return bool(head), (f"24 workers (5 blocks): {head.group(1) if head else '?'} s per cycle: {parts}; "
                        f"peak GPU memory {memory.group(1) if memory else '?'} GiB")  # fmt: skip


# ------------------------------------------------------------------------------------------------
# The check, in three stages: runs (in parallel, with the in-process checks); what uses their
# checkpoints (in parallel); the benchmark (alone: it is timed)
# ------------------------------------------------------------------------------------------------
def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--keep", default="", help="keep the runs in this folder (default: a temporary one)")
    parser.add_argument("--skip-bench", action="store_true", help="skip bench_scaling.py (about a minute)")
    args = parser.parse_args()
    if not torch.cuda.is_available():
        print(f"gpu_smoke: no CUDA device here (torch {torch.__version__}, built for CUDA {torch.version.cuda}): "
              "nothing checked; run it on a machine with a GPU (docs/scaling.md)")  # fmt: skip
        return 0
    start = time.perf_counter()
    tmp = Path(args.keep or tempfile.mkdtemp(prefix="gpu_smoke-"))
    tmp.mkdir(parents=True, exist_ok=True)
    report("INFO", "versions", versions())
    bf16 = speed.fast_bf16(cuda=True)
    runs = {  # name: (script, flags, epochs)
        "two_epochs": ("gangstr_hme.py", ["--cuda"], 2), "two_epochs_bis": ("gangstr_hme.py", ["--cuda"], 2),
        "one_epoch": ("gangstr_hme.py", ["--cuda"], 1), "cpu": ("gangstr_hme.py", [], 1),
        "lp": ("lp_baseline.py", ["--cuda"], 1), "vds": ("vds_baseline.py", ["--cuda"], 1),
        "compile": ("gangstr_hme.py", ["--cuda", "--compile"], 1),
    }  # fmt: skip
    if bf16:
        runs |= {"bf16": ("gangstr_hme.py", ["--cuda", "--precision", "bf16"], 1),
                 "compile_bf16": ("gangstr_hme.py", ["--cuda", "--compile", "--precision", "bf16"], 1)}  # fmt: skip
    with concurrent.futures.ThreadPoolExecutor(len(runs) + 4) as pool:
        futures = {f"run {name}": pool.submit(tiny_run, tmp, name, s, *f, epochs=e) for name, (s, f, e) in runs.items()}
        futures |= {"no context": pool.submit(no_context), "one per GPU": pool.submit(one_per_gpu, tmp)}
        if not bf16:
            futures |= {"bf16 refused": pool.submit(bf16_refused, tmp, "bf16", "--precision", "bf16")}
        checked("update", update_on_cpu_and_gpu)
        checked("syncs", syncs_in_a_cycle)
        peak = torch.cuda.max_memory_allocated() / 2**20
        report("INFO", "memory", f"peak GPU memory of the update and syncs checks (5 and 3 blocks): {peak:.0f} MiB")
        for name, future in futures.items():
            checked(name, future.result)
    ckpt = {name: run_folder(tmp / name) / "checkpoint.pt" for name in runs if (tmp / name).exists()}
    if not {"one_epoch", "cpu", "two_epochs"} <= ckpt.keys():
        report("FAIL", "checkpoints", "the runs they need failed")
    else:
        copies = {}
        for use, source in (("gpu_on_cpu", "one_epoch"), ("cpu_on_gpu", "cpu"), ("eval_cpu", "cpu")):
            copies[use] = tmp / use / ckpt[source].parent.name / "checkpoint.pt"
            shutil.copytree(ckpt[source].parent, copies[use].parent)
        stage = {"resume GPU>CPU": (continued, copies["gpu_on_cpu"], "--no-cuda"),
                 "resume CPU>GPU": (continued, copies["cpu_on_gpu"], "--cuda"),
                 "resume GPU>GPU": (continued, ckpt["one_epoch"]),
                 "eval GPU>CPU": (evaluated, ckpt["two_epochs"]),
                 "eval CPU>GPU": (evaluated, copies["eval_cpu"], "--cuda"),
                 "init-from": (initialized, ckpt["cpu"], tmp)}  # fmt: skip
        if "bf16" in ckpt:  # a bf16 run evaluated where bf16 may be slow, and on its GPU
            stage |= {"eval bf16>CPU": (evaluated, ckpt["bf16"]), "eval bf16>GPU": (evaluated, ckpt["bf16"], "--cuda")}
        with concurrent.futures.ThreadPoolExecutor(len(stage)) as pool:
            futures = {name: pool.submit(fn, *a) for name, (fn, *a) in stage.items()}
            for name, future in futures.items():
                checked(name, future.result)
        checked("resume", resume_equals_uninterrupted, tmp)
    if not args.skip_bench:
        checked("bench", bench)
    failed = results.count("FAIL")
    kept = f"; runs kept in {tmp}" if args.keep else ""
    print(f"gpu_smoke: {results.count('PASS')} passed, {failed} failed in {time.perf_counter() - start:.0f} s{kept}")
    if not args.keep:
        shutil.rmtree(tmp, ignore_errors=True)
    return 1 if failed else 0


if __name__ == "__main__":
    os.environ.setdefault("PYTHONUNBUFFERED", "1")
    sys.exit(main())
