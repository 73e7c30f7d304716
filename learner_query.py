"""Beyond the paper (SPEC §7.1): the learner asks the social partner for help, and picks among its offers.

The paper ends (Conclusion) on "an automatic competence-based query mechanism from the learner". Two parts,
each read only from what the agent has (its semantic graph, its networks, its own counts), never from the
oracle beyond the goals the partner offers, the evaluation classes, or any hand-written notion of stacks:
  - Query (--ask-after, --help-cycles, --ask-progress): *when* a cycle is social besides the coin;
  - LearnerPicks (--learner-picks): *which* of the partner's candidates it proposes. The partner offers
    exactly what it offers today (SocialPartner.frontier_candidates, beyond_candidates: the sets a person sees
    on the page); the learner's signal replaces the uniform draw.
gangstr_hme.py imports this file only when one of those flags is set; its GoalSampler holds the hooks.
"""

from __future__ import annotations

import numpy as np
import torch

import oracle_graph as og

PICKS = ("novelty", "zpd")
PROGRESS = ("nodes", "classes")


# ------------------------------------------------------------------------------------------------
# When: the learner's query (SPEC §7.1)
# ------------------------------------------------------------------------------------------------
class Query:
    """The learner asks for help once its progress has stalled for ask_after cycles. Its progress, by
    --ask-progress: 'nodes' (or '', the default), the configs of its semantic graph; or 'classes', its SR
    classes (SPEC §6), the kinds of transition it has made, in which every partner proposal it reaches counts
    (a beyond goal is an untried edge, and an untried edge has a class of its own, since every class comes
    with all its edges).
      - stalled: cycles in a row that added no progress;
      - once stalled reaches ask_after, the learner asks (a query): the next cycle is social;
      - the help goes on, one social cycle after another, while each adds progress, for help_cycles cycles
        at most; then stalled counts again from 0.
    The graph is the same in every process (SPEC §11), so every worker gets the same answer, and no random
    draw is made: the coin's stream (--sp-ratio) is unchanged. Read once a cycle, by the first worker to
    start it (the graph has learnt from the previous cycle by then)."""

    def __init__(self, args, learner):
        self.args, self.learner = args, learner
        # the progress and the cycle it was read at, cycles without progress, the help given in a row (0: none)
        self.state = dict(progress=0, read_at=-1, stalled=0, helped=0)

    def progress(self) -> int:
        graph = self.learner.graph
        return len(graph.sr) if self.args.ask_progress == "classes" else graph.n_nodes

    def asks(self) -> bool:
        """Whether this cycle is help the learner asked for."""
        q, args = self.state, self.args
        if q["read_at"] != self.learner.segments:  # a new cycle: the previous one's outcome is in the graph
            now = self.progress()
            q["read_at"], grew, q["progress"] = self.learner.segments, now > q["progress"], now
            if q["helped"] and grew and q["helped"] < args.help_cycles:
                q["helped"] += 1  # the help goes on
            elif q["helped"]:
                q["helped"] = q["stalled"] = 0  # the help is over
            else:
                q["stalled"] = 0 if grew else q["stalled"] + 1
                if q["stalled"] >= args.ask_after:
                    q["helped"] = 1  # the query
        return q["helped"] > 0

    def state_dict(self) -> torch.Tensor:
        return torch.tensor(list(self.state.values()), dtype=torch.int64)

    def load_state_dict(self, s: torch.Tensor):
        self.state = dict(zip(self.state, s.tolist(), strict=True))


# ------------------------------------------------------------------------------------------------
# What: the learner picks among the partner's offers (SPEC §7.1)
# ------------------------------------------------------------------------------------------------
class LearnerPicks:
    """The social partner of gangstr_hme.py with the learner's choice among its candidates (`partner`, a
    SocialPartner, offers them; everything else, stepping stones and classes, is the partner's). A config's
    facts are its true predicates (SPEC §2); a pair is two of them, or one with itself. By --learner-picks:
      - 'novelty' (count-based): a beyond goal is a candidate that is not yet a node of the agent's graph
        (no stable segment has started or ended there, up to the blocks' order), if there is one, and among
        those the one holding the most pairs that no node holds together. A frontier goal is a node, whose
        pairs have all been held: all tie, and the draw below decides, as the uniform partner does.
      - 'zpd' (competence, the zone of proximal development): the frontier goal is the stepping stone the
        agent is surest to arrive at, by its graph: the highest product of SR estimates along a path from
        where it stands (SPEC §6's safest path; 1 for where it stands). A beyond goal is picked by novelty,
        then, among the equally novel, the hardest by the critic: the lowest value Q(s, mu(s, g), g) of the
        candidate g from where the agent stands (mu: the deterministic actor; Q: the smaller twin).
    The highest score wins (then the next score, among those tied); ties are drawn from the worker's
    stream, one draw as the uniform partner makes, so a run stays exact under any split of the workers into
    processes and across --resume (SPEC §11)."""

    def __init__(self, partner, args, learner, split_obs):
        self.partner, self.args, self.learner, self.split_obs = partner, args, learner, split_obs
        self.facts = og.config_dim(args.n_blocks)
        self.pairs = np.zeros((self.facts, self.facts), dtype=np.int64)  # nodes in which facts i and j both hold
        self.counted = 0  # nodes counted in `pairs` so far (the graph only ever adds nodes)

    def __getattr__(self, name):  # stepping_stones, oracle, outcome, ...: the partner's
        if name == "partner":
            raise AttributeError(name)
        return getattr(self.partner, name)

    def frontier_goal(self, graph, current: int, w, elsewhere: bool = False) -> int | None:
        candidates = self.partner.frontier_candidates(graph, current, elsewhere)
        if self.args.learner_picks == "zpd" and len(candidates):
            return self.pick(w, candidates, self.arrival(graph, current, candidates))
        return self.pick(w, candidates, self.novelty(graph, candidates))

    def beyond_goal(self, graph, config: int, w) -> int | None:
        candidates = self.partner.beyond_candidates(graph, config)
        new = ~np.isin(candidates, np.asarray(graph.masks, dtype=np.int64))  # no node of its graph yet
        scores = [new.astype(np.float64), self.novelty(graph, candidates)]
        if self.args.learner_picks == "zpd" and len(candidates):
            scores.append(-self.values(w, candidates))  # the hardest, by the critic
        return self.pick(w, candidates, *scores)

    def pick(self, w, candidates: np.ndarray, *scores: np.ndarray) -> int | None:
        """The candidate of highest score, then of highest next score among those tied, and so on (ties to
        1e-9: sums of logs in another order tie); among the last ties, one draw from the worker's stream.
        None: no candidate."""
        if not len(candidates):
            return None
        best = np.arange(len(candidates))
        for score in scores:
            best = best[score[best] >= score[best].max() - 1e-9]
        return int(candidates[best[w.rng.integers(len(best))]])

    def novelty(self, graph, candidates: np.ndarray) -> np.ndarray:
        """Each candidate's pairs of facts that no node of the agent holds together (see the class)."""
        if self.counted < graph.n_nodes:  # count the nodes added since the last pick
            new = og.from_mask(np.asarray(graph.masks[self.counted :], dtype=np.int64), self.args.n_blocks) > 0
            self.pairs += new.T.astype(np.int64) @ new.astype(np.int64)
            self.counted = graph.n_nodes
        held = (og.from_mask(np.asarray(candidates, dtype=np.int64), self.args.n_blocks) > 0).astype(np.int64)
        unseen = np.triu(self.pairs == 0).astype(np.int64)  # each unordered pair once, a fact with itself included
        return np.einsum("ci,ij,cj->c", held, unseen, held)

    def arrival(self, graph, current: int, candidates: np.ndarray) -> np.ndarray:
        """The log of the graph's estimate of arriving at each candidate from `current`: minus the cost of the
        safest path (the sum of -log SR along it), by Bellman-Ford over all edges at once."""
        indptr, heads, classes = graph.csr(1)  # edges grouped by the node they lead to
        cost = -np.log(np.clip(np.asarray(graph.sr), 1e-12, 1.0))[classes]
        into = np.flatnonzero(np.diff(indptr))  # nodes that some edge leads to
        dist = np.full(graph.n_nodes, np.inf)
        dist[graph.node_of[current]] = 0.0
        while True:  # every edge relaxed once a round: as many rounds as the longest safest path has edges
            new = dist.copy()
            new[into] = np.minimum(dist[into], np.minimum.reduceat(dist[heads] + cost, indptr[into]))
            if np.array_equal(new, dist):
                break
            dist = new
        return -dist[[graph.node_of[int(c)] for c in candidates]]

    @torch.inference_mode()
    def values(self, w, candidates: np.ndarray) -> np.ndarray:
        """The critic's value (the smaller twin) of each candidate goal from where the agent stands, with the
        deterministic actor's action."""
        agent = self.learner.agent
        now = w.env.set_goal(w.env.goal)
        goals = og.from_mask(np.asarray(candidates, dtype=np.int64), self.args.n_blocks).astype(np.float32)
        obs = torch.from_numpy(agent.normalizer(np.repeat(now["observation"][None], len(goals), 0).astype(np.float32)))
        body, blocks = self.split_obs(obs.to(agent.device), agent.gi.n)
        gap = torch.from_numpy(goals - now["achieved_goal"].astype(np.float32)).to(agent.device)
        msg = agent.critic.messages(agent.gi, blocks, gap)
        mean, _ = agent.actor(body, blocks, msg)
        return torch.min(*agent.critic.q(body, blocks, torch.tanh(mean), msg)).double().cpu().numpy()


def check_args(a) -> str | None:
    """The options of this file: the first bad value, described, or None."""
    if a.learner_picks and a.learner_picks not in PICKS:
        return f"--learner-picks must be one of {', '.join(PICKS)} (or '': the uniform draw), got {a.learner_picks!r}"
    if a.ask_progress not in ("", *PROGRESS):
        return f"--ask-progress must be one of {', '.join(PROGRESS)}, got {a.ask_progress!r}"
    if a.learner_picks and a.sp_ratio == 0 and a.ask_after == 0 and not a.eval_only:
        return "--learner-picks needs social cycles to pick in: give --sp-ratio above 0 or --ask-after above 0"
    if a.learner_picks and a.partner == "person":
        return "--learner-picks and --partner person both choose the partner's goals: give one of them"
    return None
