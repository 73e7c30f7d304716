"""What a checkpoint's policy can do with its hands: per evaluation class, one segment from a fresh reset
towards a goal of the class (drawn uniformly from its members), with the deterministic and the stochastic
policy; prints how often the goal is reached at the segment's end, how often a block was lifted (its
centre at least half a block above its resting height, 0.425 + 0.025 m, at some step: a grasp, or a
block pushed onto another) and the median of each episode's highest block.

    python benchmarks/probe_skill.py runs/NAME/checkpoint.pt [--episodes 48] [--classes S2 P3] [--seed 0]
    python benchmarks/probe_skill.py paper --classes C1 S2

It tells skill from practice (docs/results.md, "Why stacks come late"): a run that pursued thousands of
S2 goals and reached none, and whose policy never lifts a block here, lacks the grasp, not the goals. No
planning: the goal is pursued directly, as one small step from the reset's config (true for C1-C3 and S2
at 3 blocks; the other classes are two steps or more away, so their 'reached' is near 0 by design).
A checkpoint of gangstr_hme.py, or the paper's file; the environment's seeds are 1000 + episode.
"""

import dataclasses
import sys
from pathlib import Path

import numpy as np
import torch

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))
import fetch5_env  # noqa: E402
import gangstr_hme as G  # noqa: E402
import oracle_graph as og  # noqa: E402
import plumbing  # noqa: E402

REST_Z = fetch5_env.TABLE_Z + fetch5_env.BLOCK_HALF  # a block's centre resting on the table (SPEC §3)
LIFTED = REST_Z + fetch5_env.BLOCK_HALF  # half a block higher


def probe(state: dict, path: str, classes: list[str], episodes: int, seed: int) -> list[tuple]:
    """(class, policy, goals reached, episodes with a block lifted, median highest block) per class and policy.
    Both policies pursue the same goals from the same resets; the stochastic one's noise has its own stream."""
    paper = state.get("format") == "paper"  # the paper's file holds no arguments: the defaults' segment length
    args = G.Args(n_blocks=state["n_blocks"]) if paper else G.Args(**state["args"])
    args = dataclasses.replace(args, plain=True, init_from="")  # acting only: no speed trick, the rates unscaled
    agent = G.SAC(args, fetch5_env.obs_size(args.n_blocks), "cpu")
    plumbing.load_weights(agent, state, args, path, "checkpoint")  # as --init-from loads them
    env, members, rows = fetch5_env.FetchManipulateEnv(n_blocks=args.n_blocks), og.evaluation_classes(args.n_blocks), []
    for cls in classes:
        goals = members[cls][np.random.default_rng(seed).integers(len(members[cls]), size=episodes)]
        for policy in ("deterministic", "stochastic"):
            noise_rng, reached, highest = np.random.default_rng([seed, 1]), 0, []
            for e, goal in enumerate(goals):
                obs, _ = env.reset(seed=1000 + e, options={"goal": goal})
                top = REST_Z
                for _ in range(args.segment_len):
                    noise = None if policy == "deterministic" else noise_rng.standard_normal((1, 4)).astype(np.float32)
                    f32 = {k: v[None].astype(np.float32) for k, v in obs.items()}
                    action = agent.act(f32["observation"], f32["achieved_goal"], f32["desired_goal"], noise)[0]
                    obs, reward, *_ = env.step(action)
                    top = max(top, float(env.block_positions()[:, 2].max()))
                reached += bool(reward)  # the segment's last step: success as training counts it (SPEC §6)
                highest.append(top)
            lifted = int((np.array(highest) >= LIFTED).sum())
            rows.append((cls, policy, reached, lifted, float(np.median(highest))))
    return rows


def main(argv=None) -> int:
    parser = plumbing.OneLineParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("checkpoint", help="a run's checkpoint.pt, or paper (the paper's agent, as --checkpoint paper)")
    parser.add_argument("--episodes", type=int, default=48, help="episodes per class and policy")
    parser.add_argument("--classes", nargs="+", default=None, help="evaluation classes (default: all)")
    parser.add_argument("--seed", type=int, default=0, help="seeds the goals drawn and the policy's noise")
    args = parser.parse_args(argv)
    if args.episodes < 1:
        parser.error(f"--episodes must be at least 1, got {args.episodes}")
    path = plumbing.paper_file("checkpoint") if args.checkpoint == "paper" else args.checkpoint  # fetched once
    state = plumbing.load_checkpoint(G.Args, path, "checkpoint")  # else exit 2, naming why
    names = list(og.evaluation_classes(plumbing.blocks_of(state)))
    if bad := [c for c in args.classes or [] if c not in names]:
        parser.error(f"--classes {bad[0]!r} is not a class at {plumbing.blocks_of(state)} blocks ({', '.join(names)})")
    torch.set_num_threads(1)
    print(f"{args.checkpoint}: one segment from a reset towards a goal of each class, {args.episodes} episodes each")
    print("class  policy         reached  block lifted  highest block (median, m)")
    for cls, policy, reached, lifted, top in probe(
        state, args.checkpoint, args.classes or names, args.episodes, args.seed
    ):
        print(f"{cls:<6} {policy:<14} {reached:>3}/{args.episodes:<4} {lifted:>3}/{args.episodes:<8} {top:.3f}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
