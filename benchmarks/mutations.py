"""Can the tests fail? Breaks the code one small change at a time, each in a fresh copy of the project,
and runs the tests that claim the behaviour it breaks: a mutation they do not notice ("survived") is a
test that cannot fail (docs/development.md). Not part of the test suite or CI: the whole list takes several minutes.

    python benchmarks/mutations.py                # every mutation
    python benchmarks/mutations.py -k her --jobs 2
    python benchmarks/mutations.py --list

When to run it: after changing a test or the code a test guards, and before a release. A new test gets
a mutation here (a sign, an index, a constant of the code it checks), and must kill it.

Each mutation replaces text that must occur exactly once in its file (the list fails loudly when the code
moves on without it). The copy holds the files git knows of, as they are in the working tree (tracked,
and untracked but not ignored); the working tree itself is never touched. A mutation is "killed" when its
guard (pytest arguments: test files, then -k EXPR) fails, or errors at collection, or runs out of time.
A survivor whose behaviour SPEC leaves free is marked harmless, with the reason, and counted apart.
First, the guards run on the unmutated copy: a guard that fails there would "kill" anything.
"""

import argparse
import concurrent.futures
import os
import shlex
import shutil
import subprocess
import sys
import tempfile
import time
from dataclasses import dataclass
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent


@dataclass(frozen=True)
class Mutation:
    name: str
    file: str
    old: str | tuple[str, ...]  # text that occurs once in file (a tuple: several edits, one mutation)
    new: str | tuple[str, ...]
    guard: str  # pytest arguments: test files, then optionally -k EXPR
    harmless: str = ""  # why a survivor is fine: the behaviour it changes is free under SPEC

    def edits(self) -> list[tuple[str, str]]:
        old, new = (x if isinstance(x, tuple) else (x,) for x in (self.old, self.new))
        return list(zip(old, new, strict=True))


G, LP, VDS, ENV, ORACLE = "gangstr_hme.py", "lp_baseline.py", "vds_baseline.py", "fetch5_env.py", "oracle_graph.py"
P, LQ, S, PP = "plumbing.py", "learner_query.py", "speed.py", "person_partner.py"
TG, TH, TB, TE, TO = (f"tests/test_{x}.py" for x in ("gangstr", "hme", "baselines", "env", "oracle_graph"))
TGPU, TL = "tests/test_gpu.py", "tests/test_learner_query.py"

# fmt: off
MUTATIONS = [
    # --- the update's CPU kernels ---------------------------------------------------------------------
    Mutation("kernels: live samples cut at a multiple of 32 (some left out)", S,
             "k = min(len(grad), -(-int(live.sum()) // multiple) * multiple)",
             "k = min(len(grad), int(live.sum()) // multiple * multiple)",
             "tests/test_update.py -k 'cpu_kernels_compute_the_plain_nets_and_their_gradients_in_fp32'"),
    Mutation("kernels: the max's gradient through edges the ReLU zeroed", S,
             "hit = (y == out[:, :, None]) & (y > 0)", "hit = y == out[:, :, None]",
             "tests/test_update.py -k 'cpu_kernels_compute_the_plain_nets_and_their_gradients_in_fp32'"),
    Mutation("kernels: live samples' gradients put back in the wrong rows", S,
             "index_copy_(0, rows, t)", "index_copy_(0, rows.flip(0), t)",
             "tests/test_update.py -k 'cpu_kernels_compute_the_plain_nets_and_their_gradients_in_fp32'"),
    Mutation("kernels: the TD target's message chunks out of order", S,
             "for e in edges.split(64)])", "for e in edges.split(64)][::-1])",
             "tests/test_update.py -k 'cpu_kernels_compute_the_plain_nets_and_their_gradients_in_fp32'"),
    Mutation("kernels: the graph-wide inputs' gradient from the wrong weight columns", S,
             "@ w1[:, :k].float()", "@ w1[:, 1 : k + 1].float()",
             "tests/test_update.py -k 'cpu_kernels_compute_the_plain_nets_and_their_gradients_in_fp32'"),
    Mutation("kernels: the message net's backward with its fp32 weight", S,
             "ctx.save_for_backward(x, h, y, out, w2.to(dtype))", "ctx.save_for_backward(x, h, y, out, w2)",
             "tests/test_update.py -k 'cpu_kernels_compute_the_plain_nets_in_bf16'"),
    Mutation("cpu_line: AMX read from the AVX512-BF16 flag", S,
             '(("AMX", "amx_bf16"),', '(("AMX", "avx512_bf16"),', "tests/test_update.py -k cpu_line"),
    Mutation("kernels: the max's gradient not shared among exact ties (each tied edge gets all of it)", S,
             "g = torch.where(hit, grad.to(y.dtype)[:, :, None], 0) / hit.sum(2, keepdim=True).clamp_min_(1)",
             "g = torch.where(hit, grad.to(y.dtype)[:, :, None], 0)",
             "tests/test_update.py -k ties"),
    # --- what a fork may change: a sampler's budget, the fast nets' probe, --plain -----------------------
    Mutation("budget: a cycle's segments not checked", G,
             "    plumbing.check_budgets(run)  # each worker spent exactly its segments (a forked sampler may not)\n",
             "", "tests/test_fork.py -k budget"),
    Mutation("budget: a cycle that asks for too many segments runs on", G,
             "                if w.left < 0:  # a forked cycle", "                if False:  # a forked cycle",
             "tests/test_fork.py -k budget"),
    Mutation("budget: the message names the first worker, not the one that failed", P,
             "spent {n - w.left} of worker {w.index}'s", "spent {n - w.left} of worker {run.workers[0].index}'s",
             "tests/test_fork.py -k budget"),
    Mutation("kernels: the probe finds every net the fast nets' own", S,
             "f.shape == p.shape and torch.allclose(f, p, rtol=1e-4, atol=1e-4, equal_nan=True)",
             "f.shape == p.shape", "tests/test_fork.py -k 'changes_mlp or aggregation or off_the_cpu'"),
    Mutation("kernels: a kink on the probe's first batch turns the fast nets off", S,
             "same = same or (values_agree and all(agree(random_batch())))", "same = same",
             "tests/test_fork.py -k kink"),
    Mutation("kernels: values off on the probe's first batch alone forgiven as a kink", S,
             "same = same or (values_agree and all(agree(random_batch())))",
             "same = same or all(agree(random_batch()))", "tests/test_fork.py -k 'value_off_on_one_batch'"),
    Mutation("kernels: the probe's values and gradients judged together (a kink's gradient taken for a value)", S,
             "return same[0], all(same)", "return all(same), all(same)", "tests/test_fork.py -k kink"),
    Mutation("kernels: the fast path skips the probe", S,
             "agent.fast_nets = fast_nets_compute(agent, script, kernels)", "agent.fast_nets = True",
             "tests/test_fork.py -k changes_mlp"),
    Mutation("kernels: the probe compares values alone, not gradients", S,
             "return torch.cat([losses, target]), torch.cat(grads)",
             "return torch.cat([losses, target]), target.new_zeros(1)", "tests/test_fork.py -k other_gradients"),
    Mutation("kernels: run whether fast_nets asks for them or not", S,
             'return FAST["kernels"] and x.is_cpu and', "return x.is_cpu and", "tests/test_fork.py -k off_the_cpu"),
    Mutation("--plain: the fast path stays on", G, "        if not args.plain:  # the fast path",
             "        if True:  # the fast path", "tests/test_fork.py -k plain_turns"),
    Mutation("fast path: Adam not fused", S, "    fuse_adams(agent)\n", "", "tests/test_fork.py -k plain_turns"),
    Mutation("fused Adam: rebuilt from the first group's weights and the default rate (the others lost)", S,
             "    fuse_adams(agent)\n",
             '    agent.actor_opt, agent.critic_opt = (torch.optim.Adam(o.param_groups[0]["params"], '
             'lr=o.defaults["lr"], fused=True) for o in (agent.actor_opt, agent.critic_opt))\n',
             "tests/test_fork.py -k 'keeps_them_all or moments'"),
    Mutation("fused Adam: the defaults fused, the parameter groups not", S,
             "        for settings in (opt.defaults, *opt.param_groups):", "        for settings in (opt.defaults,):",
             "tests/test_fork.py -k keeps_them_all"),
    Mutation("fused Adam: a fork's moments dropped", S, "            opt.load_state_dict(opt.state_dict())",
             "            opt.state.clear()", "tests/test_fork.py -k moments"),
    Mutation("fused Adam: any optimizer class fused", S,
             "    if type(opt) not in (Adam, AdamW):", "    if False:",
             "tests/test_fork.py -k cannot_stand_in"),
    Mutation("fused Adam: torch's Adam read where a fork may have rebound torch.optim.Adam", S,
             "if type(opt) not in (Adam, AdamW):", "if type(opt) not in (torch.optim.Adam, torch.optim.AdamW):",
             "tests/test_paper_agent.py -k forks_parameter_groups"),
    Mutation("fused Adam: a subclass of Adam fused as Adam", S,
             "    if type(opt) not in (Adam, AdamW):",
             "    if not isinstance(opt, Adam):", "tests/test_fork.py -k cannot_stand_in"),
    Mutation("fused Adam: differentiable=True fused", S, '(("differentiable", True), ("foreach", True),',
             '(("foreach", True),', "tests/test_fork.py -k cannot_stand_in"),
    Mutation("fused Adam: a setting of a fork's later parameter group not read", S,
             "if any(group.get(key) is value for group in opt.param_groups):",
             "if any(group.get(key) is value for group in opt.param_groups[:1]):",
             "tests/test_fork.py -k second_parameter_group"),
    Mutation("fused Adam: foreach=True fused", S, '("foreach", True), ("fused", False))', '("fused", False),)',
             "tests/test_fork.py -k cannot_stand_in"),
    Mutation("fused Adam: a fork's fused=False fused", S, '("foreach", True), ("fused", False))',
             '("foreach", True),)', "tests/test_fork.py -k cannot_stand_in"),
    Mutation("fused Adam: an optimizer kept as built without a word", S,
             "    if kept and not (dist.is_initialized()", "    if False and not (dist.is_initialized()",
             "tests/test_fork.py -k cannot_stand_in"),
    Mutation("fused Adam: the line names the actor's optimizer whichever was kept", S,
             'kept.append(f"the {name}\'s optimizer {why}")', 'kept.append(f"the actor\'s optimizer {why}")',
             "tests/test_fork.py -k cannot_stand_in"),
    Mutation("fast path: freed memory not kept", S, "    if kernels:\n        keep_freed_memory()\n", "",
             "tests/test_fork.py -k plain_turns"),
    Mutation("--plain: bf16 accepted with it", P, 'if a.plain and (a.compile or a.precision != "fp32"):',
             "if a.plain and a.compile:", "tests/test_fork.py -k refuses"),
    Mutation("--plain: in the lp baseline, the fast path stays on", LP, "        if not args.plain:  # the fast path",
             "        if True:  # the fast path", "tests/test_fork.py -k plain_turns"),
    Mutation("versions: a checkpoint under other library versions resumed without a word", P,
             "if name in saved and saved[name] != now[name]]", "if name in saved and False]",
             "tests/test_gangstr.py -k library_versions"),
    Mutation("versions: the checkpoint records none", P, "env_version=ENV_VERSION, versions=library_versions(),",
             "env_version=ENV_VERSION,", "tests/test_gangstr.py -k library_versions"),
    # --- the project's own documents ---------------------------------------------------------------
    # (the new texts are split so that this file names no missing section and no tracker itself)
    Mutation("docs: a SPEC section that does not exist", G, "# every number: SPEC §5-§7, §9-§12.",
             "# every number: SPEC §5-§7, §9-§1" "4.", "tests/test_docs.py -k section_sign"),
    Mutation("docs: a section of a page that does not exist", G, 'section "How to read gangstr_hme.py beside',
             'section "How to run gangstr_hme.py beside', "tests/test_docs.py -k page_and_section"),
    Mutation("docs: a loose reference to a tracker", S, "update 1.06-1.11x that of commit 25d2c6b",
             "update 1.06-1.11x iss" "ue 25's", "tests/test_docs.py -k loose_references"),
    Mutation("docs: a page that does not exist", S, "(a speed trick, docs/speed.md: the",
             "(a speed trick, docs/sp" "eeds.md: the", "tests/test_docs.py -k page_and_section"),
    # --- mutations the suite used to miss -------------------------------------------------------
    Mutation("paper layers: mean and log-std heads swapped", P,
             'mean_linear", "actor", "head.out"),\n    ("rho_actor.log_std_linear',
             'log_std_linear", "actor", "head.out"),\n    ("rho_actor.mean_linear',
             "tests/test_paper_agent.py -k test_the_papers_file_loads"),
    Mutation("log pi without - log_std", G, "-0.5 * noise.pow(2) - log_std - 0.5", "-0.5 * noise.pow(2) - 0.5",
             f"{TG} -k test_sac_losses_follow_the_spec"),
    Mutation("HER relabels from the next segment", G, "g[her] = self.ag[w[her], ep[her], future[her]]",
             "g[her] = self.ag[w[her], (ep[her] + 1) % self.size, future[her]]", f"{TG} -k test_her_"),
    Mutation("HER switched off in training", G, "her_prob = 1 - 1 / (1 + args.her_k)", "her_prob = 0.0",
             f"{TG} -k test_training_relabels"),
    Mutation("actor loss through the live critic, messages not detached", G,
             "q_pi = torch.min(*self.acting_critic.q(body, blocks, pi, msg.detach()))",
             "q_pi = torch.min(*self.critic.q(body, blocks, pi, msg))", f"{TG} -k test_actor_loss_moves"),
    Mutation("VDS softmax of twice the logits", VDS, "e = np.exp(x - x.max())", "e = np.exp(2 * (x - x.max()))",
             f"{TB} -k test_goals_are_drawn_in_proportion"),
    Mutation("VDS heads regress 0 x target", VDS, "mse = ((self.vds(features) - target[None]) ** 2)",
             "mse = ((self.vds(features) - 0 * target[None]) ** 2)", f"{TB} -k test_vds_heads_regress"),
    Mutation("velocities not scaled by dt", ENV,
             ("obs[5:8] = grip_vel * dt", "blocks[:, 9:12] = (qvel[:, :3] - grip_vel) * dt"),
             ("obs[5:8] = grip_vel", "blocks[:, 9:12] = qvel[:, :3] - grip_vel"),
             f"{TE} -k test_block_velocities_are_scaled_by_dt"),
    Mutation("action scale 0.065", ENV, "ACTION_SCALE = 0.05 ", "ACTION_SCALE = 0.065 ",
             f"{TE} -k mocap_target_0_05_per_unit"),
    Mutation("action scale 0.042", ENV, "ACTION_SCALE = 0.05 ", "ACTION_SCALE = 0.042 ",
             f"{TE} -k mocap_target_0_05_per_unit"),
    Mutation("class goals: the last member drawn 4x as often", ORACLE,
             "return members[rng.integers(len(members), size=size)]",
             "return members[np.minimum(rng.integers(len(members) + 3, size=size), len(members) - 1)]",
             f"{TO} -k test_goals_are_sampled_uniformly"),
    Mutation("Welch's df replaced by Student's", "plot_results.py",
             "df = (vx + vy) ** 2 / (vx**2 / (len(x) - 1) + vy**2 / (len(y) - 1))", "df = len(x) + len(y) - 2",
             "tests/test_plot_results.py -k welch"),
    Mutation("a checkpoint's --precision bf16 not checked on resume", P,
             "    if why := check_device(merged):", "    if False and (why := check_device(merged)):",
             "tests/test_update.py -k resumed_where_bf16_is_slow"),
    Mutation("tables: a class counts as reached just above 0.5", "plot_results.py",
             "hit = np.flatnonzero(values >= level)", "hit = np.flatnonzero(values > level)",
             "tests/test_plot_results.py -k tables"),
    Mutation("tables: the first epoch at 0.5 counted from 1", "plot_results.py",
             "return str(int(hit[0])) if len(hit)", "return str(int(hit[0]) + 1) if len(hit)",
             "tests/test_plot_results.py -k committed_social_partner_runs"),
    Mutation("tables: proposals summed past the shortest run", "plot_results.py",
             "return f\"{int(r[f'sp_frontier_{k}'][:n].sum())}", "return f\"{int(r[f'sp_frontier_{k}'].sum())}",
             "tests/test_plot_results.py -k tables"),
    Mutation("tables: SR cells show the first seed as the mean", "plot_results.py",
             "cells = [f\"{sr[:, e].mean():.2f}", "cells = [f\"{sr[0, e]:.2f}",
             "tests/test_plot_results.py -k tables"),
    Mutation("target critic updated every update after the first", G,
             "if self.n_updates % self.args.target_update_every == 0:",
             "if self.n_updates >= self.args.target_update_every:", f"{TG} -k test_target_critic_is_polyak"),
    Mutation("--help without one default", P,
             'f" (default: {f.default!r})" if with_defaults else ""',
             'f" (default: {f.default!r})" if with_defaults and f.name != "n_epochs" else ""',
             f"{TG} -k test_help_shows_every_default"),
    Mutation("chi-square series branch returns 0.5", "tests/chisquare.py",
             "return 1.0 - total * math.exp(log_prefactor)", "return 0.5", "tests/test_chisquare.py"),
    Mutation("lockstep workers train on worker 0's replay only", G,
             "self.buffer.sample(args.batch_size, rngs, her_prob",
             "self.buffer.sample(args.batch_size, rngs[:1], her_prob",
             "tests/test_distributed.py -k test_two_workers_in_one_process"),
    Mutation("the fork's contract leaves out RESUMABLE", G, "      Args.RESUMABLE (optional;", "      (optional;",
             "tests/test_fork.py -k docstring_names"),
    Mutation("SPEC's list of a sampler's hooks leaves one out", "docs/SPEC.md",
             "  `goal_outcome(w, goal, reached)`, `after_cycle()`", "  `after_cycle()`",
             "tests/test_fork.py -k specs_list"),
    Mutation("the fork's contract lists a hook nothing calls", LP,
             "      check_sampler_args(args), a function",
             "      before_epoch(): nothing.\n      check_sampler_args(args), a function",
             "tests/test_fork.py -k docstring_names"),
    Mutation("--resume: the graph's nodes in sorted order", G, 'for m in state["masks"].tolist():',
             'for m in sorted(state["masks"].tolist()):', "tests/test_fork.py -k saved_order"),
    Mutation("torchrun logs process 0's own batch's losses", P,
             "        means = all_sum(means) / world()\n", "",
             "tests/test_distributed.py -k test_the_logged_losses_are_the_mean"),
    # --- the environment (SPEC §3) ---------------------------------------------------------------------
    Mutation("close threshold 0.095", ENV, "CLOSE_DIST = 0.09 ", "CLOSE_DIST = 0.095 ", f"{TE} -k thresholds"),
    Mutation("above from 2 cm up", ENV, "ABOVE_DZ = 0.05, (0.03, 0.06)", "ABOVE_DZ = 0.05, (0.02, 0.06)",
             f"{TE} -k thresholds"),
    Mutation("finger action sign", ENV, "self._finger_qpos + a[3]", "self._finger_qpos - a[3]",
             f"{TE} -k test_finger_action_opens"),
    Mutation("reset accepts blocks closer than a diagonal", ENV,
             "if np.all(np.linalg.norm(placed - xy, axis=1) >= MIN_SPAWN_DIST):", "if True:",
             f"{TE} -k test_resets_rest_blocks"),
    Mutation("no workspace clip", ENV,
             "np.minimum(np.maximum(target, WORKSPACE_LOW, out=target), WORKSPACE_HIGH, out=self.data.mocap_pos[0])",
             "self.data.mocap_pos[0] = target", f"{TE} -k toward_a_corner"),
    Mutation("roll sign", ENV, "np.arctan2(-m[..., 5], m[..., 8]", "np.arctan2(m[..., 5], m[..., 8]",
             f"{TE} -k test_euler_from_mat_recovers"),
    Mutation("success on any predicate", ENV, "return np.all(np.asarray(achieved_goal) ==",
             "return np.any(np.asarray(achieved_goal) ==", "tests/test_success.py -k one_success_rule"),
    # --- the oracle (SPEC §2, §4) ----------------------------------------------------------------------
    Mutation("a third overlap is stable", ORACLE, "STABLE_OVERLAP = 0.5 ", "STABLE_OVERLAP = 0.3 ",
             f"{TO} -k test_partial_overlap"),
    Mutation("no change counts as a small step", ORACLE, "return (diff != 0) & ((diff", "return ((diff",
             f"{TO} -k test_small_step_needs"),
    # --- SAC, HER, normalizer, GNN (SPEC §5) -----------------------------------------------------------
    Mutation("entropy bonus sign in the TD target", G, "(q_next - a.alpha * logp2)", "(q_next + a.alpha * logp2)",
             f"{TG} -k test_sac_losses_follow_the_spec"),
    Mutation("twin-Q max in the TD target", G, "q_next = torch.min(*self.critic_target.q(",
             "q_next = torch.max(*self.critic_target.q(", f"{TG} -k test_sac_losses_follow_the_spec"),
    Mutation("TD target on the online critic's messages", G, "tmsg2 = self.critic_target.messages(gi, blocks2, gap2)",
             "tmsg2 = self.critic.messages(gi, blocks2, gap2)", f"{TG} -k test_sac_losses_follow_the_spec"),
    Mutation("tanh correction sign", G, "torch.log(1 - a.pow(2) + 1e-6)", "torch.log(1 + a.pow(2) + 1e-6)",
             f"{TG} -k test_sac_losses_follow_the_spec"),
    Mutation("actor loss reaches the message net", G,
             "q_pi = torch.min(*self.acting_critic.q(body, blocks, pi, msg.detach()))",
             "q_pi = torch.min(*self.acting_critic.q(body, blocks, pi, msg))", f"{TG} -k test_actor_loss_moves"),
    Mutation("polyak weights swapped", G, "tp.mul_(self.args.polyak).add_(p, alpha=1 - self.args.polyak)",
             "tp.mul_(1 - self.args.polyak).add_(p, alpha=self.args.polyak)", f"{TG} -k test_target_critic_is_polyak"),
    Mutation("normalizer std floor 0.1", G, "np.maximum(self.eps**2, self.sumsq", "np.maximum(self.eps, self.sumsq",
             f"{TG} -k test_normalizer_clips"),
    Mutation("normalizer statistics of unclipped observations", G,
             "x = np.clip(x.reshape(len(x), -1, len(self.sum)), -self.clip, self.clip).astype(np.float64)",
             "x = x.reshape(len(x), -1, len(self.sum)).astype(np.float64)", f"{TG} -k test_normalizer_clips"),
    Mutation("HER future may pick the transition's own step", G, "future = t + 1 + (rng.random(batch)",
             "future = t + (rng.random(batch)", f"{TG} -k test_her_future"),
    Mutation("HER final is the second-to-last config", G, "future = np.full(batch, seg_len)",
             "future = np.full(batch, seg_len - 1)", f"{TG} -k test_her_final"),
    Mutation("HER reward from the achieved config before the step", G, "reward=fetch5_env.goal_reached(ag_next, g)",
             "reward=fetch5_env.goal_reached(self.ag[w, ep, t], g)", f"{TG} -k test_her_final"),
    Mutation("messages summed over edges", G, "m.shape[-1]).amax(dim=2)", "m.shape[-1]).sum(dim=2)",
             f"{TG} -k test_a_blocks_message_is_the_max"),
    Mutation("kernels: a head's gradient through its ReLU unmasked", S,
             "g = grad.contiguous()\n        gh = relu_backward_(product(g, w2.t()), h)",
             "g = grad.contiguous()\n        gh = product(g, w2.t())",
             "tests/test_update.py -k 'cpu_kernels_compute_the_plain_nets_and_their_gradients_in_fp32'"),
    Mutation("kernels: messages summed over edges", S, "return x, h, y, y.amax(dim=2)", "return x, h, y, y.sum(dim=2)",
             "tests/test_update.py -k 'cpu_kernels_compute_the_plain_nets_and_their_gradients_in_fp32'"),
    Mutation("edge input reads close for above", G, "above = np.arange(len(src)) + len(og.close_pairs(n_blocks))",
             "above = np.arange(len(src))", f"{TG} -k test_a_blocks_message_is_the_max"),
    # --- the semantic graph and its paths (SPEC §6) ----------------------------------------------------
    Mutation("SR EMA moves away from the outcome", G, "(float(success) - self.sr[c])", "(self.sr[c] - float(success))",
             f"{TG} -k 'test_edges_are_created or test_sr_ema'"),
    Mutation("edges for steps that are not small", G, "if start != final and is_small_step(start, final, self.n):",
             "if start != final:", f"{TG} -k test_edges_are_created"),
    Mutation("no SR sharing between permuted edges", G, "key = int(((ps << self.dim) | pf).min())",
             "key = int((ps[0] << self.dim) | pf[0])", f"{TG} -k test_edges_are_created"),
    Mutation("Dijkstra sums 1 - SR", G, "cost = (-np.log(np.clip(graph.sr, 1e-12, 1.0))).tolist()",
             "cost = (1 - np.clip(graph.sr, 1e-12, 1.0)).tolist()", f"{TG} -k test_safest_path_is_the_most_reliable"),
    Mutation("safest path: predecessors drawn uniformly, not by path counts", G, "r -= count[u]",
             "r -= count[path[-1]] / len(options)", f"{TG} -k test_equally_safe_paths"),
    Mutation("Yen pops the longest candidate", G, "heapq.heappush(candidates, (len(root) + len(spur),",
             "heapq.heappush(candidates, (-len(root) - len(spur),", f"{TG} -k test_yen_k_shortest"),
    Mutation("Yen counts block permutations as shapes", G, "kept.setdefault(_shape(graph, found[-1]), found[-1])",
             "kept.setdefault(tuple(found[-1]), found[-1])", f"{TG} -k k_different_shapes"),
    Mutation("a long path keeps its first configs", G, "else [path[0]] + path[-(cap - 1) :]", "else path[:cap]",
             f"{TG} -k test_plans_without_a_path"),
    Mutation("shortest paths with probability 1 - shortest_ratio", G,
             "if explore and rng.random() < graph.args.shortest_ratio:",
             "if explore and rng.random() < 1 - graph.args.shortest_ratio:", f"{TG} -k test_training_plans_take"),
    Mutation("autotelic goals never the newest node", G, "return self.masks[rng.integers(self.n_nodes)]",
             "return self.masks[rng.integers(max(1, self.n_nodes - 1))]", f"{TG} -k test_autotelic_goals_are_uniform"),
    Mutation("stability read over the first steps (the authors' bug)", G,
             "stable = (ag[:, T - a.stable_steps :] == ag[:, -1:])",
             "stable = (ag[:, 1 : 1 + a.stable_steps] == ag[:, -1:])",
             f"{TG} -k test_a_segment_is_stable"),
    Mutation("A*: a node reached again at the same depth takes the new predecessor", G,
             "(u, v) in banned_edges or nd >= dist.get(v, math.inf):",
             "(u, v) in banned_edges or nd > dist.get(v, math.inf):", f"{TG} -k 'yen or k_shortest'",
             harmless="the spur path found is another path of the same length: which of equally short paths Yen "
                      "meets first is free under SPEC §6 (k shortest paths of different shapes, one drawn uniformly)"),
    # --- HME: the social partner, internalization, rehearsal (SPEC §7) ---------------------------------
    Mutation("social with probability 1 - sp_ratio", G, "w.rng.random() < args.sp_ratio  # --sp-ratio",
             "w.rng.random() > args.sp_ratio  # --sp-ratio", f"{TH} -k test_cycle_kinds"),
    Mutation("rehearsal with probability 1 - internalization_prob", G, "w.rng.random() < args.internalization_prob:",
             "w.rng.random() >= args.internalization_prob:", f"{TH} -k test_cycle_kinds"),
    Mutation("stepping stones: tried edges instead of untried", G, "return known & ~np.isin(keys, graph.edge_keys())",
             "return known & np.isin(keys, graph.edge_keys())", f"{TH} -k test_stepping_stones_match"),
    Mutation("beyond goals include tried neighbours", G, "return tails[~np.isin(keys, graph.edge_keys())]",
             "return tails", f"{TH} -k test_beyond_goals_are_oracle"),
    Mutation("frontier: the agent may not move (elsewhere ignored)", G,
             "return stones[stones != current] if elsewhere else stones", "return stones",
             f"{TH} -k 'test_frontier_goals_are or (never_proposes and uniform)'"),
    Mutation("frontier: the current config not reachable from itself", G, "og.bfs_hops(*self.csr(0)[:2], s) >= 0]",
             "og.bfs_hops(*self.csr(0)[:2], s) > 0]", f"{TH} -k test_frontier_goals_are"),
    Mutation("beyond goals do not chain", G, "            start = beyond\n", "            pass\n",
             f"{TH} -k test_social_cycle_follows"),
    Mutation("beyond goals from the reset config", G, "yield from self.beyond_goals(w, base)",
             "yield from self.beyond_goals(w, here)", f"{TH} -k test_social_cycle_follows"),
    Mutation("frontier reached with the stochastic policy", G,
             "pursue(self.learner, w, frontier, explore=False, deterministic=True)",
             "pursue(self.learner, w, frontier, explore=False, deterministic=False)",
             f"{TH} -k test_social_cycle_follows"),
    Mutation("rehearsal attempts the beyond goal deterministically", G,
             "if arrived and w.left > 0:\n                yield Request(beyond, deterministic=False)",
             "if arrived and w.left > 0:\n                yield Request(beyond, deterministic=True)",
             f"{TH} -k test_rehearsal_goes_to"),
    Mutation("rehearsal always draws the first pair", G,
             "self.internalization_buffer[w.rng.integers(len(self.internalization_buffer))]",
             "self.internalization_buffer[0 * w.rng.integers(len(self.internalization_buffer))]",
             f"{TH} -k 'stored_once or merge_into_one_set'"),
    Mutation("merged pairs: new ones first", G, "return list(dict.fromkeys([*kept, *new]))",
             "return list(dict.fromkeys([*new, *kept]))", f"{TH} -k merge_into_one_set"),
    Mutation("internalization buffer keeps duplicates", G, "return list(dict.fromkeys([*kept, *new]))",
             "return [*kept, *new]", f"{TH} -k 'stored_once or merge_into_one_set'"),
    # --- beyond the paper: the learner asks for help (SPEC §7.1) ---------------------------------------
    Mutation("the learner asks while its graph grows", LQ, 'q["stalled"] = 0 if grew else q["stalled"] + 1',
             'q["stalled"] = q["stalled"] + 1', f"{TH} -k test_the_learner_asks_for_help"),
    Mutation("help goes on after a social cycle that added no node", LQ,
             'if q["helped"] and grew and q["helped"] < args.help_cycles:',
             'if q["helped"] and q["helped"] < args.help_cycles:', f"{TH} -k 'asks_for_help or help_goes_on'"),
    Mutation("help is not capped at help_cycles", LQ,
             'if q["helped"] and grew and q["helped"] < args.help_cycles:',
             'if q["helped"] and grew:', f"{TH} -k help_goes_on"),
    Mutation("the signal read by every worker, not once a cycle", LQ,
             'if q["read_at"] != self.learner.segments:', "if True:", f"{TH} -k test_the_learner_asks_for_help"),
    Mutation("--ask-after 0 does not turn the query off", G,
             ("if args.ask_after or args.learner_picks:", "Query(args, learner) if args.ask_after else None"),
             ("if True:", "Query(args, learner) if True else None"),
             f"{TH} -k 'test_the_learner_asks_for_help or coin_alone'"),
    Mutation("a query counted by every worker", G, 'self.query.state["helped"] == 1 and w.index == 0',
             'self.query.state["helped"] == 1', f"{TH} -k test_queries_help_cycles"),
    Mutation("help with nothing proposed never counted", G, "proposed = w.left < n_segments",
             "proposed = w.left <= n_segments", f"{TH} -k test_queries_help_cycles"),
    Mutation("the query's state not restored by --resume", G, 'if self.query is not None and "query" in s:',
             "if False:", f"{TG} -k 'stopped_run_resumes and ctrl'"),
    Mutation("--ask-progress classes counts nodes", LQ,
             'len(graph.sr) if self.args.ask_progress == "classes" else graph.n_nodes', "graph.n_nodes",
             f"{TL} -k sr_classes"),
    # --- beyond the paper: the learner picks among the partner's candidates (SPEC §7.1) -----------------
    Mutation("--learner-picks not installed", G, "if args.learner_picks:  # the learner picks", "if False:",
             f"{TL} -k change_what_the_partner_proposes"),
    Mutation("novelty: every pair counts, seen or not", LQ, "unseen = np.triu(self.pairs == 0)",
             "unseen = np.triu(self.pairs >= 0)", f"{TL} -k novelty"),
    Mutation("novelty: a fact never held alone does not count", LQ, "unseen = np.triu(self.pairs == 0)",
             "unseen = np.triu(self.pairs == 0, 1)", f"{TL} -k counts_the_pairs"),
    Mutation("novelty: nodes counted again at every pick", LQ, "            self.counted = graph.n_nodes\n", "",
             f"{TL} -k counts_the_pairs"),
    Mutation("novelty reads a class table", LQ, 'return np.einsum("ci,ij,cj->c", held, unseen, held)',
             'return np.einsum("ci,ij,cj->c", held, unseen, held) + 9 * (self.partner.oracle.class_of(og.from_mask('
             'np.asarray(candidates, dtype=np.int64), self.args.n_blocks)) == "C1")', f"{TL} -k renaming"),
    Mutation("ties: always the first", LQ, "best[w.rng.integers(len(best))]", "best[0]", f"{TL} -k ties_are_drawn"),
    Mutation("ties: drawn from numpy's global stream", LQ, "best[w.rng.integers(len(best))]",
             "best[np.random.randint(len(best))]", f"{TL} -k same_state_gives_the_same_pick"),
    Mutation("beyond goals: a config the agent has been in as good as a new one", LQ,
             "scores = [new.astype(np.float64), self.novelty(graph, candidates)]",
             "scores = [self.novelty(graph, candidates)]", f"{TL} -k new_configs_first"),
    Mutation("zpd: the easiest, not the hardest", LQ, "scores.append(-self.values(w, candidates))",
             "scores.append(self.values(w, candidates))", f"{TL} -k new_configs_first"),
    Mutation("zpd: the frontier least sure to arrive at", LQ, "return -dist[[graph.node_of",
             "return dist[[graph.node_of", f"{TL} -k surest"),
    Mutation("zpd: one round of Bellman-Ford", LQ, "if np.array_equal(new, dist):", "if True:", f"{TL} -k surest"),
    Mutation("zpd: the larger twin", LQ, "return torch.min(*agent.critic.q(", "return torch.max(*agent.critic.q(",
             f"{TL} -k smaller_twin"),
    Mutation("zpd: the stochastic actor's mean, shifted", LQ, "torch.tanh(mean), msg)", "torch.tanh(mean + 0.5), msg)",
             f"{TL} -k smaller_twin"),
    Mutation("--ask-progress without --ask-after accepted", G,
             'for k in ("help_cycles", "ask_progress")}', 'for k in ("help_cycles",)}', f"{TL} -k bad_learner_options"),
    Mutation("--help-cycles without --ask-after accepted", G,
             'for k in ("help_cycles", "ask_progress")}', 'for k in ("ask_progress",)}',
             f"{TL} -k bad_learner_options"),
    Mutation("a flag that needs another refused by its value, not for being given (the default's value passes)", P,
             "        if name in given and not getattr(a, needed)",
             "        if getattr(a, name) != getattr(type(a), name) and not getattr(a, needed)",
             f"{TL} -k bad_learner_options"),
    Mutation("--resume: values that mean the same refused as a change", P,
             "    meaning = lambda k, v: same.get(k, {}).get(v, v)  # noqa: E731",
             "    meaning = lambda k, v: v  # noqa: E731", f"{TL} -k resume_takes_a_value"),
    Mutation("a page shows a command the argument check refuses", "docs/training.md",
             "python gangstr_hme.py --ask-after 50 --partner person ", "python gangstr_hme.py --partner person ",
             "tests/test_docs.py -k every_command"),
    Mutation("picks: --strategy frontier offers the agent's own config", LQ,
             "candidates = self.partner.frontier_candidates(graph, current, elsewhere)",
             "candidates = self.partner.frontier_candidates(graph, current)",
             f"{TL} {TH} -k 'offered_candidates or (never_proposes and not uniform)'"),
    Mutation("zpd: the frontier by novelty alone, blind to the SR estimates", LQ,
             'if self.args.learner_picks == "zpd" and len(candidates):\n            return self.pick(w, candidates, '
             'self.arrival(', 'if False:\n            return self.pick(w, candidates, self.arrival(',
             f"{TL} -k zpd_changes_its_frontier"),
    Mutation("ties: a draw of numpy's global stream, from a beyond goal", LQ, "best[w.rng.integers(len(best))]",
             "best[np.random.randint(len(best))]", f"{TL} -k ties_are_drawn"),
    Mutation("novelty: the least novel beyond goal", LQ,
             "scores = [new.astype(np.float64), self.novelty(graph, candidates)]",
             "scores = [new.astype(np.float64), -self.novelty(graph, candidates)]", f"{TL} -k proposes_toward"),
    Mutation("picks: new configs read from the oracle's stepping stones", LQ,
             "new = ~np.isin(candidates, np.asarray(graph.masks, dtype=np.int64))",
             "new = ~np.isin(candidates, self.stepping_stones(graph))", f"{TL} -k oracle_beyond"),
    Mutation("picks: candidates checked against an oracle graph the pick builds itself", LQ,
             "        candidates = self.partner.beyond_candidates(graph, config)\n",
             "        candidates = self.partner.beyond_candidates(graph, config)\n"
             "        candidates = candidates[og.OracleGraph(self.args.n_blocks).contains(og.from_mask(candidates, "
             "self.args.n_blocks))]\n", f"{TL} -k oracle_beyond"),
    Mutation("picks: the partner's oracle kept at the start and read past the offers", LQ,
             ("        self.facts = og.config_dim(args.n_blocks)\n",
              "        candidates = self.partner.frontier_candidates(graph, current, elsewhere)\n"),
             ("        self.facts, self.known = og.config_dim(args.n_blocks), partner.oracle\n",
              "        candidates = self.partner.frontier_candidates(graph, current, elsewhere)\n"
              "        candidates = candidates[self.known.contains(og.from_mask(candidates, self.args.n_blocks))]\n"),
             f"{TL} -k oracle_beyond"),
    Mutation("help vs discovery: social cycles from cumulative segments", "plot_results.py",
             'np.diff(run["segments"], prepend=0.0) / run.get("n_segments", 10)',
             'run["segments"] / run.get("n_segments", 10)', "tests/test_plot_results.py -k help_vs_discovery"),
    Mutation("proposals per social cycle: cycles of epochs without logged proposals counted", "plot_results.py",
             "total = cycles[logged].sum()", "total = np.nansum(cycles)",
             "tests/test_plot_results.py -k proposals_per_social_cycle"),
    Mutation("first discovery: social cycles up to the epoch before it", "plot_results.py",
             "social_cycles(r)[: found[0] + 1]", "social_cycles(r)[: found[0]]",
             "tests/test_plot_results.py -k first_discovery"),
    # --- the paper's agent on request (--init-from paper, --checkpoint paper) -------------------------
    Mutation("paper: the download's hash not checked", P,
             "torch.hub.download_url_to_file(PAPER_URL, str(path), PAPER_SHA256, progress=sys.stderr.isatty())",
             "torch.hub.download_url_to_file(PAPER_URL, str(path), None, progress=sys.stderr.isatty())",
             "tests/test_paper_agent.py -k paper_offline_on_a_wrong_hash"),
    Mutation("paper: downloaded again on every use", P, "        if downloads and not path.is_file():\n",
             "        if downloads:\n", "tests/test_paper_agent.py -k paper_is_downloaded_once"),
    Mutation("paper: a file in the cache taken unchecked", P,
             'if (digest := hashlib.file_digest(f, "sha256").hexdigest()) != PAPER_SHA256:',
             'if (digest := hashlib.file_digest(f, "sha256").hexdigest()) == "":',
             "tests/test_paper_agent.py -k paper_offline_on_a_wrong_hash"),
    Mutation("paper: a failed download leaves the cache folder it made", P,
             "            shutil.rmtree(made, ignore_errors=True)\n", "            pass\n",
             "tests/test_paper_agent.py -k paper_offline_on_a_wrong_hash"),
    Mutation("paper: a silent server waited for without end", P,
             "            socket.setdefaulttimeout(PAPER_TIMEOUT)  # urlopen's, inside torch.hub\n", "",
             "tests/test_paper_agent.py -k paper_offline_on_a_wrong_hash"),
    Mutation("paper: --init-from paper read as a path", P, 'if a.init_from not in ("", "paper") and',
             "if a.init_from and", "tests/test_paper_agent.py -k paper_is_downloaded_once"),
    Mutation("paper: fetched before the other flags are checked", P,
             "    args, state, init = parse_args(Args, check_sampler_args, argv), None, None\n    for flag",
             '    if "paper" in (argv or sys.argv):\n        paper_file("--init-from")\n'
             "    args, state, init = parse_args(Args, check_sampler_args, argv), None, None\n    for flag",
             "tests/test_paper_agent.py -k bad_flag_beside_paper"),
    Mutation("paper: the cache elsewhere than ~/.cache without XDG_CACHE_HOME", P, 'Path.home() / ".cache"',
             'Path.home() / "cache"', "tests/test_paper_agent.py -k xdg_cache_home"),
    Mutation("paper: an empty XDG_CACHE_HOME taken as the current folder", P,
             'Path(os.environ.get("XDG_CACHE_HOME") or Path.home() / ".cache")',
             'Path(os.environ.get("XDG_CACHE_HOME", Path.home() / ".cache"))',
             "tests/test_paper_agent.py -k xdg_cache_home"),
    Mutation("paper: the process-wide socket timeout left at PAPER_TIMEOUT", P,
             "        socket.setdefaulttimeout(timeout)\n", "        pass\n",
             "tests/test_paper_agent.py -k socket_timeout_back"),
    Mutation("paper: a Ctrl-C during the download removes a cache folder it found", P,
             "made = next((p for p in reversed(path.parents) if not p.exists()), None) if downloads else None",
             "made = path.parent if downloads else None", "tests/test_paper_agent.py -k ctrl_c_during"),
    Mutation("paper: a Ctrl-C during the download leaves the folders made for it", P, "except BaseException as e:",
             "except Exception as e:", "tests/test_paper_agent.py -k ctrl_c_during_the_paper_download"),
    Mutation("paper: a Ctrl-C during the download taken for a failed download (exit 2)", P,
             "            raise  # a Ctrl-C", "            pass  # a Ctrl-C",
             "tests/test_paper_agent.py -k ctrl_c_during_the_paper_download"),
    Mutation("paper: under torchrun every process downloads", P,
             'downloads = int(os.environ.get("LOCAL_RANK", "0")) == 0', "downloads = True",
             "tests/test_paper_agent.py -k 'under_torchrun_one_process or under_torchrun_a_waiting'"),
    Mutation("paper: under torchrun no process downloads", P,
             'downloads = int(os.environ.get("LOCAL_RANK", "0")) == 0', 'downloads = "LOCAL_RANK" not in os.environ',
             "tests/test_paper_agent.py -k under_torchrun_one_process"),
    Mutation("paper: a waiting process removes the folders its node's downloader made", P,
             " if downloads else None  # to remove", "  # to remove",
             "tests/test_paper_agent.py -k under_torchrun_a_waiting"),
    Mutation("paper: a waiting process waits without end", P, "if time.monotonic() > deadline:", "if False:",
             "tests/test_paper_agent.py -k under_torchrun_a_waiting"),
    Mutation("paper: a waiting process takes the other's file unchecked", P, "            time.sleep(0.1)\n",
             "            time.sleep(0.1)\n        if not downloads:\n            return str(path)\n",
             "tests/test_paper_agent.py -k under_torchrun_a_waiting"),
    # --- fine-tuning after --init-from (--init-lr-scale, --init-warmup, ...); plot_results --epochs ---------
    Mutation("--init-warmup: the learning rates left at theirs during the warm-up", G,
             '                group["lr"] = lr * scale\n', "                pass\n",
             "tests/test_paper_agent.py -k 'rise_linearly or resumed_during_the_warmup'"),
    Mutation("--init-warmup: the first update a step ahead of the ramp", G,
             "scale = (self.n_updates + 1) / self.args.init_warmup",
             "scale = (self.n_updates + 2) / self.args.init_warmup",
             "tests/test_paper_agent.py -k rise_linearly"),
    Mutation("--init-warmup: the warm-up also in runs without --init-from", G,
             "if self.args.init_from and self.n_updates < self.args.init_warmup:",
             "if self.n_updates < self.args.init_warmup:", "tests/test_paper_agent.py -k never_touched"),
    Mutation("--init-warmup: the ramp set after the warm-up too (a fork's schedule overwritten)", G,
             "if self.args.init_from and self.n_updates < self.args.init_warmup:",
             "if self.args.init_from and self.n_updates < self.args.init_warmup + 5:",
             "tests/test_paper_agent.py -k rise_linearly"),
    Mutation("--init-lr-scale: the rates left unscaled", G,
             "scale = args.init_lr_scale if args.init_from else 1.0", "scale = 1.0",
             "tests/test_paper_agent.py -k 'times_init_lr_scale or resumed_during_the_warmup'"),
    Mutation("--init-lr-scale: also without --init-from", G,
             "scale = args.init_lr_scale if args.init_from else 1.0", "scale = args.init_lr_scale",
             "tests/test_paper_agent.py -k never_touched"),
    Mutation("--init-lr-scale: the warm-up ramps to the unscaled rates", G,
             "zip((*self.actor_opt.param_groups, *self.critic_opt.param_groups), self.lrs, strict=True)",
             "zip((*self.actor_opt.param_groups, *self.critic_opt.param_groups), (self.args.lr_actor, "
             "self.args.lr_critic))", "tests/test_paper_agent.py -k times_init_lr_scale"),
    Mutation("--init-warmup: a fork's parameter groups all ramped to the script's rate", G,
             'self.lrs = [g["lr"] for g in (*self.actor_opt.param_groups, *self.critic_opt.param_groups)]',
             'self.lrs = [o.defaults["lr"] for o in (self.actor_opt, self.critic_opt) for g in o.param_groups]',
             "tests/test_paper_agent.py -k own_rate"),
    Mutation("--init-lr-scale: a scale of 0 accepted", P,
             '("lr_actor", "lr_critic", "init_lr_scale"):', '("lr_actor", "lr_critic"):',
             "tests/test_paper_agent.py -k bad_uses_of_the_new_flags"),
    Mutation("--init-from: the file's normalizer updated unless frozen by hand", P,
             '        if "freeze_normalizer" not in given:', "        if False:",
             "tests/test_paper_agent.py -k keeps_the_files_normalizer_unless"),
    Mutation("--init-from: --no-freeze-normalizer overridden", P,
             '        if "freeze_normalizer" not in given:', "        if True:",
             "tests/test_paper_agent.py -k keeps_the_files_normalizer_unless"),
    Mutation("--init-from: a checkpoint from before the fine-tuning flags resumed at the new defaults", P,
             '    state["args"] = PREDATED | state["args"]', '    state["args"] = state["args"] | PREDATED',
             "tests/test_paper_agent.py -k before_the_fine_tuning_flags_resumes"),
    Mutation("plot_results: own hours without the evaluations' time", "plot_results.py",
             'np.cumsum(run["time_collect"] + run["time_update"] + run["time_eval"])',
             'np.cumsum(run["time_collect"] + run["time_update"])', "tests/test_plot_results.py -k hours_cut"),
    Mutation("plot_results: --hours drops the epoch that ends on the hour", "plot_results.py",
             'np.searchsorted(own_hours(run), hours, side="right")', "np.searchsorted(own_hours(run), hours)",
             "tests/test_plot_results.py -k hours_cut"),
    Mutation("plot_results: --epochs ignored", "plot_results.py",
             "first_hours(first_epochs(read_run(Path(f)), args.epochs), args.hours)",
             "first_hours(read_run(Path(f)), args.hours)",
             "tests/test_plot_results.py -k epochs_cuts"),
    Mutation("plot_results: --epochs 0 cuts every run to nothing", "plot_results.py",
             "v[:n] if n and isinstance(v, np.ndarray) else v", "v[:n] if isinstance(v, np.ndarray) else v",
             "tests/test_plot_results.py -k epochs_cuts"),
    Mutation("--init-learning-starts: updates from the first segment", G,
             "for _ in range(args.n_updates if self.buffer.size and not self.waiting else 0):",
             "for _ in range(args.n_updates if self.buffer.size else 0):",
             "tests/test_paper_agent.py -k 'no_update_runs_until or resumed_during_the_warmup'"),
    Mutation("--init-learning-starts: also without --init-from", G,
             "        if args.init_from and args.init_learning_starts:", "        if args.init_learning_starts:",
             "tests/test_paper_agent.py -k never_touched"),
    Mutation("--init-learning-starts: counted from the run's segments, not the replay (a resume's empty replay)", G,
             "held = int(gather_workers(np.full((args.num_envs, 1), self.buffer.size)).min())",
             "held = self.segments // (world() * args.num_envs)", "tests/test_paper_agent.py -k fills_again"),
    Mutation("--init-learning-starts: each process by its own replay (processes disagree)", G,
             "held = int(gather_workers(np.full((args.num_envs, 1), self.buffer.size)).min())",
             "held = self.buffer.size", "tests/test_distributed.py -k init_learning_starts"),
    Mutation("--init-learning-starts: still waiting when the replay holds exactly enough", G,
             "if held < args.init_learning_starts else None", "if held <= args.init_learning_starts else None",
             "tests/test_paper_agent.py -k replays_capacity_is_accepted"),
    Mutation("--init-learning-starts: a replay's capacity refused", P,
             "    if a.init_learning_starts > a.buffer_size // a.segment_len:",
             "    if a.init_learning_starts >= a.buffer_size // a.segment_len:",
             "tests/test_paper_agent.py -k replays_capacity_is_accepted"),
    Mutation("--init-learning-starts: the console's critic loss nan while the replay fills", P,
             "    if waiting is not None:\n", "    if False:\n",
             "tests/test_paper_agent.py -k resumed_during_the_warmup"),
    Mutation("--init-learning-starts: the progress line not told of the wait", P,
             'tally["losses"]["critic_loss"], getattr(run.learner, "waiting", None))',
             'tally["losses"]["critic_loss"])', "tests/test_paper_agent.py -k resumed_during_the_warmup"),
    Mutation("--eval-only of the paper's file: its JSON in the download cache, beside the file", P,
             "    folder = Path(args.runs_dir).resolve() if paper else checkpoint.parent",
             "    folder = checkpoint.parent", "tests/test_paper_agent.py -k eval_only_of_the_papers_file"),
    Mutation("--eval-only of a run's checkpoint: its JSON in --runs-dir, not beside it", P,
             "    folder = Path(args.runs_dir).resolve() if paper else checkpoint.parent",
             "    folder = Path(args.runs_dir).resolve()", "tests/test_gangstr.py -k eval_only_prints_sr_per_class"),
    Mutation("own goals per class: every one counted as reached", G,
             'self.stats[f"own_reached_{name}"] += reached', 'self.stats[f"own_reached_{name}"] += 1',
             "tests/test_worker.py -k own_goals"),
    Mutation("own goals per class: a goal's class looked up by another config", VDS,
             "self.class_of = {int(m): name for name, configs in classes.items() for m in og.to_mask(configs)}",
             "self.class_of = {int(m) + 1: name for name, configs in classes.items() for m in og.to_mask(configs)}",
             "tests/test_worker.py -k own_goals"),
    Mutation("a run without --init-from: the HER ratio off by one", LP,
             "her_prob = 1 - 1 / (1 + args.her_k)", "her_prob = 1 - 1 / (2 + args.her_k)",
             "tests/test_paper_agent.py -k computes_what_it_did_before"),
    Mutation("--init-warmup: a negative warm-up accepted", P,
             '"video_episodes", "init_warmup", "init_learning_starts"):', '"video_episodes", "init_learning_starts"):',
             "tests/test_paper_agent.py -k bad_uses_of_the_new_flags"),
    Mutation("--init-learning-starts: more than the replay holds accepted", P,
             "    if a.init_learning_starts > a.buffer_size // a.segment_len:", "    if False:",
             "tests/test_paper_agent.py -k bad_uses_of_the_new_flags"),
    Mutation("the --init-from flags accepted without --init-from", P,
             "if stray and not (a.init_from or a.resume):", "if stray and a.resume:",
             "tests/test_paper_agent.py -k bad_uses_of_the_new_flags"),
    # --- docs held to the code ------------------------------------------------------------------------
    Mutation("docs: training.md's default of --gamma differs from Args'", "docs/training.md",
             "| `--gamma` | `0.99` |", "| `--gamma` | `0.95` |", "tests/test_docs.py -k every_flag"),
    Mutation("outputs: a progress.csv column renamed, the page not", P,
             'time_eval=tally["eval"],', 'time_evaluation=tally["eval"],',
             "tests/test_docs.py -k 'every_progress_csv_column and vds'"),
    Mutation("README: the example sampler reads an attribute the oracle graph lacks", "README.md",
             "self.configs = og.OracleGraph(args.n_blocks).masks", "self.configs = og.OracleGraph(args.n_blocks).mask",
             "tests/test_fork.py -k readmes_example"),
    Mutation("README: the fork's hook list leaves out goal_outcome", "README.md",
             "pattern), `goal_outcome(w, goal, reached)`, `after_cycle()`", "pattern), `after_cycle()`",
             "tests/test_fork.py -k names_every_hook"),
    # --- a person as the partner (--partner person) -----------------------------------------------------
    Mutation("page: the reason for a missing picture shown only between questions", "person_partner.py",
             '$("noframe").textContent = s.render_problem ?',
             '$("noframe").textContent = !s.question && s.render_problem ?',
             "tests/test_person_browser.py -k without_pictures"),
    Mutation("page: rendering attempted without the quiet check (GLFW warnings)", "person_partner.py",
             "            self.no_pictures(plumbing.rendering_problem())\n", "            pass\n",
             "tests/test_person_browser.py -k without_pictures"),
    Mutation("page: the terminal told of a missing picture at every question", "person_partner.py",
             "        if not self.renderers and self.render_problem is None:\n", "        if not self.renderers:\n",
             "tests/test_person_browser.py -k without_pictures"),
    Mutation("the person's pick does not reach the agent", "person_partner.py",
             'picked, by = answered[1], "person"', 'picked, by = self.partner.choose(w, candidates), "person"',
             "tests/test_person.py -k pick_reaches_the_agent"),
    Mutation("the person's pick does not reach the agent (in the browser)", "person_partner.py",
             'picked, by = answered[1], "person"', 'picked, by = self.partner.choose(w, candidates), "person"',
             "tests/test_person_browser.py -k clicks_a_candidate"),
    Mutation("the token is not checked", "person_partner.py",
             "if not hmac.compare_digest(token.encode(), self.token.encode()):", "if False:",
             "tests/test_person.py -k token"),
    Mutation("the Host header is not checked", "person_partner.py",
             "if self.loopback() and host not in {", "if False and host not in {",
             "tests/test_person.py -k Host"),
    Mutation("a candidate not offered is taken", "person_partner.py",
             'if goal is not None and goal not in [c["mask"] for c in q["candidates"]]:', "if False:",
             "tests/test_person.py -k offered"),
    Mutation("an answer to a stale question is taken", "person_partner.py",
             'if q is None or q["id"] != qid:', "if q is None:", "tests/test_person.py -k stale"),
    Mutation("an oversized body is read", "person_partner.py",
             'if len(value.lstrip("0")) > len(str(MAX_BODY)) or int(value) > MAX_BODY:', "if False:",
             "tests/test_person.py -k oversized"),
    Mutation("a stop request leaves the question waiting", "person_partner.py",
             "and not self.stopping():", ":", "tests/test_person.py -k stop_request"),
    Mutation("a stop's waiting question drawn by the oracle as a timeout: the cycle goes on past it", PP,
             '"dropped" if self.stopping() else "timeout"', '"timeout"', "tests/test_person_stops.py -k ctrl-c"),
    Mutation("a stop's waiting question: the cycle goes on without a goal", PP,
             "                raise plumbing.CycleGivenUp  # the checkpoint", "                pass  # the checkpoint",
             "tests/test_person_stops.py -k sigterm"),
    Mutation("a sampler that gives up cycles not said so: the stop's cycle carried on", G,
             "            self.gives_up_cycles = True  # a stop", "            pass  # a stop",
             "tests/test_person_stops.py -k ctrl-c"),
    Mutation("a pick never pursued left unwritten when the next question has nothing to ask", PP,
             ("        if w.index in self.open_rows:  # its previous pick was never pursued",
              "        if len(candidates) == 0:\n            return None  # nothing to propose: nothing to ask\n"),
             ("        if len(candidates) == 0:\n            return None\n        if w.index in self.open_rows:  #",
              ""), "tests/test_person.py -k never_pursued"),
    Mutation("--resume: Adam steps as the checkpoint's run did (--plain or not)", P,
             '"fused": ours.get("fused")}', '"fused": g.get("fused")}', "tests/test_fork.py -k own_command_line"),
    Mutation("--resume: Adam's step counts left where the checkpoint's run kept them", P,
             '    opt.load_state_dict({**saved, "param_groups": groups})',
             '    opt.load_state_dict(saved)\n    for g, ours in zip(opt.param_groups, groups):\n'
             '        g["fused"] = ours["fused"]\n    opt.load_state_dict(opt.state_dict())',
             "tests/test_fork.py -k step_counts_are_where"),
    Mutation("paper: a SIGTERM during the download kills it where it stands", P,
             "signal.signal(signal.SIGTERM, signal.default_int_handler) if", "signal.getsignal(signal.SIGTERM) if",
             "tests/test_paper_agent.py -k ctrl_c_during"),
    Mutation("paper: a waiting process says it was interrupted when torchrun ends it", P,
             "catches = downloads and threading.", "catches = threading.",
             "tests/test_paper_agent.py -k without_a_word"),
    Mutation("a cycle given up for a stop saved as it was left, not as it began", P,
             "state = self.before_evaluation if self.before_evaluation is not None else self.before_cycle",
             "state = self.before_evaluation", "tests/test_person_stops.py -k ctrl-c"),
    Mutation("--resume: picks.csv not cut back to the checkpoint's questions", PP,
             'rows = [r for r in rows if r["question"].isdigit() and int(r["question"]) <= self.resumed_at]',
             "rows = rows", "tests/test_person_stops.py -k kill-9"),
    Mutation("--resume: the questions asked not checkpointed", G,
             "| (dict(person=self.person.state_dict()) if self.person else {}))",
             "| {})", "tests/test_person_stops.py -k kill-9"),
    Mutation("a timeout draws other than the oracle", "person_partner.py",
             'picked, by = self.partner.choose(w, candidates), "dropped"',
             'picked, by = int(candidates[0]), "dropped"', "tests/test_person.py -k no_answer_in_time"),
    Mutation("a second answer replaces the first", "person_partner.py", "if self.answer is not None:", "if False:",
             "tests/test_person.py -k second_answer"),
    Mutation("page, HTTP: a query field without '=' beside the token is a 500", PP,
             "query = urllib.parse.parse_qs(url.query)",
             "query = urllib.parse.parse_qs(url.query, strict_parsing=True)",
             "tests/test_person.py -k random_requests"),
    Mutation("page, HTTP: a 415 that does not name the Content-Type it got", PP,
             'f"answers are application/json, not {named}"', '"answers are application/json"',
             "tests/test_person.py -k content_type"),
    Mutation("page, HTTP: the HTTP parser's refusals in its own HTML", PP,
             "def send_error(self, code, message=None, explain=None):",
             "def send_error_unused(self, code, message=None, explain=None):",
             "tests/test_person.py -k 'parser_refuses or random_requests'"),
    Mutation("page, HTTP: a refusal to HTTP/0.9 or HTTP/2 without a status line", PP,
             'self.request_version, self.close_connection = "HTTP/1.0", True', "self.close_connection = True",
             "tests/test_person.py -k 'parser_refuses and HTTP'"),
    Mutation("page, HTTP: HTTP/0.9 served (without a status line)", PP,
             'if len(words) == 2 or (len(words) > 2 and re.fullmatch(r"HTTP/0+\\.[0-9]+", words[-1])):', "if False:",
             "tests/test_person.py -k 'parser_refuses and 0.9'"),
    Mutation("page, HTTP: a body that ends before its Content-Length is taken", PP,
             "if len(body) < length:", "if False:", "tests/test_person.py -k 'bad_request and past'"),
    Mutation("page, HTTP: a body that never comes whole is a 500", PP,
             "except TimeoutError:", "except ZeroDivisionError:", "tests/test_person.py -k never_comes"),
    Mutation("page, HTTP: the first of two Content-Lengths taken", PP, "if len(lengths) > 1 or not (", "if not (",
             "tests/test_person.py -k 'Content-Lengths'"),
    Mutation("page, HTTP: a Content-Length in other digits than ASCII read", PP,
             "not (value.isascii() and value.isdigit())", "not value.isdigit()",
             "tests/test_person.py -k 'bad_request and other'"),
    Mutation("page, HTTP: int() of a Content-Length of any length (a 500 past 4,300 digits)", PP,
             'if len(value.lstrip("0")) > len(str(MAX_BODY)) or int(value) > MAX_BODY:', "if int(value) > MAX_BODY:",
             "tests/test_person.py -k 'bad_request and 000'"),
    Mutation("page, HTTP: an answer in UTF-16 taken", PP,
             'data = json.loads(body.decode("utf-8"))', "data = json.loads(body)",
             "tests/test_person.py -k 'UTF or random_requests'"),
    Mutation("page, HTTP: Content-Type application/json read in lower case only", PP,
             '.strip(" \\t").lower() != "application/json":', '.strip(" \\t") != "application/json":',
             "tests/test_person.py -k 'content_type or random_requests'"),
    Mutation("the person's options left unchecked by the script's hook", G,
             'for k in ("partner", "person_timeout", "person_host", "person_port")):', "for k in ()):",
             "tests/test_person.py -k 'bad_partner_options or bad_page_options'"),
    Mutation("the person's picks and timeouts not counted in progress.csv", G,
             "            **{k: counts[k] for k in person},\n", "", "tests/test_person.py -k finishes_by_timeouts"),
    Mutation("the sampler's options unchecked after --resume's merge", P,
             "if (why := check_sampler_args(args)) is not None:  # the checkpoint's options",
             "if None:  # the checkpoint's options", "tests/test_person.py -k asked_only"),
    # --- LP (SPEC §8) ----------------------------------------------------------------------------------
    Mutation("LP without abs", LP, "lp[k] = abs(x[len(x) // 2 :].mean() - x[: len(x) // 2].mean())",
             "lp[k] = x[len(x) // 2 :].mean() - x[: len(x) // 2].mean()", f"{TB} -k 'test_lp_needs_20 or test_lp_is'"),
    Mutation("LP needs 21 outcomes", LP, "if len(o) >= self.min_outcomes:", "if len(o) > self.min_outcomes:",
             f"{TB} -k test_lp_needs_20"),
    Mutation("LP draws empty buckets", LP, "lp = self.progress() * nonempty", "lp = self.progress()",
             f"{TB} -k test_bucket_probabilities"),
    Mutation("LP mixes without 1 - uniform_prob", LP, "+ (1 - self.uniform_prob) * lp / lp.sum()", "+ lp / lp.sum()",
             f"{TB} -k test_bucket_probabilities"),
    Mutation("LP goal always the bucket's first config", LP, "return int(bucket[w.rng.integers(len(bucket))])",
             "return int(bucket[0])", f"{TB} -k test_lp_goals_come_from"),
    Mutation("LP credits every attempt as reached", LP, "w.attempts.append((w.drawn_from, reached))",
             "w.attempts.append((w.drawn_from, True))", f"{TB} -k test_lp_goals_come_from"),
    # --- VDS (SPEC §8) ---------------------------------------------------------------------------------
    Mutation("VDS disagreement as variance", VDS, ".std(dim=0).cpu().numpy()", ".var(dim=0).cpu().numpy()",
             f"{TB} -k test_disagreement_is_the_std"),
    Mutation("VDS candidates with replacement", VDS, "w.rng.choice(nodes, args.vds_candidates, False)",
             "w.rng.choice(nodes, args.vds_candidates, True)", f"{TB} -k test_at_most_1000"),
    Mutation("VDS multiplies by the temperature", VDS, "(score - score.max()) / args.vds_temperature",
             "(score - score.max()) * args.vds_temperature", f"{TB} -k test_goals_are_drawn_in_proportion"),
    # --- checkpoints and resume (SPEC §10) -------------------------------------------------------------
    Mutation("resume: workers' random streams not restored", P,
             "w.rng.bit_generator.state = json.loads(rng)", "w.rng.bit_generator.state = w.rng.bit_generator.state",
             f"{TG} -k test_a_run_restored_from_a_checkpoint"),
    Mutation("resume: envs' random streams not restored", P,
             "w.env.np_random.bit_generator.state = json.loads(env_rng)", "pass",
             f"{TG} -k test_a_run_restored_from_a_checkpoint"),
    Mutation("resume: update counter restarts", P, 'agent.n_updates = c["n_updates"]',
             "agent.n_updates = 0", f"{TG} -k test_a_run_restored_from_a_checkpoint"),
    Mutation("resume: replay pointer restarts", P, 'b.size, b.ptr = n, s["buffer"]["ptr"]',
             "b.size, b.ptr = n, 0", f"{TG} -k test_a_run_restored_from_a_checkpoint"),
    Mutation("checkpoint: normalizer sumsq saved as sum", P,
             "sumsq=torch.tensor(agent.normalizer.sumsq)", "sumsq=torch.tensor(agent.normalizer.sum)",
             f"{TG} -k test_a_run_restored_from_a_checkpoint"),
    Mutation("checkpoint without the critic's optimizer", P,
             '"actor_opt", "critic_opt")  # SAC\'s, as saved', '"actor_opt")  # SAC\'s, as saved',
             f"{TG} -k test_a_run_restored_from_a_checkpoint"),
    Mutation("resume: rows not restored", P, 'run.rows = s["rows"]', "run.rows = []",
             f"{TG} -k test_a_run_restored_from_a_checkpoint"),
    Mutation("resume: internalized pairs not restored", G,
             'self.internalization_buffer = merge_pairs([], [tuple(p) for p in s["internalization"].tolist()])',
             "self.internalization_buffer = []", f"{TG} -k test_a_run_restored_from_a_checkpoint"),
    Mutation("checkpoint of an older environment accepted", P,
             "if version != ENV_VERSION:", "if version > ENV_VERSION:", f"{TG} -k 'saying_what_it_is and environment'"),
    Mutation("checkpoints loaded with weights_only=False", P,
             "torch.load(path, weights_only=True, map_location", "torch.load(path, weights_only=False, map_location",
             "tests/test_paper_agent.py -k 'foreign_object and touch'"),
    Mutation("--resume ignores flags that contradict the checkpoint", P,
             "    if bad:\n", "    if bad and args.eval_only:\n", f"{TG} -k 'contradict and resume'"),
    # --- what a --cuda user meets, checked on a CPU ------------------------------------------------
    Mutation("gpu: --eval-only keeps a bf16 checkpoint's --precision", P,
             '"threads", "cuda", "precision", "plain", "eval_only",', '"threads", "cuda", "plain", "eval_only",',
             f"{TGPU} -k evaluated_in_fp32"),
    Mutation("gpu: a torchrun process past the last GPU not refused", P,
             "if a.cuda and local_gpu() >= torch.cuda.device_count():",
             "if a.cuda and local_gpu() > torch.cuda.device_count():", f"{TGPU} -k more_processes_than_gpus"),
    Mutation("gpu: fast bf16 counts compute capability 7 (emulated)", S,
             "torch.cuda.get_device_capability(gpu) >= (8, 0)",
             "torch.cuda.get_device_capability(gpu) >= (7, 0)", f"{TGPU} -k emulated"),
    Mutation("gpu: fast bf16 asked of GPU 0, not the process's own", S,
             'gpu = int(os.environ.get("LOCAL_RANK", "0"))', "gpu = 0", f"{TGPU} -k own_gpu"),
    Mutation("gpu: cuBLAS left to sum bf16 products in bf16", P,
             "allow_bf16_reduced_precision_reduction = False", "allow_bf16_reduced_precision_reduction = True",
             f"{TGPU} -k sums_its_bf16"),
    Mutation("gpu: nccl keeps its 10-minute timeout", P,
             'init_process_group("nccl" if cuda else "gloo", timeout=COLLECTIVE_TIMEOUT)',
             'init_process_group("nccl" if cuda else "gloo", timeout=None if cuda else COLLECTIVE_TIMEOUT)',
             f"{TGPU} -k 30_minutes"),
    Mutation("gpu: the batch copied array by array, waited for", S,
             "parts = staging.to(device, non_blocking=True).split(sizes)",
             "parts = [torch.from_numpy(v.ravel()).to(device) for v in arrays.values()]", f"{TGPU} -k one_copy"),
    Mutation("gpu: raw observations sent too", G,
             'b = b | dict(obs=self.normalizer(b["obs"]),', 'b = b | dict(raw=b["obs"], obs=self.normalizer(b["obs"]),',
             f"{TGPU} -k one_copy"),
    Mutation("gpu: a CPU batch copied", S, "return {k: torch.from_numpy(v) for k, v in arrays.items()}",
             "return {k: torch.tensor(v) for k, v in arrays.items()}", f"{TGPU} -k one_copy"),
    Mutation("gpu: an update reads its statistics itself", G, "return {k: v.detach() for k, v in info.items()}",
             "return {k: v.detach().cpu() for k, v in info.items()}", f"{TGPU} -k reads_its_updates"),
    Mutation("gpu: a cycle logs its last update's statistics, not their mean", P,
             "means = np.array([np.mean(values[:, j]) for j in range(len(keys))])", "means = values[-1]",
             f"{TGPU} -k reads_its_updates"),
    Mutation("gpu: the smoke check fails where there is no GPU", "benchmarks/gpu_smoke.py",
             "        return 0\n    start = time.perf_counter()", "        return 1\n    start = time.perf_counter()",
             f"{TGPU} -k smoke"),
    # --- a worker's streams and outcomes, the progress line -----------------------------------------------
    Mutation("a worker and its env seeded with the same number: one stream read twice", G,
             ("self.rng = np.random.default_rng(mine)", "self.env.reset(seed=int(env.generate_state(1)[0]))"),
             ("self.rng = np.random.default_rng(words[0])", "self.env.reset(seed=words[0])"),
             "tests/test_worker.py -k independent_streams"),
    Mutation("--eval-only reseeds every worker alike", P, "        w.seed(args.seed + w.index)\n",
             "        w.seed(args.seed)\n", "tests/test_worker.py -k eval_only"),
    Mutation("an attempt cut off by the budget counts as a failure", G,
             "        if w.left <= 0:\n            return None", "        if w.left <= 0:\n            return False",
             "tests/test_worker.py -k cut_off"),
    Mutation("time left in the epoch without its evaluation", P,
             "epoch_left = per_cycle * (a.n_cycles - run.cycle) + per_eval",
             "epoch_left = per_cycle * (a.n_cycles - run.cycle)", "tests/test_plumbing.py -k progress"),
    # --- what the partner opens: discoveries, arrivals, the fixed agent, evaluation sub-goals -----
    Mutation("agent nodes per class count the configs met", P,
             "int(np.isin(og.to_mask(m), nodes).sum()) for k, m", "int(np.isin(og.to_mask(m), met).sum()) for k, m",
             f"{TG} -k agent_nodes_per_class"),
    Mutation("every frontier proposal counts as an arrival", G,
             '        if arrived:\n            self.count("frontier_arrived", frontier)',
             '        if True:\n            self.count("frontier_arrived", frontier)',
             f"{TH} -k counted_in_their_class"),
    Mutation("a reached beyond goal is not counted", G,
             '            self.count("beyond_reached", beyond)\n            start = beyond',
             "            start = beyond", f"{TH} -k counted_in_their_class"),
    Mutation("--freeze-normalizer ignored", G, "if not self.args.freeze_normalizer:", "if True:",
             f"{TG} -k a_fixed_agent"),
    Mutation("the console shows a nan loss when no update ran", P, "    if args.n_updates > 0:\n",
             "    if True:\n", "tests/test_paper_agent.py -k 'a_fixed_agent or init_from_starts'"),
    Mutation("a diverged run reads as one without updates", P, "    if args.n_updates > 0:\n",
             "    if not math.isnan(critic_loss):\n", f"{TG} -k a_fixed_agent"),
    Mutation("a reached beyond goal uncounted under --strategy beyond", G,
             '            if segment.success:\n                self.count("beyond_reached", beyond)\n',
             "            if segment.success:\n", f"{TH} -k beyond_strategy_retries"),
    Mutation("Fisher's test leaves out tables as likely as the one seen", "plot_results.py",
             "if prob(x) <= seen * (1 + 1e-9)", "if prob(x) < seen", "tests/test_plot_results.py -k fisher"),
    Mutation("progress.csv rewritten with the epoch's row alone", P,
             "        write_csv(self.path, self.rows)\n", "        write_csv(self.path, self.rows[-1:])\n",
             f"{TG} -k older_versions"),
    Mutation("evaluation keeps a long path's first sub-goals", G, "path[1:][-args.max_eval_subgoals :]",
             "path[1:][: args.max_eval_subgoals]", f"{TG} -k max_eval_subgoals_of"),
]
# fmt: on


# ------------------------------------------------------------------------------------------------
# Running them
# ------------------------------------------------------------------------------------------------
def project_files() -> list[str]:
    """The files git knows of: tracked, and untracked but not ignored (a new test not yet committed)."""
    out = subprocess.run(["git", "ls-files", "-z", "--cached", "--others", "--exclude-standard"], cwd=ROOT,
                         capture_output=True, text=True, check=True)  # fmt: skip
    return [f for f in out.stdout.split("\0") if f and (ROOT / f).is_file()]


def mutated(m: Mutation) -> str:
    """The mutated text of m.file; exits with the reason if an old text does not occur exactly once."""
    text = (ROOT / m.file).read_text()
    for old, new in m.edits():
        if text.count(old) != 1:
            sys.exit(
                f"mutation {m.name!r}: {old!r} occurs {text.count(old)} times in {m.file}, not once: update the list"
            )
        text = text.replace(old, new)
    return text


def copy_project(files: list[str], dest: Path):
    for f in files:
        (dest / f).parent.mkdir(parents=True, exist_ok=True)
        shutil.copy2(ROOT / f, dest / f)


def pytest_run(folder: Path, guard: str, timeout: float) -> tuple[int | None, str]:
    """(pytest's exit code or None on timeout, its output's tail) for the guard's tests in folder."""
    cmd = [sys.executable, "-m", "pytest", "-x", "-q", "-p", "no:cacheprovider", *shlex.split(guard)]
    env = os.environ | {"PYTHONDONTWRITEBYTECODE": "1"}
    try:
        out = subprocess.run(cmd, cwd=folder, capture_output=True, text=True, timeout=timeout, env=env)
    except subprocess.TimeoutExpired:
        return None, ""
    return out.returncode, (out.stdout + out.stderr)[-1500:]


def check(m: Mutation | None, guard: str, files: list[str], timeout: float) -> tuple[str, float, str]:
    """Apply m (None: nothing) to a fresh copy and run guard: (verdict, seconds, output tail)."""
    t = time.perf_counter()
    with tempfile.TemporaryDirectory(prefix="mutation-") as tmp:
        copy_project(files, Path(tmp))
        if m is not None:
            (Path(tmp) / m.file).write_text(mutated(m))
        code, tail = pytest_run(Path(tmp), guard, timeout)
    verdict = {None: "killed", 0: "survived", 1: "killed", 2: "killed"}.get(code, f"error {code}")
    if code is None:
        verdict = "killed (timeout)"
    return verdict, time.perf_counter() - t, tail


def baseline_guards(mutations: list[Mutation]) -> list[str]:
    """The guards merged per set of test files (one pytest run each): -k expressions joined with 'or'."""
    groups: dict[tuple[str, ...], list[str | None]] = {}
    for m in mutations:
        args = shlex.split(m.guard)
        files, expr = (args[: args.index("-k")], args[args.index("-k") + 1]) if "-k" in args else (args, None)
        groups.setdefault(tuple(files), []).append(expr)
    merged = []
    for files, exprs in groups.items():
        k = "" if None in exprs else " -k " + shlex.quote(" or ".join(f"({e})" for e in dict.fromkeys(exprs)))
        merged.append(" ".join(files) + k)
    return merged


def main():
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("-k", dest="select", default="", help="only the mutations whose name contains this text")
    parser.add_argument("--list", action="store_true", help="list the mutations and their guards, run nothing")
    parser.add_argument("--jobs", type=int, default=1, help="mutations checked at once (each runs pytest)")
    parser.add_argument("--timeout", type=float, default=600, help="seconds a guard may run (then: killed)")
    parser.add_argument("--no-baseline", action="store_true", help="skip running the guards on the unmutated code")
    args = parser.parse_args()
    chosen = [m for m in MUTATIONS if args.select.lower() in m.name.lower()]
    for m in chosen:
        mutated(m)  # every old text occurs once, before anything runs
    if args.list:
        for m in chosen:
            print(f"{m.name}\n    {m.file}; guard: {m.guard}" + (f"\n    harmless: {m.harmless}" if m.harmless else ""))
        print(f"{len(chosen)} mutations")
        return 0
    files, start = project_files(), time.perf_counter()
    pool = concurrent.futures.ThreadPoolExecutor(max(1, args.jobs))
    if not args.no_baseline:
        guards = baseline_guards(chosen)
        print(f"the guards on the unmutated code ({len(guards)} pytest runs) ...", flush=True)
        for guard, (verdict, _, tail) in zip(guards, pool.map(lambda g: check(None, g, files, args.timeout), guards),
                                             strict=True):  # fmt: skip
            if verdict != "survived":
                print(f"error: a guard fails on the unmutated code: pytest {guard}\n{tail}", file=sys.stderr)
                return 2
    print(f"{len(chosen)} mutations:", flush=True)
    counts = dict(killed=0, survived=0, harmless=0, error=0)
    futures = {pool.submit(check, m, m.guard, files, args.timeout): m for m in chosen}
    for future in concurrent.futures.as_completed(futures):
        m, (verdict, seconds, tail) = futures[future], future.result()
        kind = verdict.split()[0]
        if kind == "survived" and m.harmless:
            kind, verdict = "harmless", f"survived, harmless: {m.harmless}"
        counts[kind] += 1
        print(f"  {'KILLED' if kind == 'killed' else kind.upper():9s} {m.name}  ({m.file}; {seconds:.0f} s)"
              + (f"\n            {verdict}" if kind == "harmless" else "")
              + (f"\n{tail}" if kind == "error" else ""), flush=True)  # fmt: skip
    minutes = (time.perf_counter() - start) / 60
    print(f"{counts['killed']} killed, {counts['survived']} survived, {counts['harmless']} harmless survivors, "
          f"{counts['error']} errors, of {len(chosen)}; {minutes:.1f} min")  # fmt: skip
    return 0 if counts["survived"] == counts["error"] == 0 else 1


if __name__ == "__main__":
    sys.exit(main())
