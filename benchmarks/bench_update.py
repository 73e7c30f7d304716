"""The SAC update against the machine's limit (docs/speed.md), in one run, medians over interleaved repeats:

- the update's FLOPs (torch.utils.flop_counter.FlopCounterMode) and its products' shapes;
- this machine's fp32 and bf16 product rates at those shapes (torch's own product, MKL on CPU, and
  oneDNN's), and the update's floor: the sum of its products' times, each at the fastest rate;
- the update's time (5 blocks, batch 256) at 1 and 2 threads, fp32 and bf16, each over its floor, against
  the update of commit 2f9820b (before the speed tricks) and this checkout's with --plain (every speed
  trick off), in the same run;
- the single-observation action, before and now;
- collected env steps per second of a 1-worker 5-block training cycle (10 segments, then 30 updates), per
  precision, before and now.

Each measured condition runs in a fresh process (the update's memory settings are process-wide: see
speed.keep_freed_memory), the conditions interleaved round by round so that drifts in the machine's load hit each.
The code of 2f9820b comes from git (`git show 2f9820b:gangstr_hme.py`), imported from a temporary folder.

--drift: from the same start and the same batches, 1,000 updates in bf16 and in fp32, and in fp32
at 2 threads (summation order alone differs): the gap between their networks' Q values and actions on held-out
observations.

    python benchmarks/bench_update.py [--rounds 5] [--updates 30] [--cycles 4] [--drift [--drift-updates 1000]]
"""

import argparse
import importlib.util
import json
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
import torch

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))
import bench_learner  # noqa: E402 (this folder: the median of timed calls)

BEFORE = "2f9820b"  # the update before any speed trick
N_BLOCKS, BATCH = 5, 256


def load(code: str, folder: Path):
    """The training script at `code`: 'now' (this checkout's gangstr_hme.py; 'now-default-heap': without
    speed.keep_freed_memory, to show what it buys; 'now-plain': run with --plain) or 'before' (BEFORE's, from git,
    written to `folder` and imported under another name; it imports this checkout's env and oracle, whose
    assets sit beside them). BEFORE had no plumbing.py or speed.py: its script holds all it runs."""
    if code.startswith("now"):
        import gangstr_hme  # noqa: PLC0415
        import speed  # noqa: PLC0415

        if code == "now-default-heap":
            speed.keep_freed_memory = lambda: None
        return gangstr_hme
    path = folder / f"gangstr_{BEFORE}.py"
    if not path.exists():
        path.write_text(subprocess.run(["git", "show", f"{BEFORE}:gangstr_hme.py"], cwd=ROOT, check=True,
                                       capture_output=True, text=True).stdout)  # fmt: skip
    spec = importlib.util.spec_from_file_location(path.stem, path)
    module = importlib.util.module_from_spec(spec)
    sys.modules[path.stem] = module  # its dataclasses look their module up
    spec.loader.exec_module(module)
    return module


def make_data(mod, path: Path, n_batches: int, n_segments: int = 30, seed: int = 0):
    """Real segments of a fresh agent, and from their replay `n_batches` HER batches, the initial weights and
    the normalizer: saved to `path`, so that every condition updates the same networks on the same batches."""
    torch.manual_seed(seed)
    args = mod.Args(n_blocks=N_BLOCKS, seed=seed)
    run = mod.Run(args, torch.device("cpu"))
    (w,) = run.workers
    learner = run.learner
    for _ in range(n_segments // 10):
        segments = [mod.run_segments(learner.agent, [w], [mod.Request(int(mod.og.to_mask(w.env.goal)), False)])[0]
                    for _ in range(10)]  # fmt: skip
        learner.learn_from([segments])
    rng = np.random.default_rng(seed)
    batches = [learner.buffer.sample(BATCH, [rng], 0.8, "final") for _ in range(n_batches)]
    norm = learner.agent.normalizer
    torch.save(dict(batches=batches, actor=learner.agent.actor.state_dict(), critic=learner.agent.critic.state_dict(),
                    normalizer=(norm.sum, norm.sumsq, norm.count),
                    obs=(segments[0].obs[0], segments[0].ag[0], segments[0].g)), path)  # fmt: skip


def agent_from(mod, data: dict, precision: str, plain: bool = False):
    extra = ({"precision": precision} if precision != "fp32" else {}) | ({"plain": True} if plain else {})
    args = mod.Args(n_blocks=N_BLOCKS, **extra)
    agent = mod.SAC(args, 10 + 15 * N_BLOCKS, torch.device("cpu"))
    agent.actor.load_state_dict(data["actor"])
    agent.critic.load_state_dict(data["critic"])
    agent.critic_target.load_state_dict(data["critic"])
    agent.normalizer.add(*data["normalizer"])
    return agent


def median_ms(fn, repeats: int) -> float:
    """bench_learner's median, without its warm-up calls (each condition here warms up on its own)."""
    return bench_learner.median_ms(fn, repeats, warmup=0)


# --- one condition, in its own process ---------------------------------------------------------------
def condition_updates(mod, data: dict, precision: str, updates: int, plain: bool = False) -> dict:
    """Median ms of one update at 1 and 2 threads, and of one single-observation action (1 thread)."""
    agent = agent_from(mod, data, precision, plain)
    batches = data["batches"]
    out = {}
    for threads in (1, 2):
        torch.set_num_threads(threads)
        for b in batches[:3]:  # warm-up: allocations, oneDNN's primitive caches
            agent.update(b)
        it = iter(range(updates))
        out[f"update_{threads}"] = median_ms(lambda it=it: agent.update(batches[next(it) % len(batches)]), updates)
    torch.set_num_threads(1)
    obs, ag, g = (np.asarray(x, np.float32)[None] for x in data["obs"])
    noise = np.zeros((1, 4), np.float32)
    act = lambda: agent.act(obs, ag, g, noise)  # noqa: E731
    for _ in range(200):
        act()
    out["act"] = statistics.median(median_ms(act, 1000) for _ in range(5))  # ms per call: 5 x 1,000 calls
    return out


def condition_cycles(mod, precision: str, cycles: int) -> dict:
    """Env steps per second of 1-worker 5-block training cycles (collection, then the cycle's updates),
    after one cycle that fills the replay; torch's default threads, as a training script runs."""
    torch.manual_seed(0)
    extra = {"precision": precision} if precision != "fp32" else {}
    run = mod.Run(mod.Args(n_blocks=N_BLOCKS, seed=0, **extra), torch.device("cpu"))
    mod.one_cycle(run)
    collect, update = run.tally["collect"], run.tally["update"]
    t = time.perf_counter()
    for _ in range(cycles):
        mod.one_cycle(run)
    seconds = time.perf_counter() - t
    steps = cycles * run.args.n_segments * run.args.segment_len
    return dict(steps_per_s=steps / seconds, collect_s=(run.tally["collect"] - collect) / cycles,
                update_s=(run.tally["update"] - update) / cycles, threads=torch.get_num_threads())  # fmt: skip


def worker(ns):
    folder = Path(ns.folder)
    mod = load(ns.code, folder)
    if ns.worker == "updates":
        data = torch.load(folder / "data.pt", weights_only=False)
        out = condition_updates(mod, data, ns.precision, ns.updates, plain=ns.code == "now-plain")
    else:
        out = condition_cycles(mod, ns.precision, ns.cycles)
    print(json.dumps(out))


# --- FLOPs, products and floors (in the main process) ------------------------------------------------
def products_of_update(mod, data: dict) -> tuple[int, list[tuple[int, int, int]]]:
    """The FLOPs of one update (losses and backward) and its products' shapes (M, K, N), from the plain update
    of BEFORE: the products the update computes, whatever computes them."""
    from torch.utils._python_dispatch import TorchDispatchMode  # noqa: PLC0415
    from torch.utils.flop_counter import FlopCounterMode  # noqa: PLC0415

    shapes = []

    class Shapes(TorchDispatchMode):
        def __torch_dispatch__(self, func, types, args=(), kwargs=None):
            if func in (torch.ops.aten.mm.default, torch.ops.aten.addmm.default):
                a, b = args[-2], args[-1]
                shapes.append((a.shape[0], a.shape[1], b.shape[1]))
            return func(*args, **(kwargs or {}))

    agent = agent_from(mod, data, "fp32")
    torch.set_num_threads(1)
    with FlopCounterMode(display=False) as counter:
        agent.update(data["batches"][0])
    with Shapes():
        agent.update(data["batches"][0])
    return counter.get_total_flops(), shapes


def product_times(shapes, threads: int, bf16: bool, repeats: int = 20) -> dict:
    """Per distinct shape, ms of one product: torch's fp32 (MKL on CPU), oneDNN's fp32 and, where the CPU has
    bf16 instructions (`bf16`: without them oneDNN has no bf16 product), oneDNN's bf16."""
    torch.set_num_threads(threads)
    onednn = torch.ops.mkldnn._linear_pointwise
    out = {}
    for m, k, n in sorted(set(shapes)):
        a, w = torch.randn(m, k), torch.randn(n, k)
        ab, wb = a.bfloat16(), w.bfloat16()
        out[m, k, n] = dict(torch_fp32=min(median_ms(lambda a=a, w=w: a @ w.T, repeats) for _ in range(3)),
                            onednn_fp32=min(median_ms(lambda a=a, w=w: onednn(a, w, None, "none", [], ""), repeats)
                                            for _ in range(3)),
                            **({} if not bf16 else dict(onednn_bf16=min(
                                median_ms(lambda a=ab, w=wb: onednn(a, w, None, "none", [], ""), repeats)
                                for _ in range(3)))))  # fmt: skip
    return out


def floors(shapes, times: dict) -> dict:
    """The update's products alone, each at its fastest measured rate: fp32; and bf16 as --precision bf16 runs
    them (the products over every edge or node, batch x nodes or batch x edges rows, in bf16; the heads fp32)."""
    large_rows = {BATCH * N_BLOCKS, BATCH * N_BLOCKS * (N_BLOCKS - 1)}
    fp32 = [min(times[s]["torch_fp32"], times[s]["onednn_fp32"]) for s in shapes]
    if "onednn_bf16" not in times[shapes[0]]:
        return dict(fp32=sum(fp32))
    bf16 = [times[s]["onednn_bf16"] if large_rows & set(s) else f for s, f in zip(shapes, fp32, strict=True)]
    return dict(fp32=sum(fp32), bf16=sum(bf16))


def profile(mod, data: dict, precision: str, updates: int = 20):
    """Where one update's time goes (torch.profiler, 1 thread): the self time of its ops, by kind."""
    from torch.profiler import ProfilerActivity, profile  # noqa: PLC0415

    torch.set_num_threads(1)
    agent = agent_from(mod, data, precision)
    for b in data["batches"][:3]:
        agent.update(b)
    with profile(activities=[ProfilerActivity.CPU]) as prof:
        for i in range(updates):
            agent.update(data["batches"][i % len(data["batches"])])
    kinds = {"products": ("mkldnn::_linear_pointwise", "aten::mm", "aten::addmm", "aten::bmm"),
             "ReLU (forward and backward)": ("aten::threshold_backward", "aten::clamp_min", "aten::relu"),
             "copies and casts": ("aten::copy_", "aten::_to_copy", "aten::clone"),
             "sums (bias gradients, over nodes)": ("aten::sum",),
             "max over edges (forward and backward)": ("aten::amax", "aten::eq", "aten::gt", "aten::bitwise_and",
                                                       "aten::where", "aten::div"),
             "gathers, concatenations, live samples": ("aten::index", "aten::cat", "aten::index_copy_", "aten::sort",
                                                       "aten::any", "aten::new_zeros", "aten::zeros"),
             "the CPU kernels' own Python": ("NodeNet", "NodeNetBackward", "EdgeMax", "EdgeMaxBackward", "Head",
                                             "HeadBackward"),
             "Adam": ("Optimizer.step#Adam.step", "aten::_fused_adam_",
                      "Optimizer.zero_grad#Adam.zero_grad")}  # fmt: skip
    rest = "the rest (views, casts, allocations, autograd, Python)"
    split = dict.fromkeys([*kinds, rest], 0.0)
    for e in prof.key_averages():
        kind = next((k for k, names in kinds.items() if e.key in names), rest)
        split[kind] += e.self_cpu_time_total / updates / 1e3
    total = sum(split.values())
    print(f"\nWhere a {precision} update's time goes (1 thread, profiled: {total:.1f} ms per update)")
    for k, ms in split.items():
        print(f"  {k:<56} {ms:5.1f} ms  {ms / total:4.0%}")


# --- 4(a): what bf16 does to the networks --------------------------------------------------------------
def drift(mod, before, n_updates: int, n_segments: int = 100, n_held_out: int = 20):
    """From the same start (a replay of n_segments real segments, fresh networks) and the same batches,
    n_updates updates per setting; then the Q values (both twins, at the stored action) and the deterministic
    actions on the transitions of n_held_out other segments, compared between settings. Settings that differ
    in summation order alone, for scale: fp32 at 1 and 2 threads, and fp32 before the speed tricks (`before`,
    MKL's products) and now (oneDNN's)."""
    torch.manual_seed(1)
    run = mod.Run(mod.Args(n_blocks=N_BLOCKS, seed=1), torch.device("cpu"))
    (w,) = run.workers
    learner = run.learner

    def segments(k):
        return [mod.run_segments(learner.agent, [w], [mod.Request(int(mod.og.to_mask(w.env.goal)), False)])[0]
                for _ in range(k)]  # fmt: skip

    for _ in range(n_segments // 10):
        learner.learn_from([segments(10)])
    held_out = segments(n_held_out)  # not stored: the networks never train on them
    test = dict(obs=np.concatenate([s.obs[:-1] for s in held_out]), ag=np.concatenate([s.ag[:-1] for s in held_out]),
                g=np.concatenate([np.repeat(s.g[None], len(s.actions), 0) for s in held_out]),
                action=np.concatenate([s.actions for s in held_out]))  # fmt: skip
    norm = learner.agent.normalizer
    start = dict(actor=learner.agent.actor.state_dict(), critic=learner.agent.critic.state_dict(),
                 normalizer=(norm.sum, norm.sumsq, norm.count))  # fmt: skip
    checkpoints = sorted({c for c in (10, 100, n_updates) if c <= n_updates})

    def train(mod, precision: str, threads: int) -> dict:
        torch.set_num_threads(threads)
        agent = agent_from(mod, start, precision)
        rng = np.random.default_rng(1)  # the same batches for every setting
        out, t0 = {}, time.perf_counter()
        for i in range(1, n_updates + 1):
            agent.update(learner.buffer.sample(BATCH, [rng], 0.8, "final"))
            if i in checkpoints:
                with torch.no_grad():
                    obs = torch.from_numpy(agent.normalizer(test["obs"]))
                    body, blocks = mod.split_obs(obs, N_BLOCKS)
                    msg = agent.critic.messages(agent.gi, blocks, torch.from_numpy(test["g"] - test["ag"]).float())
                    q = torch.stack(agent.critic.q(body, blocks, torch.from_numpy(test["action"]), msg))
                    out[i] = (q, torch.tanh(agent.actor(body, blocks, msg)[0]))
        seconds = time.perf_counter() - t0
        print(f"  {mod.__name__} {precision}, {threads} thread(s): {n_updates} updates in {seconds:.0f} s", flush=True)
        return out

    runs = {("fp32", 1): train(mod, "fp32", 1), ("fp32", 2): train(mod, "fp32", 2),
            ("before", 1): train(before, "fp32", 1), ("bf16", 1): train(mod, "bf16", 1)}  # fmt: skip
    pairs = ((("fp32", 1), ("fp32", 2), "fp32, 1 vs 2 threads"), (("fp32", 1), ("before", 1), f"fp32, {BEFORE} vs now"),
             (("fp32", 1), ("bf16", 1), "fp32 vs bf16, 1 thread"))  # fmt: skip
    print(f"\nGaps on {len(test['obs'])} held-out transitions (Q: both twins at the stored action; actions: the "
          "deterministic policy's, in [-1, 1])")  # fmt: skip
    print(f"  {'after':>6} {'pair':<24} {'mean |Q|':>9} {'mean |dQ|':>10} {'relative':>9} {'max |dQ|':>9} "
          f"{'mean |da|':>10} {'max |da|':>9}")  # fmt: skip
    for i in checkpoints:
        for a, b, name in pairs:
            (qa, aa), (qb, ab) = runs[a][i], runs[b][i]
            dq, da = (qa - qb).abs(), (aa - ab).abs()
            print(f"  {i:>6} {name:<24} {qa.abs().mean():9.3f} {dq.mean():10.2e} {dq.mean() / qa.abs().mean():9.1e} "
                  f"{dq.max():9.2e} {da.mean():10.2e} {da.max():9.2e}")  # fmt: skip


# --- the main process ----------------------------------------------------------------------------------
def run_condition(folder: Path, part: str, code: str, precision: str, ns) -> dict:
    cmd = [sys.executable, __file__, "--worker", part, "--code", code, "--precision", precision, "--folder",
           str(folder), "--updates", str(ns.updates), "--cycles", str(ns.cycles)]  # fmt: skip
    out = subprocess.run(cmd, capture_output=True, text=True, cwd=ROOT)
    if out.returncode:
        sys.exit(f"{part} {code} {precision} failed:\n{out.stderr}")
    return json.loads(out.stdout.strip().splitlines()[-1])


def main():
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--rounds", type=int, default=5, help="interleaved rounds of every condition")
    parser.add_argument("--updates", type=int, default=30, help="timed updates per thread count and round")
    parser.add_argument("--cycles", type=int, default=4, help="timed training cycles per round (after one)")
    parser.add_argument("--skip-cycles", action="store_true", help="no training cycles")
    parser.add_argument("--drift", action="store_true", help="only 4(a): what bf16 does to the networks")
    parser.add_argument("--drift-updates", type=int, default=1000)
    parser.add_argument("--worker", choices=["updates", "cycles"], help=argparse.SUPPRESS)
    parser.add_argument("--code", choices=["now", "now-default-heap", "now-plain", "before"], help=argparse.SUPPRESS)
    parser.add_argument("--precision", default="fp32", help=argparse.SUPPRESS)
    parser.add_argument("--folder", help=argparse.SUPPRESS)
    ns = parser.parse_args()
    if ns.worker:
        return worker(ns)
    import speed  # noqa: PLC0415

    print(speed.cpu_line())
    bf16 = speed.fast_bf16(cuda=False)  # without bf16 instructions, --precision bf16 is refused: fp32 alone
    precisions = ("fp32", "bf16") if bf16 else ("fp32",)
    with tempfile.TemporaryDirectory() as tmp:
        folder = Path(tmp)
        now = load("now", folder)
        if ns.drift:
            return drift(now, load("before", folder), ns.drift_updates)
        make_data(now, folder / "data.pt", n_batches=16)
        flops, shapes = products_of_update(load("before", folder), torch.load(folder / "data.pt", weights_only=False))
        print(f"\nOne update (5 blocks, batch {BATCH}): {flops / 1e9:.2f} GFLOP in {len(shapes)} products")
        times = {t: product_times(shapes, t, bf16) for t in (1, 2)}
        print("Product rates, GFLOP/s (at the update's shapes, M x K x N; torch's fp32 is MKL here)")
        print(
            f"  {'shape':<18} {'count':>5}"
            + "".join(f" {k + f' {t}t':>15}" for t in (1, 2) for k in times[1][shapes[0]])
        )
        for s in sorted(set(shapes), key=lambda s: -s[0] * s[1] * s[2]):
            rates = [2 * s[0] * s[1] * s[2] / times[t][s][k] / 1e6 for t in (1, 2) for k in times[t][s]]
            print(f"  {'x'.join(map(str, s)):<18} {shapes.count(s):>5}" + "".join(f" {r:15.0f}" for r in rates))
        floor = {t: floors(shapes, times[t]) for t in (1, 2)}

        conditions = [("before", "fp32"), ("now-plain", "fp32"), ("now-default-heap", "fp32")]
        conditions += [("now", p) for p in precisions]
        got = {c: [] for c in conditions}
        for r in range(ns.rounds):
            for c in conditions if r % 2 == 0 else conditions[::-1]:
                got[c].append(run_condition(folder, "updates", *c, ns))
            print(f"  round {r + 1}/{ns.rounds} of the update timings done", flush=True)
        med = {c: {k: statistics.median(x[k] for x in got[c]) for k in got[c][0]} for c in conditions}
        print(f"\nThe update, ms (medians of {ns.rounds} rounds x {ns.updates} updates; floor: its products alone)")
        for t in (1, 2):
            base = med["before", "fp32"][f"update_{t}"]
            for c in conditions:
                ms = med[c][f"update_{t}"]
                spread = [x[f"update_{t}"] for x in got[c]]
                fl = floor[t][c[1]]
                print(f"  {t} thread(s) {c[0]:>16} {c[1]}: {ms:6.1f} ms ({min(spread):.1f}-{max(spread):.1f})  "
                      f"{BEFORE}/this {base / ms:4.2f}x   floor {fl:5.1f} ms, {ms / fl:4.2f}x it")  # fmt: skip
        for precision in precisions:
            profile(now, torch.load(folder / "data.pt", weights_only=False), precision)
        print("Single-observation action, 1 thread, ms: " + ", ".join(
            f"{c[0]} {c[1]} {med[c]['act']:.3f}" for c in conditions))  # fmt: skip

        if not ns.skip_cycles:
            conditions = [("before", "fp32")] + [("now", p) for p in precisions]
            cycles = {c: [] for c in conditions}
            for r in range(ns.rounds):
                for c in conditions if r % 2 == 0 else conditions[::-1]:
                    cycles[c].append(run_condition(folder, "cycles", *c, ns))
                print(f"  round {r + 1}/{ns.rounds} of the training cycles done", flush=True)
            threads = cycles["now", "fp32"][0]["threads"]
            print(f"\nTraining cycle, 1 worker, 5 blocks, {threads} threads (medians of {ns.rounds} "
                  f"rounds x {ns.cycles} cycles)")  # fmt: skip
            base = statistics.median(x["steps_per_s"] for x in cycles["before", "fp32"])
            for c in conditions:
                sps = statistics.median(x["steps_per_s"] for x in cycles[c])
                col = statistics.median(x["collect_s"] for x in cycles[c])
                upd = statistics.median(x["update_s"] for x in cycles[c])
                print(f"  {c[0]:>6} {c[1]}: {sps:6.1f} env steps/s ({sps / base:.2f}x {BEFORE}); per cycle: "
                      f"collection {col:.2f} s, updates {upd:.2f} s")  # fmt: skip


if __name__ == "__main__":
    main()
