"""Where one worker's epoch goes (docs/speed.md): a learner of gangstr_hme.py with the
main job's settings (SP-20%, one worker, the paper's cycle of 10 segments and 30 updates of 256), built in this
process, timed over --cycles training cycles after --warmup ones, then one evaluation. Parts:

- collecting: acting (the batched forward passes), physics (the env's steps), planning and graph updates
  (Learner.plan_seconds), the rest (the goal sampler's program, segment bookkeeping, replay stores, normalizer);
- updating: the batch (drawn from the replay, with HER), to tensors (normalized, on the device), the SAC step
  (losses, backward, the gradients' sum, the target's soft update), Adam's steps, the rest;
- evaluating: acting, physics, the rest (planning on the agent's graph included).

Each part's seconds per cycle, and an epoch's (--n-cycles cycles and its evaluation) from them. From scratch:
the graph is small and the replay nearly empty, so planning and the batch cost less than late in a run
(a run's progress.csv has time_plan_and_graph per epoch). Conditions run one after the other, in turn,
--repeats times; medians.

    python benchmarks/bench_epoch.py [--n-blocks 3 5] [--precision fp32 bf16] [--threads 1 2] [--cycles 10]
"""

import argparse
import collections
import itertools
import statistics
import sys
import time
from pathlib import Path

import torch

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))
sys.path.insert(0, str(Path(__file__).resolve().parent))
from bench_scaling import timed  # noqa: E402

import gangstr_hme as gh  # noqa: E402
import speed  # noqa: E402

COLLECT = ("acting", "physics", "planning + graph")
UPDATE = ("the batch", "to tensors", "SAC step", "Adam")


def profile(n_blocks: int, precision: str, threads: int, args) -> dict[str, float]:
    """Seconds per training cycle of each part, and of an evaluation."""
    torch.set_num_threads(threads)
    torch.manual_seed(args.seed)
    cfg = gh.Args(n_blocks=n_blocks, sp_ratio=0.2, seed=args.seed, precision=precision, threads=threads)
    run = gh.Run(cfg, torch.device("cpu"))
    learner, agent = run.learner, run.learner.agent
    s: dict[str, float] = collections.defaultdict(float)
    where = {"act": "acting", "physics": "physics"}  # the keys acting and physics count under (eval: switched)
    acting, step_envs = agent.act, speed.step_envs
    agent.act = lambda *a, **kw: timed(s, where["act"], acting)(*a, **kw)
    speed.step_envs = lambda *a, **kw: timed(s, where["physics"], step_envs)(*a, **kw)  # looked up at call time
    learner.buffer.sample = timed(s, "the batch", learner.buffer.sample)
    agent.to_tensors = timed(s, "to tensors", agent.to_tensors)
    agent.update = timed(s, "update", agent.update)
    for opt in (agent.actor_opt, agent.critic_opt):
        opt.step = timed(s, "Adam", opt.step)
    learner.train = timed(s, "updating", learner.train)
    try:
        for cycle in range(args.warmup + args.cycles):
            if cycle == args.warmup:
                s.clear()
                learner.plan_seconds = 0.0
                t = time.perf_counter()
            gh.one_cycle(run)
        cycles = time.perf_counter() - t
        s["planning + graph"] = learner.plan_seconds
        where.update(act="eval acting", physics="eval physics")
        t = time.perf_counter()
        gh.evaluate(run)
        evaluating = time.perf_counter() - t
    finally:
        speed.step_envs = step_envs
    per = {k: v / args.cycles for k, v in s.items()}
    per["SAC step"] = per["update"] - per["to tensors"] - per["Adam"]
    per["updating: rest"] = per["updating"] - per["the batch"] - per["update"]
    per["collecting"] = cycles / args.cycles - per["updating"]
    per["collecting: rest"] = per["collecting"] - sum(per[k] for k in COLLECT)
    per["evaluating"], per["eval rest"] = evaluating, evaluating - s["eval acting"] - s["eval physics"]
    per["eval acting"], per["eval physics"] = s["eval acting"], s["eval physics"]
    return per


def main():
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--n-blocks", type=int, nargs="+", default=[3, 5])
    parser.add_argument("--precision", nargs="+", default=["fp32", "bf16"], choices=["fp32", "bf16"])
    parser.add_argument("--threads", type=int, nargs="+", default=[1, 2])
    parser.add_argument("--cycles", type=int, default=10, help="timed training cycles (after --warmup)")
    parser.add_argument("--warmup", type=int, default=2, help="cycles first, untimed: the replay holds segments")
    parser.add_argument("--n-cycles", type=int, default=gh.Args.n_cycles, help="an epoch's cycles (its estimate)")
    parser.add_argument("--repeats", type=int, default=1)
    parser.add_argument("--seed", type=int, default=0)
    args = parser.parse_args()
    print(speed.cpu_line())
    conditions = list(itertools.product(args.n_blocks, args.precision, args.threads))
    runs: dict[tuple, list[dict]] = {c: [] for c in conditions}
    for _ in range(args.repeats):
        for c in conditions:
            runs[c].append(profile(*c, args))
    parts = ["collecting", *COLLECT, "collecting: rest", "updating", *UPDATE, "updating: rest"]
    for (blocks, precision, threads), got in runs.items():
        med = {k: statistics.median(r[k] for r in got) for k in got[0]}
        cycle = med["collecting"] + med["updating"]
        epoch = args.n_cycles * cycle + med["evaluating"]
        print(f"\n{blocks} blocks, {precision}, {threads} thread(s): {cycle:.3f} s a cycle, an epoch "
              f"{epoch:.0f} s ({args.n_cycles} cycles, evaluation {med['evaluating']:.1f} s: acting "
              f"{med['eval acting']:.1f}, physics {med['eval physics']:.1f}, rest {med['eval rest']:.1f}); "
              f"median of {len(got)}")  # fmt: skip
        for k in parts:
            indent = "  " if k in ("collecting", "updating") else "    "
            print(f"{indent}{k:20s} {med[k]:7.3f} s a cycle  {100 * med[k] * args.n_cycles / epoch:5.1f}% of the epoch")


if __name__ == "__main__":
    main()
