"""A torchrun worker for tests/test_distributed.py (not a test itself).

    torchrun --standalone --nproc-per-node 2 tests/dist_worker.py OUT_DIR

Each worker makes one SAC update on its own fixed batch, then trains a few cycles, and saves what the
test compares to OUT_DIR/rank{r}.pt; finally every worker runs gangstr_hme.main on a tiny run whose
folder goes to OUT_DIR/runs."""

import sys
from pathlib import Path

import numpy as np
import torch

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))
import gangstr_hme as gh  # noqa: E402

TINY = dict(n_blocks=3, n_cycles=3, n_segments=4, n_updates=2, batch_size=16, segment_len=10, stable_steps=3,
            eval_goals_per_class=2, threads=1, sp_ratio=0.5, buffer_size=4000, seed=3)  # fmt: skip


def fixed_batch(seed: int, n: int = 16) -> dict:
    """A batch of made-up transitions, the same wherever it is made with the same seed."""
    rng = np.random.default_rng(seed)
    pm = lambda: rng.choice([-1.0, 1.0], size=(n, 9)).astype(np.float32)  # noqa: E731
    return dict(obs=rng.normal(size=(n, 55)).astype(np.float32), obs_next=rng.normal(size=(n, 55)).astype(np.float32),
                ag=pm(), ag_next=pm(), g=pm(), action=rng.uniform(-1, 1, (n, 4)).astype(np.float32),
                reward=rng.integers(0, 2, n).astype(np.float32))  # fmt: skip


def main(out: Path):
    args = gh.Args(**TINY)
    torch.set_num_threads(1)
    device = gh.init_workers(args)
    r = gh.rank()
    torch.manual_seed(args.seed + r)
    learner = gh.Learner(args, device)  # parameters broadcast from worker 0 here
    sac = learner.agent
    initial = {k: {n: t.clone() for n, t in getattr(sac, k).state_dict().items()} for k in ("actor", "critic")}
    batch = fixed_batch(100 + r)
    torch.manual_seed(7 + r)  # the draws of this worker's update, for the test to replay
    sac.update(batch)
    after_one = {k: {n: t.clone() for n, t in getattr(sac, k).state_dict().items()} for k in ("actor", "critic")}
    grads = {k: {n: p.grad.clone() for n, p in getattr(sac, k).named_parameters()} for k in ("actor", "critic")}
    for _ in range(args.n_cycles):
        learner.learn_from(learner.run_cycle())
        learner.train()
    params = torch.cat(
        [p.detach().reshape(-1) for m in (sac.actor, sac.critic, sac.critic_target) for p in m.parameters()]
    )
    norm = sac.normalizer
    saved = dict(
        initial=initial,
        batch={k: torch.from_numpy(v) for k, v in batch.items()},
        after_one=after_one,
        grads=grads,
        params=params,
        graph=learner.graph.state_dict(),
        internalization=torch.tensor(learner.internalization_buffer, dtype=torch.int64).reshape(-1, 2),
        normalizer=torch.tensor(np.concatenate([norm.sum, norm.sumsq, [norm.count]])),
        encountered=torch.tensor(sorted(learner.encountered)),
        segments=learner.segments,
        buffer_size=learner.buffer.size,
        world=gh.world(),
    )
    torch.save(saved, out / f"rank{r}.pt")
    argv = ["--n-blocks", "3", "--n-epochs", "2", "--n-cycles", "2", "--n-segments", "3", "--n-updates", "2",
            "--batch-size", "16", "--segment-len", "10", "--stable-steps", "3", "--eval-goals-per-class", "3",
            "--threads", "1", "--sp-ratio", "0.5", "--runs-dir", str(out / "runs")]  # fmt: skip
    return gh.main(argv)


if __name__ == "__main__":
    gh.leave(main(Path(sys.argv[1])))  # as the scripts leave: gloo's thread can abort a normal exit
