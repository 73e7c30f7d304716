"""Workers for tests/test_distributed.py (not a test itself): the same 2-worker run, two ways.

    torchrun --standalone --nproc-per-node 2 tests/dist_worker.py OUT_DIR      # 2 processes x 1 worker
    python tests/dist_worker.py OUT_DIR --num-envs 2                          # 1 process x 2 workers

Each process makes one SAC update on its workers' fixed batches (a separate copy of the networks),
then trains a few cycles, and saves what the test compares to OUT_DIR/{mode}{rank}.pt; under
torchrun, every worker then runs gangstr_hme.main on a tiny run whose folder goes to OUT_DIR/runs."""

import dataclasses
import sys
from pathlib import Path

import numpy as np
import torch

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))
import gangstr_hme as gh  # noqa: E402
import plumbing  # noqa: E402

TINY = dict(n_blocks=3, n_cycles=3, n_segments=4, n_updates=2, batch_size=16, segment_len=10, stable_steps=3,
            eval_goals_per_class=2, threads=1, sp_ratio=0.5, buffer_size=4000, seed=3, ask_after=1,
            learner_picks="zpd", precision="fp32")  # fmt: skip  # fp32: the update checked against the plain nets


def fixed_batch(seed: int, n: int = 16) -> dict:
    """A batch of made-up transitions, the same wherever it is made with the same seed."""
    rng = np.random.default_rng(seed)
    pm = lambda: rng.choice([-1.0, 1.0], size=(n, 9)).astype(np.float32)  # noqa: E731
    return dict(obs=rng.normal(size=(n, 55)).astype(np.float32), obs_next=rng.normal(size=(n, 55)).astype(np.float32),
                ag=pm(), ag_next=pm(), g=pm(), action=rng.uniform(-1, 1, (n, 4)).astype(np.float32),
                reward=rng.integers(0, 2, n).astype(np.float32), noise_next=rng.normal(size=(n, 4)).astype(np.float32),
                noise_pi=rng.normal(size=(n, 4)).astype(np.float32))  # fmt: skip


def main(out: Path, num_envs: int):
    args = gh.Args(**TINY, num_envs=num_envs)
    torch.set_num_threads(1)
    device = plumbing.init_workers(args)
    r = plumbing.rank()
    torch.manual_seed(args.seed + r)
    run = gh.Run(args, device)  # parameters broadcast from worker 0 here
    learner = run.learner
    nets = ("actor", "critic")
    initial = {k: {n: t.clone() for n, t in getattr(learner.agent, k).state_dict().items()} for k in nets}
    sac = gh.SAC(args, 55, device)  # the fixed-batch update, on a copy: the learner's cycles start from `initial`
    for k in nets:
        getattr(sac, k).load_state_dict(initial[k])
    sac.critic_target.load_state_dict(initial["critic"])
    mine = [fixed_batch(100 + w.index) for w in run.workers]
    sac.update({k: np.concatenate([b[k] for b in mine]) for k in mine[0]})
    after_one = {k: {n: t.clone() for n, t in getattr(sac, k).state_dict().items()} for k in nets}
    grads = {k: {n: p.grad.clone() for n, p in getattr(sac, k).named_parameters()} for k in nets}
    first_cycle, first_normalizer, goals, logged = [], None, [], []
    for cycle in range(args.n_cycles):
        per_worker = gh.run_cycle(run)
        run.sampler.after_cycle()  # as one_cycle: the workers' internalized pairs merged
        learner.learn_from(per_worker)
        goals.append([[gh.og.to_mask(s.g) for s in w.segments] for w in run.workers])  # the picks among them
        if cycle == 0:  # each worker's segments: goal, start and final configs, success; the statistics
            first_cycle = [[(gh.og.to_mask(s.g), s.start, s.final, s.success) for s in w.segments]
                           for w in run.workers]  # fmt: skip
            norm = learner.agent.normalizer
            first_normalizer = torch.tensor(np.concatenate([norm.sum, norm.sumsq, [norm.count]]))
        logged.append(learner.train([w.rng for w in run.workers], run.sampler.after_update))  # the row's losses
    params = torch.cat(
        [p.detach().reshape(-1) for m in (learner.agent.actor, learner.agent.critic) for p in m.parameters()]
    )
    norm = learner.agent.normalizer
    # --init-learning-starts 3: process 1's replay filling again (as in a resumed job), process 0's full
    waiter = gh.Learner(dataclasses.replace(args, init_from="gangstr.pt", init_learning_starts=3, n_updates=0), device)
    waiter.buffer.size = 1 if r == 1 else 3
    waiter.train([w.rng for w in run.workers])
    saved = dict(
        initial=initial,
        batches=[{k: torch.from_numpy(v) for k, v in b.items()} for b in mine],
        after_one=after_one,
        grads=grads,
        first_cycle=torch.tensor(first_cycle, dtype=torch.int64),
        first_normalizer=first_normalizer,
        params=params,
        graph=learner.graph.state_dict(),
        internalization=torch.tensor(run.sampler.internalization_buffer, dtype=torch.int64).reshape(-1, 2),
        normalizer=torch.tensor(np.concatenate([norm.sum, norm.sumsq, [norm.count]])),
        encountered=torch.tensor(sorted(learner.encountered)),
        segments=learner.segments,
        buffer_size=learner.buffer.size,
        world=plumbing.world(),
        query=run.sampler.query.state_dict(),
        goals=torch.tensor(goals, dtype=torch.int64).transpose(0, 1),  # (workers, cycles, segments)
        proposed=sum(v for k, v in run.sampler.stats.items() if k.startswith("sp_beyond_") and "_reached_" not in k),
        help_cycles=run.sampler.stats["help_cycles"],
        losses={k: torch.tensor([m[k] for m in logged]) for k in logged[0]},
        waiting=torch.tensor(waiter.waiting or (-1, -1)),
    )
    torch.save(saved, out / f"{'lockstep' if num_envs > 1 else 'rank'}{r}.pt")
    if num_envs > 1:
        return 0
    argv = ["--n-blocks", "3", "--n-epochs", "2", "--n-cycles", "2", "--n-segments", "3", "--n-updates", "2",
            "--batch-size", "16", "--segment-len", "10", "--stable-steps", "3", "--eval-goals-per-class", "3",
            "--threads", "1", "--sp-ratio", "0.5", "--runs-dir", str(out / "runs")]  # fmt: skip
    return gh.main(argv)


if __name__ == "__main__":
    num_envs = int(sys.argv[3]) if sys.argv[2:3] == ["--num-envs"] else 1
    plumbing.leave(main(Path(sys.argv[1]), num_envs))  # as the scripts leave: gloo's thread can abort a normal exit
