"""The paper's trained agent (or a checkpoint of ours) in this environment, as a MuJoCo or Gymnasium release is
judged by: its SR per class by `gangstr_hme.py --eval-only` (the same command, run in this process; its JSON is
written beside a copy of the file), pooled over seeds, and the share of block-steps during those evaluations
with a block on its side (|roll| or |pitch| over bench_grasp's TIP_ANGLE). Run it in one virtual environment
per release, on the same seeds: the goals and the draws are the same, only the physics differs.

    python benchmarks/bench_paper_agent.py --checkpoint paper [--seeds 1 2 3] [--goals 60]
        [--plan-on oracle] [--out results.json]

The paper's file is not in the repository (it has no licence): `paper` fetches it once from the authors'
repository into a cache (docs/training.md), or give the path of a copy.
"""

import argparse
import json
import shutil
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))
import bench_grasp  # noqa: E402 (this folder: TIP_ANGLE)

import gangstr_hme as gh  # noqa: E402
import plumbing  # noqa: E402
import speed  # noqa: E402


def tipped_share(segments: list, n_blocks: int) -> tuple[int, int]:
    """(block-steps with a block on its side, block-steps) over the segments' steps after the first."""
    obs = np.stack([s.obs[1:] for s in segments])  # (K, T, obs_dim)
    euler = obs[..., 10:].reshape(*obs.shape[:2], n_blocks, 15)[..., 3:5]  # roll and pitch of each block
    tipped = (np.abs(euler) > bench_grasp.TIP_ANGLE).any(-1)
    return int(tipped.sum()), int(tipped.size)


def main():
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--checkpoint", required=True, help="paper (the authors' file), its path, or ours")
    parser.add_argument("--seeds", type=int, nargs="+", default=[1, 2, 3])
    parser.add_argument("--goals", type=int, default=60, help="evaluation goals per class and seed")
    parser.add_argument("--plan-on", default="oracle", choices=["oracle", "agent"])
    parser.add_argument("--out", help="also write the pooled figures to this JSON file")
    ns = parser.parse_args()
    counts = dict(tipped=0, block_steps=0, env_steps=0, seconds=0.0)
    real_run_segments = gh.run_segments

    def counted(agent, workers, requests):
        t = time.perf_counter()
        segments = real_run_segments(agent, workers, requests)
        counts["seconds"] += time.perf_counter() - t
        tipped, block_steps = tipped_share(segments, agent.args.n_blocks)
        counts["tipped"] += tipped
        counts["block_steps"] += block_steps
        counts["env_steps"] += sum(len(s.actions) for s in segments)
        return segments

    gh.run_segments = counted
    results = []
    with tempfile.TemporaryDirectory() as tmp:
        source = plumbing.paper_file("--checkpoint") if ns.checkpoint == "paper" else ns.checkpoint
        checkpoint = Path(tmp) / Path(source).name
        shutil.copy(source, checkpoint)
        for seed in ns.seeds:
            argv = ["--eval-only", "--checkpoint", str(checkpoint), "--plan-on", ns.plan_on, "--seed", str(seed),
                    "--eval-goals-per-class", str(ns.goals), "--threads", "1"]  # fmt: skip
            assert gh.main(argv) == 0
            (found,) = Path(tmp).glob(f"eval_*seed{seed}*.json")
            results.append(json.loads(found.read_text()))
    classes = [k for k in results[0]["sr"] if k != "global"]
    pooled = {k: float(np.mean([r["sr"][k] for r in results])) for k in classes}
    pooled["global"] = float(np.mean([pooled[k] for k in classes]))
    print(speed.cpu_line())
    print("versions: " + ", ".join(f"{k} {v}" for k, v in plumbing.library_versions().items()))
    who = "the paper's agent" if ns.checkpoint == "paper" else ns.checkpoint
    print(f"{who}, sub-goals planned on the {ns.plan_on}'s graph, seeds {ns.seeds} x {ns.goals} goals per class, "
          "pooled:")  # fmt: skip
    print("  " + " ".join(f"{k} {pooled[k]:.3f}" for k in classes) + f" | global {pooled['global']:.3f}")
    share = counts["tipped"] / max(1, counts["block_steps"])
    print(f"  blocks on their side: {share:.2%} of {counts['block_steps']:,} block-steps; "
          f"{counts['env_steps'] / counts['seconds']:.0f} env steps/s acting and stepping, 1 thread")  # fmt: skip
    if ns.out:
        Path(ns.out).write_text(json.dumps(dict(versions=plumbing.library_versions(), plan_on=ns.plan_on,
                                                seeds=ns.seeds, goals=ns.goals, sr=pooled, per_seed=results,
                                                tipped_share=share, **counts), indent=2))  # fmt: skip


if __name__ == "__main__":
    main()
