# Docs: docs/training.md and docs/results.md; the paper's figures (Section 4) from the runs' progress.csv.
"""Plot the paper's figures from run folders (SPEC §10: one progress.csv row per epoch).

    python plot_results.py --condition SP-20% runs/gangstr_hme__* --condition SP-0% runs/gangstr_sp0__* \
        --reference SP-0% --out figures [--epochs N] [--hours H]

Each --condition names a condition and lists its run folders (one per seed). Figures, as PNG and PDF:
- global_sr: global success rate over episodes, mean +- std over seeds; a star marks the points where
  a condition differs from --reference (Welch's t-test, p < --alpha);
- sr_per_class: success rate per evaluation class, one panel per class; sr_per_class_by_hour: the same over
  each run's own hours (its epochs' wall seconds, time_epoch, or before it their parts; --hours H cuts each run there);
- sp_per_class: per class, the social partner's proposals (frontier and beyond), the agent's distinct
  encounters, and its success rate over time (first seed-mean of each condition that has proposals);
- stepping_stones: the stepping stones left, per condition with a social partner;
- discovered_per_class and agent_nodes, for runs that log the agent graph's nodes per class: per class, its
  configurations that are agent-graph nodes; the graph's size;
- help_vs_discovery, for those runs: one point per run, social cycles in the run (x, log scale) against
  the hard-class configurations discovered by its last epoch (y; HARD: S3, S2&S2, S2&S3, P3&S2, S4, S5);
- proposals_per_social_cycle, for conditions whose runs had social cycles: per class, the partner's beyond
  and frontier proposals per social cycle over the whole run, one bar per condition (mean, min-max over runs).
And tables.md, the same runs in numbers (Markdown): SR per class by epoch, the epoch at which each class
first reaches 0.5 (and the first own hour at 0.5 and at 0.8), the distinct configs met by epoch, the social
partner's proposals and what the agent reached of them, and per condition its proposals per social cycle; the
configurations discovered per class (by epoch, first epoch, Welch's test at the end) and, per run, the help it
had (social cycles, the learner's queries) beside the first epoch at which it opened each hard class, with the
social cycles by then; for runs that log their own goals per class, why each construction comes late (discovery,
practice or skill: practice_tables).
"""

from __future__ import annotations

import argparse
import csv
import json
import math
import os
import sys
from pathlib import Path

import numpy as np

import oracle_graph as og


# ------------------------------------------------------------------------------------------------
# Reading runs
# ------------------------------------------------------------------------------------------------
def read_run(folder: Path) -> dict[str, np.ndarray]:
    """Columns of a run folder's progress.csv as float arrays (one entry per epoch; an empty cell, a column that
    a run resumed from an older version did not log before, is nan)."""
    path = Path(folder) / "progress.csv"
    if not path.is_file():
        raise ValueError(f"no progress.csv in run folder {str(folder)!r}")
    with path.open(newline="") as f:
        rows = list(csv.DictReader(f))
    if not rows or "global_sr" not in rows[0]:
        raise ValueError(f"{str(path)!r} has no rows with a global_sr column")
    try:
        run = {k: np.array([float(r[k]) if r[k] != "" else math.nan for r in rows]) for k in rows[0]}
    except (TypeError, ValueError) as e:
        raise ValueError(f"{str(path)!r} holds a value that is not a number ({e})") from None
    if "epoch" in run and not np.array_equal(run["epoch"], np.arange(len(rows))):
        raise ValueError(f"{str(path)!r}: epochs are not 0, 1, 2... once each (a duplicated or missing epoch)")
    config = Path(folder) / "config.json"
    try:  # the block count sets the class sizes; the seed names the run in the tables
        settings = json.loads(config.read_text())
        run["n_blocks"] = int(settings["n_blocks"])
        for key in ("seed", "n_segments"):  # n_segments: a cycle's segments, to count social cycles
            if key in settings:
                run[key] = int(settings[key])
    except (OSError, ValueError, KeyError, TypeError) as e:
        raise ValueError(f"cannot read n_blocks from {str(config)!r} ({type(e).__name__}: {e})") from None
    return run


def first_epochs(run: dict, n: int) -> dict:
    """The run's first n epochs (n = 0: all), so that runs of different lengths compare over the same span."""
    return {k: v[:n] if n and isinstance(v, np.ndarray) else v for k, v in run.items()}


def own_hours(run: dict) -> np.ndarray:
    """Hours of the run's own time at each epoch's end: its wall seconds (time_epoch; with --overlap, collecting
    and updating at once), or in a row written before that column its collecting, updating and evaluating seconds
    summed (start-up, checkpoints and time stopped left out), the time axis of runs compared at equal compute."""
    parts = run["time_collect"] + run["time_update"] + run["time_eval"]
    wall = run.get("time_epoch", np.full_like(parts, np.nan))
    return np.cumsum(np.where(np.isnan(wall), parts, wall)) / 3600


def first_hours(run: dict, hours: float, folder: str) -> dict:
    """The run's epochs that end within `hours` of its own time (0: all); ValueError if none does."""
    if not hours:
        return run
    if "time_eval" not in run:
        raise ValueError(f"{folder!r} logs no time columns: --hours cannot cut it")
    if not (n := int(np.searchsorted(own_hours(run), hours, side="right"))):
        raise ValueError(f"{folder!r}: its first epoch ends after --hours {hours} ({own_hours(run)[0]:.2f} h)")
    return first_epochs(run, n)


def stack(runs: list[dict], column: str) -> np.ndarray:
    """(seeds, epochs) of one column, cut to the shortest run of the condition."""
    n = min(len(r[column]) for r in runs)
    return np.stack([r[column][:n] for r in runs])


def class_names(runs: list[dict]) -> list[str]:
    return [k[3:] for k in runs[0] if k.startswith("sr_") and k not in ("sr_classes",)]


# ------------------------------------------------------------------------------------------------
# Welch's t-test (no SciPy: the Student-t tail through the regularized incomplete beta function)
# ------------------------------------------------------------------------------------------------
def _betacf(a: float, b: float, x: float) -> float:
    """Continued fraction of the incomplete beta function (modified Lentz)."""
    tiny, c, d = 1e-300, 1.0, 1.0 - (a + b) * x / (a + 1.0)
    d = 1.0 / (d if abs(d) > tiny else tiny)
    h = d
    for m in range(1, 300):
        for num in (m * (b - m) * x / ((a + 2 * m - 1) * (a + 2 * m)),
                    -(a + m) * (a + b + m) * x / ((a + 2 * m) * (a + 2 * m + 1))):  # fmt: skip
            d = 1.0 + num * d
            d = 1.0 / (d if abs(d) > tiny else tiny)
            c = 1.0 + num / c
            c = c if abs(c) > tiny else tiny
            h *= d * c
        if abs(d * c - 1.0) < 1e-14:
            break
    return h


def betainc(a: float, b: float, x: float) -> float:
    """Regularized incomplete beta I_x(a, b)."""
    if x <= 0.0 or x >= 1.0:
        return float(x >= 1.0)
    log_front = math.lgamma(a + b) - math.lgamma(a) - math.lgamma(b) + a * math.log(x) + b * math.log1p(-x)
    if x < (a + 1.0) / (a + b + 2.0):
        return math.exp(log_front) * _betacf(a, b, x) / a
    return 1.0 - math.exp(log_front) * _betacf(b, a, 1.0 - x) / b


def fisher_p(a: int, n_a: int, b: int, n_b: int) -> float:
    """Two-sided p-value of Fisher's exact test that a of n_a and b of n_b are draws of one rate: the chance,
    with the margins fixed, of a table no likelier than the one seen (hypergeometric, small counts)."""
    k, n = a + b, n_a + n_b

    def prob(x):
        return math.comb(n_a, x) * math.comb(n_b, k - x) / math.comb(n, k)

    seen = prob(a)
    return min(1.0, sum(prob(x) for x in range(max(0, k - n_b), min(k, n_a) + 1) if prob(x) <= seen * (1 + 1e-9)))


def welch_p(x: np.ndarray, y: np.ndarray) -> float:
    """Two-sided p-value of Welch's t-test for equal means (nan with fewer than 2 samples a side)."""
    if len(x) < 2 or len(y) < 2:
        return math.nan
    vx, vy = np.var(x, ddof=1) / len(x), np.var(y, ddof=1) / len(y)
    if vx + vy == 0:
        return 1.0 if np.mean(x) == np.mean(y) else 0.0
    t = (np.mean(x) - np.mean(y)) / math.sqrt(vx + vy)
    df = (vx + vy) ** 2 / (vx**2 / (len(x) - 1) + vy**2 / (len(y) - 1))
    return betainc(df / 2, 0.5, df / (df + t * t))


# ------------------------------------------------------------------------------------------------
# Figures
# ------------------------------------------------------------------------------------------------
def band(ax, x, values, label, color):
    mean, std = values.mean(0), values.std(0)
    ax.plot(x, mean, label=label, color=color)
    ax.fill_between(x, mean - std, mean + std, color=color, alpha=0.2, linewidth=0)


def save(fig, out: Path, name: str):
    """PNG and PDF, each written then renamed."""
    for ext in ("png", "pdf"):
        tmp = out / f".{name}.tmp.{ext}"
        fig.savefig(tmp, dpi=150, bbox_inches="tight")
        os.replace(tmp, out / f"{name}.{ext}")


def plot_global(plt, conditions: dict, reference: str | None, alpha: float, out: Path):
    fig, ax = plt.subplots(figsize=(7, 4.5))
    colors = dict(zip(conditions, plt.rcParams["axes.prop_cycle"].by_key()["color"] * 4, strict=False))
    for name, runs in conditions.items():
        band(ax, stack(runs, "segments")[0], stack(runs, "global_sr"), f"{name} ({len(runs)} seeds)", colors[name])
    if reference:  # stars above the curves where a condition differs from the reference
        ref = stack(conditions[reference], "global_sr")
        for k, (name, runs) in enumerate(c for c in conditions.items() if c[0] != reference):
            sr = stack(runs, "global_sr")
            n = min(sr.shape[1], ref.shape[1])
            p = np.array([welch_p(sr[:, e], ref[:, e]) for e in range(n)])
            x = stack(runs, "segments")[0][:n][p < alpha]
            ax.scatter(x, np.full(len(x), 1.03 + 0.03 * k), marker="*", color=colors[name], s=25, clip_on=False)
        ax.set_title(f"stars: Welch's t-test against {reference}, p < {alpha}", fontsize=9, pad=8 + 8 * len(conditions))
    ax.set(xlabel="episodes (40-step segments, all workers)", ylabel="global success rate", ylim=(0, 1))
    ax.legend(loc="lower right", fontsize=8)
    ax.grid(alpha=0.3)
    save(fig, out, "global_sr")
    plt.close(fig)


def panels(plt, n: int, title: str):
    cols = min(4, n)
    rows = math.ceil(n / cols)
    fig, axes = plt.subplots(rows, cols, figsize=(3.4 * cols, 2.6 * rows), squeeze=False, sharex=True)
    for ax in axes.flat[n:]:
        ax.set_visible(False)
    fig.suptitle(title)
    return fig, axes.flat


def plot_per_class(plt, conditions: dict, out: Path, column: str = "sr", name: str = "sr_per_class"):
    """One panel per class: `column`_{class} over episodes, mean +- std over seeds per condition. "sr": the
    success rate; "agent_nodes": the class's configs discovered (agent-graph nodes), out of the class's size."""
    names = class_names(next(iter(conditions.values())))
    sizes = {k: len(v) for k, v in og.evaluation_classes(int(next(iter(conditions.values()))[0]["n_blocks"])).items()}
    what = dict(sr="success rate", agent_nodes="configurations discovered (agent-graph nodes)")[column]
    fig, axes = panels(plt, len(names), f"{what} per class (mean +- std over seeds)")
    colors = plt.rcParams["axes.prop_cycle"].by_key()["color"] * 4
    for ax, cls in zip(axes, names, strict=False):
        for color, (label, runs) in zip(colors, conditions.items(), strict=False):
            band(ax, stack(runs, "segments")[0], stack(runs, f"{column}_{cls}"), label, color)
        top = 1 if column == "sr" else sizes[cls]
        ax.set(title=cls if column == "sr" else f"{cls} (of {top})", ylim=(-0.02 * top, 1.02 * top))
        ax.grid(alpha=0.3)
    axes[0].legend(fontsize=7)
    fig.supxlabel("episodes")
    fig.tight_layout()
    save(fig, out, name)
    plt.close(fig)


def has_social_partner(runs: list[dict]) -> bool:
    return any(k.startswith("sp_frontier_") and r[k].sum() > 0 for r in runs for k in r)


def plot_social(plt, conditions: dict, out: Path):
    """Per class, over time: the share of the social partner's proposals (frontier and beyond) that fall
    in the class, the share of the class's configs the agent has met, and its success rate."""
    social = {k: v for k, v in conditions.items() if has_social_partner(v)}
    if not social:
        return False
    name, runs = next(iter(social.items()))
    names = class_names(runs)
    sizes = {k: len(v) for k, v in og.evaluation_classes(int(runs[0]["n_blocks"])).items()}
    proposals = {k: stack(runs, f"sp_frontier_{k}") + stack(runs, f"sp_beyond_{k}") for k in [*names, "other"]}
    total = np.maximum(sum(proposals.values()), 1)
    fig, axes = panels(plt, len(names), f"{name}: social partner proposals, agent encounters and SR per class")
    x = stack(runs, "segments")[0]
    for ax, cls in zip(axes, names, strict=False):
        ax.plot(x, (proposals[cls] / total).mean(0), color="tab:orange", label="share of SP proposals")
        ax.plot(
            x, stack(runs, f"encounters_{cls}").mean(0) / sizes[cls], color="tab:green", label="share of configs met"
        )
        ax.plot(x, stack(runs, f"sr_{cls}").mean(0), color="tab:blue", label="success rate")
        ax.set(title=cls, ylim=(-0.02, 1.02))
        ax.grid(alpha=0.3)
    fig.legend(*axes[0].get_legend_handles_labels(), loc="upper center", bbox_to_anchor=(0.5, 0), ncol=3)
    fig.supxlabel("episodes")
    fig.tight_layout()
    save(fig, out, "sp_per_class")
    plt.close(fig)

    fig, ax = plt.subplots(figsize=(6, 4))
    for name, runs in social.items():
        band(ax, stack(runs, "segments")[0], stack(runs, "stepping_stones"), name, None)
    ax.set(xlabel="episodes", ylabel="stepping stones left", title="stepping stones over time")
    ax.legend(fontsize=8)
    ax.grid(alpha=0.3)
    save(fig, out, "stepping_stones")
    plt.close(fig)
    return True


def has_discoveries(conditions: dict) -> bool:
    """Whether the runs log the agent graph's nodes per class (progress.csv's agent_nodes_{class})."""
    return all(f"agent_nodes_{c}" in r for runs in conditions.values() for r in runs for c in class_names([r]))


def plot_discoveries(plt, conditions: dict, out: Path):
    """Per class, the class's configs that are agent-graph nodes (discovered: met at the start or the end of a
    training segment whose end is stable, SPEC §6) over time, mean +- std over seeds; and the graph's size."""
    plot_per_class(plt, conditions, out, "agent_nodes", "discovered_per_class")
    colors = plt.rcParams["axes.prop_cycle"].by_key()["color"] * 4
    fig, ax = plt.subplots(figsize=(6, 4))
    for color, (name, runs) in zip(colors, conditions.items(), strict=False):
        band(ax, stack(runs, "segments")[0], stack(runs, "agent_nodes"), f"{name} ({len(runs)} seeds)", color)
    ax.set(xlabel="episodes", ylabel="agent-graph nodes", title="the agent's semantic graph", yscale="log")
    ax.legend(fontsize=8)
    ax.grid(alpha=0.3)
    save(fig, out, "agent_nodes")
    plt.close(fig)


# The hard classes: those the paper's agent, held fixed, discovers seldom or never without the partner
# (docs/results.md, "What the partner opens: 5 blocks, the paper's agent").
HARD = ("S3", "S2&S2", "S2&S3", "P3&S2", "S4", "S5")


def social_cycles(run: dict) -> np.ndarray:
    """Social cycles per epoch (every worker's): the social share of the epoch's cycles, whose count is its
    segments over a cycle's (config.json's n_segments; 10, the default, if the file does not say)."""
    cycles = np.diff(run["segments"], prepend=0.0) / run.get("n_segments", 10)
    return np.rint(run["social_share"] * cycles)


def hard_discovered(run: dict) -> np.ndarray:
    """Hard-class configurations discovered (agent-graph nodes), by epoch."""
    return sum(run[f"agent_nodes_{c}"] for c in HARD if f"agent_nodes_{c}" in run)


def plot_help_vs_discovery(plt, conditions: dict, out: Path):
    """Help against discovery: one point per run, x = social cycles in the run (symmetric log scale: 0 is
    shown), y = hard-class configurations discovered by its last epoch; a marker per condition."""
    markers = "osD^vP*Xh<>"
    fig, ax = plt.subplots(figsize=(6.5, 4.5))
    for marker, (name, runs) in zip(markers * 4, conditions.items(), strict=False):
        x = [np.nansum(social_cycles(r)) for r in runs]
        y = [hard_discovered(r)[-1] for r in runs]
        ax.scatter(x, y, marker=marker, s=45, alpha=0.7, label=f"{name} ({len(runs)} seed{'s' * (len(runs) > 1)})")
    ax.set_xscale("symlog", linthresh=1)
    ax.set_xlim(left=-0.3)
    top = sum(len(v) for k, v in og.evaluation_classes(int(runs[0]["n_blocks"])).items() if k in HARD)
    ax.axhline(top, color="grey", lw=0.8, ls="--")
    ax.set(xlabel="social cycles in the run", ylabel=f"hard-class configs discovered (of {top})",
           title="help vs discovery: " + ", ".join(c for c in HARD))  # fmt: skip
    ax.legend(fontsize=8, loc="upper left", bbox_to_anchor=(1.02, 1))  # beside the axes: points fill them
    ax.grid(alpha=0.3)
    save(fig, out, "help_vs_discovery")
    plt.close(fig)


SIDES = ("frontier", "beyond")  # the partner's two proposals of a social cycle (SPEC §7)


def proposal_rates(run: dict) -> np.ndarray | None:
    """The partner's proposals per social cycle over the whole run, (2, classes + "other"): frontier, beyond.
    Only epochs that log both the proposals and the social share count (a resumed older run's are nan); None
    for a run without the sp_* columns or without a social cycle."""
    kinds = [*class_names([run]), "other"]
    if "social_share" not in run or any(f"sp_{side}_{k}" not in run for side in SIDES for k in kinds):
        return None
    proposed = np.array([[run[f"sp_{side}_{k}"] for k in kinds] for side in SIDES])  # (2, kinds, epochs)
    cycles = social_cycles(run)
    logged = np.isfinite(cycles) & np.isfinite(proposed).all((0, 1))
    total = cycles[logged].sum()
    return proposed[..., logged].sum(-1) / total if total > 0 else None


def proposal_rates_by_condition(conditions: dict) -> dict[str, np.ndarray]:
    """(runs, 2, classes + "other") per condition, of its runs with social cycles; conditions without any left out."""
    rates = {name: [x for r in runs if (x := proposal_rates(r)) is not None] for name, runs in conditions.items()}
    return {name: np.array(x) for name, x in rates.items() if x}


def plot_proposals_per_social_cycle(plt, conditions: dict, out: Path) -> bool:
    """Per class, the partner's beyond (top) and frontier (bottom) proposals per social cycle, one bar per
    condition (mean over its runs with social cycles, whiskers min-max): whether an arm moved which goals
    the partner proposed, not how many. Log scale where the bars span two orders of magnitude or more."""
    rates = proposal_rates_by_condition(conditions)
    if not rates:
        return False
    kinds = [*class_names(next(iter(conditions.values()))), "other"]
    colors = dict(zip(conditions, plt.rcParams["axes.prop_cycle"].by_key()["color"] * 4, strict=False))
    x, width = np.arange(len(kinds)), 0.8 / len(rates)
    fig, axes = plt.subplots(2, 1, figsize=(max(9.5, 0.25 * len(kinds) * (len(rates) + 1)), 6.5), sharex=True)
    for ax, side in zip(axes, (1, 0), strict=True):
        for i, (name, r) in enumerate(rates.items()):
            mean, low, high = r[:, side].mean(0), r[:, side].min(0), r[:, side].max(0)
            used = f" ({len(r)} of {len(conditions[name])} runs)" if len(r) < len(conditions[name]) else ""
            ax.bar(x + (i - (len(rates) - 1) / 2) * width, mean, width, yerr=(mean - low, high - mean),
                   color=colors[name], capsize=2, error_kw=dict(lw=0.8), label=f"{name}{used}")  # fmt: skip
        shown = np.concatenate([r[:, side].mean(0) for r in rates.values()])
        if (shown > 0).any() and shown.max() >= 100 * shown[shown > 0].min():
            ax.set_yscale("log")
        ax.set(ylabel=f"{SIDES[side]} proposals\nper social cycle")
        ax.grid(alpha=0.3, axis="y")
    axes[1].set_xticks(x, kinds)
    axes[0].set_title("the social partner's proposals per social cycle, per class (mean, min-max over runs)")
    axes[0].legend(fontsize=8, loc="upper left", bbox_to_anchor=(1.01, 1))
    fig.tight_layout()
    save(fig, out, "proposals_per_social_cycle")
    plt.close(fig)
    return True


# ------------------------------------------------------------------------------------------------
# Tables (Markdown, for docs/results.md)
# ------------------------------------------------------------------------------------------------
def run_label(name: str, run: dict) -> str:
    return f"{name} seed {int(run['seed'])}" if "seed" in run else name


def md_table(header: list[str], rows: list[list[str]]) -> str:
    lines = [header, ["---"] * len(header), *rows]
    return "\n".join("| " + " | ".join(map(str, line)) + " |" for line in lines)


def epochs_to_show(n: int, count: int = 8) -> list[int]:
    """About `count` evenly spaced epochs, the last one included."""
    return sorted({round(i * (n - 1) / (count - 1)) for i in range(count)}) if n > 1 else [0]


def first_at(values: np.ndarray, level: float = 0.5, at: np.ndarray | None = None) -> str:
    """The first epoch at `level` or more (`at`: that epoch's entry of it, as hours), or how far short the run
    stayed."""
    hit = np.flatnonzero(values >= level)
    if not len(hit):
        return f"never (max {values.max():.2f})"
    return str(int(hit[0])) if at is None else f"{at[hit[0]]:.2f} h"


def tables(conditions: dict, reference: str | None = None) -> str:
    """SR per class by epoch (mean over seeds, then each seed), the first epoch at 0.5 per run, the
    distinct configs met by epoch per run (of the stacks and pyramids), and per run with a
    social partner its proposals per class (frontier + beyond, summed over the run) and what the agent
    reached of them; where the runs log them, the configurations discovered per class (discovery_tables)."""
    names = class_names(next(iter(conditions.values())))
    n = min(len(r["global_sr"]) for runs in conditions.values() for r in runs)
    shown = epochs_to_show(n)
    per_epoch = sorted({int(r["segments"][0]) for runs in conditions.values() for r in runs})
    differ = " (they differ between runs)" if len(per_epoch) > 1 else ""
    out = [f"SR per class by epoch, mean over seeds (each seed), epochs of {'/'.join(map(str, per_epoch))} "
           f"segments{differ}:\n"]  # fmt: skip
    rows = []
    for cls in names:
        for name, runs in conditions.items():
            sr = stack(runs, f"sr_{cls}")
            cells = [f"{sr[:, e].mean():.2f} ({', '.join(f'{v:.2f}' for v in sr[:, e])})" for e in shown]
            rows.append([cls, name, *cells])
    out.append(md_table(["class", "condition", *(f"epoch {e}" for e in shown)], rows))

    labelled = [(run_label(name, r), r) for name, runs in conditions.items() for r in runs]
    out.append(f"\nFirst epoch at SR 0.5 or more (epochs 0-{n - 1}):\n")
    out.append(md_table(["class", *(lab for lab, _ in labelled)],
                        [[cls, *(first_at(r[f"sr_{cls}"][:n]) for _, r in labelled)] for cls in names]))  # fmt: skip

    if all("time_eval" in r for _, r in labelled):
        out.append(hours_tables(labelled, names))
    built = [c for c in names if not c.startswith("C")]  # stacks and pyramids: the constructions
    if all("time_eval" in r and "agent_nodes_C1" in r for _, r in labelled):
        out.append(practice_tables(labelled, built))

    sizes = {k: len(v) for k, v in og.evaluation_classes(int(labelled[0][1]["n_blocks"])).items()}
    out.append(f"\nDistinct configs met by epoch ({' / '.join(f'{c} of {sizes[c]}' for c in built)}):\n")
    out.append(md_table(["run", *(f"epoch {e}" for e in shown)],
                        [[lab, *("/".join(str(int(r[f"encounters_{c}"][e])) for c in built) for e in shown)]
                         for lab, r in labelled]))  # fmt: skip

    social = [(lab, r) for lab, r in labelled if any(k.startswith("sp_frontier_") and r[k][:n].sum() > 0 for k in r)]
    if social:
        kinds = [*names, "other"]
        out.append(f"\nThe social partner's proposals over epochs 0-{n - 1} (frontier + beyond), social and"
                   " rehearsal cycles, internalized pairs at the end:\n")  # fmt: skip

        def proposed(r, k):
            return f"{int(r[f'sp_frontier_{k}'][:n].sum())} + {int(r[f'sp_beyond_{k}'][:n].sum())}"

        rows = [[lab, *(proposed(r, k) for k in kinds), f"{r['social_share'][:n].mean():.2f}",
                 f"{r['rehearsal_share'][:n].mean():.2f}", str(int(r["internalized_pairs"][n - 1]))]
                for lab, r in social]  # fmt: skip
        out.append(md_table(["run", *kinds, "social share", "rehearsal share", "internalized pairs"], rows))
        if all(f"sp_frontier_arrived_{k}" in r for _, r in social for k in kinds):
            out.append(f"\nWhat the agent reached of them over epochs 0-{n - 1}: frontier arrivals (at the proposed "
                       "stepping stone) + beyond goals reached:\n")  # fmt: skip

            def reached(r, k):
                arrived, beyond = (
                    int(r[f"sp_{kind}_{k}"][:n].sum()) for kind in ("frontier_arrived", "beyond_reached")
                )
                return f"{arrived} + {beyond}"

            out.append(md_table(["run", *kinds], [[lab, *(reached(r, k) for k in kinds)] for lab, r in social]))
    rates = proposal_rates_by_condition(conditions)
    if rates:
        used = [f"{c}: {len(r)} of {len(conditions[c])} runs" for c, r in rates.items()]
        out.append("\nThe social partner's proposals per social cycle over each whole run (its proposals / its social "
                   "cycles), beyond, then frontier, mean over the condition's runs with social cycles "
                   f"({', '.join(used)}; min-max over them):\n")  # fmt: skip

        def rate(r, side, k):
            v = r[:, side, k]
            return f"{v.mean():.3g}" + (f" ({v.min():.3g}-{v.max():.3g})" if v.min() < v.max() else "")

        kinds = [*names, "other"]
        out.append(md_table(["class", *(f"{c}, {SIDES[side]}" for side in (1, 0) for c in rates)],
                            [[k, *(rate(r, side, i) for side in (1, 0) for r in rates.values())]
                             for i, k in enumerate(kinds)]))  # fmt: skip
    if has_discoveries(conditions):
        out.append(discovery_tables(conditions, labelled, names, sizes, shown, n, reference))
    return "\n".join(out) + "\n"


def hours_tables(labelled: list, names: list[str]) -> str:
    """Per run, the first hour of its own time (own_hours) at which each class's SR reaches 0.5 and 0.8; its
    hours, epochs (an hour), segments, the critic's loss (mean of its last 5 epochs) at its end, and its SR over its
    hours (mean_sr_by_time), the close classes' and all classes': less noisy than a first hour, which one
    evaluation of 24 goals a class decides."""
    out = ["\nFirst hour of each run's own time (its epochs' wall seconds) at SR 0.5, then at 0.8:\n"]
    rows = [[cls, *(" / ".join(first_at(r[f"sr_{cls}"], level, own_hours(r)) for level in (0.5, 0.8))
                    for _, r in labelled)] for cls in names]  # fmt: skip
    out.append(md_table(["class", *(lab for lab, _ in labelled)], rows))
    out.append("\nAt each run's end:\n")
    close = [c for c in names if c.startswith("C")]
    rows = [[lab, f"{own_hours(r)[-1]:.2f}", str(len(r["epoch"])), f"{len(r['epoch']) / own_hours(r)[-1]:.1f}",
             f"{int(r['segments'][-1]):,}", loss_text(r["critic_loss"][-5:]),
             *(f"{mean_sr_by_time(r, classes):.3f}" for classes in (close, names))] for lab, r in labelled]  # fmt: skip
    out.append(md_table(["run", "own hours", "epochs", "epochs an hour", "segments", "critic loss (last 5 epochs)",
                         f"mean SR over its hours, {'-'.join((close[0], close[-1]))}", "mean SR, all classes"],
                        rows))  # fmt: skip
    return "\n".join(out)


def mean_sr_by_time(run: dict, classes: list[str]) -> float:
    """The classes' mean SR averaged over the run's own time: each epoch's evaluation weighted by the epoch's
    hours (own_hours), the area under its SR curve by the hour over its hours, so that runs of different epoch
    lengths compare at equal time."""
    seconds = np.diff(own_hours(run), prepend=0.0)
    sr = np.mean([run[f"sr_{c}"] for c in classes], axis=0)
    return float(np.sum(sr * seconds) / np.sum(seconds))


def practice_tables(labelled: list, built: list[str]) -> str:
    """Why a construction class comes late, per run and class: the first epoch (and own hour) at which one of its
    configs was met and at which one became an agent-graph node (discovery); the goals of the class the agent
    pursued, its own, the partner's frontier and beyond goals (practice); the share of those it reached in
    training (skill in training); and the evaluation SR, its best and its first hour at 0.5. A count the run does
    not log (a baseline's partner, own goals before they were logged) is '-'."""
    out = ["\nWhy the constructions come late, per run and class: first epoch (own hour) a config was met, first "
           "epoch one was a graph node; goals pursued over the run, the agent's own + the partner's frontier + "
           "beyond, and the share reached in training of each; the evaluation SR's best and its first hour at "
           "0.5:\n"]  # fmt: skip

    def first(values, hours):
        hit = np.flatnonzero(values > 0)
        return f"{int(hit[0])} ({hours[hit[0]]:.2f} h)" if len(hit) else "never"

    def count(v):
        return "-" if np.isnan(v).all() else str(int(np.nansum(v)))

    def share(reached, pursued):
        return f"{np.nansum(reached) / np.nansum(pursued):.2f}" if np.nansum(pursued) else "-"

    rows = []
    for cls in built:
        for lab, r in labelled:
            h, none = own_hours(r), np.full(len(r["epoch"]), np.nan)
            pursued = [r.get(f"{k}_{cls}", none) for k in ("own", "sp_frontier", "sp_beyond")]
            reached = [r.get(f"{k}_{cls}", none) for k in ("own_reached", "sp_frontier_arrived", "sp_beyond_reached")]
            rows.append([cls, lab, first(r[f"encounters_{cls}"], h), first(r[f"agent_nodes_{cls}"], h),
                         " + ".join(count(v) for v in pursued),
                         " / ".join(share(a, b) for a, b in zip(reached, pursued, strict=True)),
                         f"{r[f'sr_{cls}'].max():.2f}", first_at(r[f"sr_{cls}"], 0.5, h)])  # fmt: skip
    out.append(md_table(["class", "run", "first met", "first node", "pursued (own + frontier + beyond)",
                         "reached in training", "SR best", "SR 0.5 at"], rows))  # fmt: skip
    return "\n".join(out)


def loss_text(losses: np.ndarray) -> str:
    """The mean of the losses logged (nan: an epoch without update), or that no update ran."""
    return f"{np.nanmean(losses):.3g}" if np.isfinite(losses).any() else "no update"


def plot_per_class_by_hour(plt, conditions: dict, out: Path):
    """One panel per class: each run's SR over its own hours (own_hours), a line per run, a color per condition."""
    names = class_names(next(iter(conditions.values())))
    fig, axes = panels(plt, len(names), "success rate per class over each run's own hours (a line per seed)")
    colors = plt.rcParams["axes.prop_cycle"].by_key()["color"] * 4
    for ax, cls in zip(axes, names, strict=False):
        for color, (label, runs) in zip(colors, conditions.items(), strict=False):
            for k, r in enumerate(runs):
                ax.plot(own_hours(r), r[f"sr_{cls}"], color=color, alpha=0.8, label=label if k == 0 else None)
        ax.set(title=cls, ylim=(-0.02, 1.02))
        ax.grid(alpha=0.3)
    axes[0].legend(fontsize=7)
    fig.supxlabel("hours of the run's own time")
    fig.tight_layout()
    save(fig, out, "sr_per_class_by_hour")
    plt.close(fig)


def discovery_tables(
    conditions: dict, labelled: list, names: list, sizes: dict, shown: list, n: int, reference: str | None
) -> str:
    """Configurations discovered (agent-graph nodes) per class: by epoch, the first epoch with one, and at the
    end, each condition against the reference (Welch's t-test)."""
    out = ["\nConfigurations discovered per class (agent-graph nodes, SPEC §6: a config met at the start or the end "
           "of a training segment whose end is stable, with its block permutations), mean over seeds (each "
           "seed):\n"]  # fmt: skip
    rows = []
    for cls in names:
        for name, runs in conditions.items():
            found = stack(runs, f"agent_nodes_{cls}")[:, :n]
            cells = [f"{found[:, e].mean():.1f} ({', '.join(f'{v:.0f}' for v in found[:, e])})" for e in shown]
            rows.append([f"{cls} (of {sizes[cls]})", name, *cells])
    out.append(md_table(["class", "condition", *(f"epoch {e}" for e in shown)], rows))

    def first_found(r, cls):
        found = np.flatnonzero(r[f"agent_nodes_{cls}"][:n] > 0)
        return str(int(found[0])) if len(found) else "never"

    out.append(f"\nFirst epoch at whose end the class has a discovered configuration (epochs 0-{n - 1}):\n")
    out.append(md_table(["run", *names], [[lab, *(first_found(r, c) for c in names)] for lab, r in labelled]))

    hard = [c for c in HARD if c in names]
    out.append(f"\nHelp and discovery per run (epochs 0-{n - 1}): social cycles, the learner's queries and its help "
               "cycles in which the partner had nothing to propose (where logged), hard-class configurations "
               "discovered at the end; per hard class, the first epoch with a discovered configuration and the "
               "social cycles up to its end, \"epoch (social cycles)\", — if never:\n")  # fmt: skip

    def first_help(r, cls):
        found = np.flatnonzero(r[f"agent_nodes_{cls}"][:n] > 0)
        return f"{int(found[0])} ({int(np.nansum(social_cycles(r)[: found[0] + 1]))})" if len(found) else "—"

    def logged(r, k):
        return str(int(np.nansum(r[k][:n]))) if k in r else "-"

    rows = [[lab, str(int(np.nansum(social_cycles(r)[:n]))), logged(r, "queries"), logged(r, "help_nothing"),
             str(int(hard_discovered(r)[n - 1])), *(first_help(r, c) for c in hard)]
            for lab, r in labelled]  # fmt: skip
    out.append(md_table(["run", "social cycles", "queries", "help, nothing proposed", "hard configs", *hard], rows))

    ref = reference if reference in conditions else next(iter(conditions))
    others = [c for c in conditions if c != ref]
    out.append(f"\nDiscovered at epoch {n - 1}, mean +- std over seeds (seeds with any); against {ref}: Welch's "
               "t-test on the counts (undefined where no condition's seeds vary), Fisher's exact test on the seeds "
               "with any (p):\n")  # fmt: skip
    rows = []
    for cls in names:
        final = {c: stack(runs, f"agent_nodes_{cls}")[:, n - 1] for c, runs in conditions.items()}
        cells = [f"{v.mean():.1f} +- {v.std(ddof=1) if len(v) > 1 else 0:.1f} ({(v > 0).sum()}/{len(v)})"
                 for v in final.values()]  # fmt: skip
        welch = [welch_p(final[c], final[ref]) if np.var(final[c]) + np.var(final[ref]) > 0 else math.nan
                 for c in others]  # fmt: skip
        fisher = [
            fisher_p((final[c] > 0).sum(), len(final[c]), (final[ref] > 0).sum(), len(final[ref])) for c in others
        ]
        rows.append([f"{cls} (of {sizes[cls]})", *cells, *(f"{p:.3g}" if p == p else "undefined" for p in welch),
                     *(f"{p:.3g}" for p in fisher)])  # fmt: skip
    out.append(md_table(["class", *conditions, *(f"Welch p, {c}" for c in others), *(f"Fisher p, {c}" for c in others)],
                        rows))  # fmt: skip
    return "\n".join(out)


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument(
        "--condition", nargs="+", action="append", required=True, metavar=("NAME", "RUN_DIR"),
        help="a condition's name, then its run folders (one per seed); repeat it for each condition",
    )  # fmt: skip
    parser.add_argument("--reference", default=None, help="condition the others are tested against (Welch)")
    parser.add_argument("--alpha", type=float, default=0.05, help="significance level of the stars")
    parser.add_argument("--out", default="figures", help="folder for the PNG and PDF files")
    parser.add_argument("--epochs", type=int, default=0, help="only the first N epochs of every run (0: all)")
    parser.add_argument("--hours", type=float, default=0,
                        help="only the epochs that end within H hours of each run's own time (0: all)")  # fmt: skip
    args = parser.parse_args(argv)
    if args.epochs < 0:
        parser.error(f"--epochs must be 0 (all) or positive, got {args.epochs}")
    if not (math.isfinite(args.hours) and args.hours >= 0):
        parser.error(f"--hours must be 0 (all) or positive, got {args.hours}")
    conditions = {}
    for name, *folders in args.condition:
        if not folders:
            parser.error(f"--condition {name!r} lists no run folder")
        if name in conditions:
            parser.error(f"--condition {name!r} is given twice")
        try:
            conditions[name] = [first_hours(first_epochs(read_run(Path(f)), args.epochs), args.hours, f)
                                for f in folders]  # fmt: skip
        except ValueError as e:
            parser.error(str(e))  # exit code 2, one line naming the file
    blocks = {int(r["n_blocks"]) for runs in conditions.values() for r in runs}
    if len(blocks) > 1:  # the classes, and so the panels and table rows, differ with the block count
        parser.error(f"the runs differ in their number of blocks ({', '.join(map(str, sorted(blocks)))})")
    if args.reference is not None and args.reference not in conditions:
        parser.error(f"--reference {args.reference!r} is not one of the conditions: {', '.join(conditions)}")
    if not 0 < args.alpha < 1:
        parser.error(f"--alpha must be in (0, 1), got {args.alpha}")
    import matplotlib  # noqa: PLC0415 (after argument checks: a bad command line fails fast)

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt  # noqa: PLC0415

    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    plot_global(plt, conditions, args.reference, args.alpha, out)
    plot_per_class(plt, conditions, out)
    social = plot_social(plt, conditions, out)
    made = ["global_sr", "sr_per_class"] + (["sp_per_class", "stepping_stones"] if social else [])
    if all("time_eval" in r for runs in conditions.values() for r in runs):
        plot_per_class_by_hour(plt, conditions, out)
        made.append("sr_per_class_by_hour")
    if has_discoveries(conditions):
        plot_discoveries(plt, conditions, out)
        made += ["discovered_per_class", "agent_nodes"]
        if all("social_share" in r for runs in conditions.values() for r in runs):
            plot_help_vs_discovery(plt, conditions, out)
            made.append("help_vs_discovery")
    if plot_proposals_per_social_cycle(plt, conditions, out):
        made.append("proposals_per_social_cycle")
    tmp = out / ".tables.tmp.md"
    tmp.write_text(tables(conditions, args.reference))
    os.replace(tmp, out / "tables.md")
    print(f"wrote {', '.join(f'{m}.png/.pdf' for m in made)} and tables.md to {out}/")
    return 0


if __name__ == "__main__":
    sys.exit(main())
