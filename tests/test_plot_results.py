"""plot_results.py: the paper's figures from run folders, and its Welch's t-test."""

import csv
import json
import math
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

import oracle_graph as og
import plot_results as pr

ROOT = Path(__file__).resolve().parent.parent


def fake_run(folder: Path, seed: int, level: float, social: bool, epochs: int = 12, blocks: int = 3,
             noise: float = 0.02, seconds: tuple[float, float, float] | None = None):  # fmt: skip
    """A run folder with a progress.csv shaped like gangstr_hme.py's (3 blocks unless told); `seconds`: each
    epoch's collecting, updating and evaluating seconds, logged as its time columns."""
    rng = np.random.default_rng(seed)
    classes = list(og.evaluation_classes(blocks))
    folder.mkdir(parents=True)
    (folder / "config.json").write_text(json.dumps({"n_blocks": blocks, "seed": seed}))
    rows = []
    for e in range(epochs):
        sr = {c: float(np.clip(level * e / epochs + rng.normal(0, noise), 0, 1)) for c in classes}
        row = dict(epoch=e, segments=500 * (e + 1), global_sr=np.mean(list(sr.values())))
        row |= {f"sr_{c}": v for c, v in sr.items()}
        row |= {f"encounters_{c}": min(e, 3) for c in classes}
        for kind in ("frontier", "beyond"):
            row |= {f"sp_{kind}_{c}": int(social) * int(rng.integers(0, 9)) for c in [*classes, "other"]}
        row["stepping_stones"] = max(0, 30 - 3 * e) if social else 0
        row |= dict(social_share=0.2 * social, rehearsal_share=0.4 * social, internalized_pairs=e * social)
        if seconds:
            row |= dict(zip(("time_collect", "time_update", "time_eval"), seconds, strict=True), critic_loss=e)
        rows.append(row)
    write_rows(folder, rows)
    return folder


def write_rows(folder: Path, rows: list[dict]):
    """rows as the run folder's progress.csv."""
    with (folder / "progress.csv").open("w", newline="") as f:
        w = csv.DictWriter(f, fieldnames=list(rows[0]))
        w.writeheader()
        w.writerows(rows)


@pytest.fixture
def figures_not_rendered(monkeypatch) -> list[str]:
    """For a test of the tables: each figure is built, not rendered to PNG and PDF (a second or more a figure,
    most of plot_results.py's time); the names it would be saved under, in order. The tests of the figures
    themselves (written as PNG and PDF, the committed runs) render them."""
    names = []
    monkeypatch.setattr(pr, "save", lambda fig, out, name: names.append(name))
    return names


def test_plots_are_written_as_png_and_pdf_for_several_conditions_and_seeds(tmp_path):
    social = [fake_run(tmp_path / f"sp20_{s}", s, 0.9, True) for s in range(3)]
    alone = [fake_run(tmp_path / f"sp0_{s}", 10 + s, 0.3, False) for s in range(3)]
    out = tmp_path / "figures"
    cmd = [sys.executable, "plot_results.py", "--condition", "SP-20%", *map(str, social),
           "--condition", "SP-0%", *map(str, alone), "--reference", "SP-0%", "--out", str(out)]  # fmt: skip
    proc = subprocess.run(cmd, cwd=ROOT, capture_output=True, text=True, timeout=120)
    assert proc.returncode == 0, proc.stderr
    for name in ("global_sr", "sr_per_class", "sp_per_class", "stepping_stones", "proposals_per_social_cycle"):
        png, pdf = (out / f"{name}.png").read_bytes(), (out / f"{name}.pdf").read_bytes()
        assert png.startswith(b"\x89PNG") and len(png) > 10_000
        assert pdf.startswith(b"%PDF") and len(pdf) > 5_000
    assert not list(out.glob(".*"))  # no temporary files left
    assert (out / "tables.md").read_text().startswith("SR per class by epoch")


def test_tables_give_sr_by_epoch_the_first_epoch_at_half_configs_met_and_proposals(tmp_path):
    social = [pr.read_run(fake_run(tmp_path / f"sp20_{s}", s, 0.5, True)) for s in (1, 2)]
    alone = [pr.read_run(fake_run(tmp_path / f"sp0_{s}", s, 0.5, False)) for s in (1, 2)]
    ramp = np.array([0.0, 0.1, 0.2, 0.3, 0.5, 0.4, 0.6, 0.7, 0.8, 0.9, 0.9, 1.0])
    social[0]["sr_S2"], social[1]["sr_S2"] = ramp, np.roll(ramp, 2) * (np.arange(12) >= 2)  # 0.5 at 4, 6
    alone[0]["sr_S2"], alone[1]["sr_S2"] = ramp * 0.4, ramp * 0.3  # never: at most 0.36, 0.27 in epochs 0-9
    social[0]["encounters_S3"] = np.minimum(np.arange(12), 6)
    social[0]["sp_frontier_P3"], social[0]["sp_beyond_P3"] = np.full(12, 2.0), np.full(12, 3.0)
    alone[1] = {k: v[:10] if isinstance(v, np.ndarray) else v for k, v in alone[1].items()}  # a shorter run
    text = pr.tables({"SP-20%": social, "SP-0%": alone})
    cells = [line.strip("| ").split(" | ") for line in text.splitlines() if line.startswith("| ")]
    rows = {row[0]: row for row in cells}  # the last table's row of each name

    assert "epoch 9 |" in text and "epoch 10" not in text  # cut to the shortest run
    first = {row[0]: row[1:] for row in markdown_table_after(text, "First epoch at SR 0.5")}
    assert first["S2"] == ["4", "6", "never (max 0.36)", "never (max 0.27)"]
    mean_s2 = next(row for row in cells if row[:2] == ["S2", "SP-20%"])
    assert mean_s2[-1] == "0.80 (0.90, 0.70)" and mean_s2[2] == "0.00 (0.00, 0.00)"  # epochs 9 and 0
    assert "(S2 of 6 / S3 of 6 / P3 of 3)" in text
    met = next(row for row in cells if row[0] == "SP-20% seed 1")  # the configs table comes first
    assert met[1].split("/")[1] == "0" and met[-1].split("/")[1] == "6"  # S3 met by epochs 0 and 9
    proposals = rows["SP-20% seed 1"]
    assert proposals[6] == "20 + 30"  # P3 over epochs 0-9: 10 x 2 frontier, 10 x 3 beyond
    assert proposals[-3:] == ["0.20", "0.40", "9"]  # social share, rehearsal share, pairs at epoch 9
    proposal_rows = text.split("The social partner's proposals")[1]
    assert "SP-20% seed 2" in proposal_rows and "SP-0%" not in proposal_rows  # only runs with a partner


def test_without_a_social_partner_only_the_success_figures_are_drawn(tmp_path, figures_not_rendered):
    runs = [fake_run(tmp_path / f"sp0_{s}", s, 0.5, False) for s in range(2)]
    assert pr.main(["--condition", "SP-0%", *map(str, runs), "--out", str(tmp_path / "f")]) == 0
    assert sorted(figures_not_rendered) == ["global_sr", "sr_per_class"]


@pytest.mark.parametrize(
    "argv, named",
    [
        (["--condition", "A", "/nonexistent/run"], "/nonexistent/run"),
        (["--condition", "A"], "'A'"),
        (["--condition", "A", "RUN", "--reference", "B"], "'B'"),
        (["--condition", "A", "RUN", "--alpha", "2"], "2.0"),
        (["--condition", "A", "RUN", "--epochs", "-3"], "-3"),
        (["--condition", "A", "RUN", "--hours", "-1"], "-1.0"),
        (["--condition", "A", "RUN", "--hours", "1"], "logs no time columns"),
    ],
)
def test_bad_arguments_exit_2_naming_the_value(tmp_path, argv, named, capsys):
    fake_run(tmp_path / "run", 0, 0.5, False)
    argv = [str(tmp_path / "run") if a == "RUN" else a for a in argv]
    with pytest.raises(SystemExit) as e:
        pr.main([*argv, "--out", str(tmp_path / "f")])
    assert e.value.code == 2 and named in capsys.readouterr().err


def test_epochs_cuts_every_run_to_its_first_n_epochs_in_figures_and_tables(tmp_path, figures_not_rendered):
    long, short = (
        fake_run(tmp_path / "long", 0, 0.5, False, epochs=12),
        fake_run(tmp_path / "short", 1, 0.9, False, epochs=5),
    )
    pr.main(
        ["--condition", "L", str(long), "--condition", "S", str(short), "--epochs", "4", "--out", str(tmp_path / "f")]
    )
    table = (tmp_path / "f" / "tables.md").read_text()
    assert "epoch 3 |" in table and "epoch 4 |" not in table  # epochs 0-3, of both runs
    pr.main(["--condition", "L", str(long), "--out", str(tmp_path / "all")])
    assert "epoch 11 |" in (tmp_path / "all" / "tables.md").read_text()  # 0: every epoch


def test_hours_cut_each_run_at_its_own_time_and_tables_give_the_first_hour_at_half_and_at_08(
    tmp_path, figures_not_rendered
):
    # every class's SR is epoch / 12; an epoch takes 0.1 h of its run's own time in one run, 0.2 h in the other
    fast = fake_run(tmp_path / "fast", 0, 1.0, False, noise=0, seconds=(200, 100, 60))
    slow = fake_run(tmp_path / "slow", 1, 1.0, False, noise=0, seconds=(400, 200, 120))
    rows = list(csv.DictReader((fast / "progress.csv").open()))
    write_rows(fast, [r | dict(sr_S2=0, sr_S3=0, sr_P3=0) for r in rows])  # the fast run learns no construction
    argv = ["--condition", "F", str(fast), "--condition", "S", str(slow)]
    pr.main([*argv, "--out", str(tmp_path / "all")])
    table = (tmp_path / "all" / "tables.md").read_text()
    assert "| C1 | 0.70 h / 1.10 h | 1.40 h / 2.20 h |" in table  # SR 0.5 at epoch 6, 0.8 at epoch 10
    # its end: hours, epochs (10 an hour), segments, last 5 losses' mean, mean SR over its hours (of 0/12 ... 11/12)
    assert "| F seed 0 | 1.20 | 12 | 10.0 | 6,000 | 9 | 0.458 | 0.229 |" in table  # half its classes at 0
    assert "| S seed 1 | 2.40 | 12 | 5.0 | 6,000 | 9 | 0.458 | 0.458 |" in table
    assert "sr_per_class_by_hour" in figures_not_rendered
    pr.main([*argv, "--hours", "0.6", "--out", str(tmp_path / "cut")])
    table = (tmp_path / "cut" / "tables.md").read_text()
    assert "| F seed 0 | 0.60 | 6 | 10.0 | 3,000 | 3 | 0.208 | 0.104 |" in table  # 0/12 ... 5/12
    assert "| S seed 1 | 0.60 | 3 | 5.0 | 1,500 | 1 | 0.083 |" in table  # 0/12 ... 2/12: less learnt in its hours
    assert "| C1 | never (max 0.42) / never (max 0.42) | never (max 0.17) / never (max 0.17) |" in table
    with pytest.raises(SystemExit) as e:  # within the first epoch: nothing to compare, refused (not every epoch)
        pr.main([*argv, "--hours", "0.15", "--out", str(tmp_path / "none")])
    assert e.value.code == 2 and not (tmp_path / "none").exists()
    assert pr.loss_text(np.full(5, np.nan)) == "no update" and pr.loss_text(np.array([np.nan, 2.0, 4.0])) == "3"


def test_own_hours_are_the_epochs_wall_time_and_before_time_epoch_the_sum_of_the_parts():
    parts = dict(time_collect=np.array([100.0, 100.0, 100.0]), time_update=np.array([200.0, 200.0, 200.0]),
                 time_eval=np.array([60.0, 60.0, 60.0]))  # fmt: skip
    np.testing.assert_allclose(pr.own_hours(parts), np.array([360.0, 720.0, 1080.0]) / 3600)
    resumed = parts | dict(time_epoch=np.array([np.nan, 250.0, 250.0]))  # its first row older than the column
    np.testing.assert_allclose(pr.own_hours(resumed), np.array([360.0, 610.0, 860.0]) / 3600)


def test_mean_sr_by_time_weights_each_evaluation_by_its_epochs_hours():
    # a 300 s epoch at SR 0 then a 100 s epoch at 1 (C1; C2 at 1 then 0): a quarter, three quarters, a half of the time
    run = dict(time_collect=np.zeros(2), time_update=np.zeros(2), time_eval=np.zeros(2),
               time_epoch=np.array([300.0, 100.0]), sr_C1=np.array([0.0, 1.0]), sr_C2=np.array([1.0, 0.0]))  # fmt: skip
    assert pr.mean_sr_by_time(run, ["C1"]) == pytest.approx(0.25)
    assert pr.mean_sr_by_time(run, ["C2"]) == pytest.approx(0.75)
    assert pr.mean_sr_by_time(run, ["C1", "C2"]) == pytest.approx(0.5)


def test_runs_of_different_block_counts_are_refused(tmp_path, capsys):
    three = fake_run(tmp_path / "three", 0, 0.5, False)
    five = fake_run(tmp_path / "five", 1, 0.5, False)
    (five / "config.json").write_text(json.dumps({"n_blocks": 5, "seed": 1}))
    with pytest.raises(SystemExit) as e:
        pr.main(["--condition", "A", str(three), "--condition", "B", str(five), "--out", str(tmp_path / "f")])
    assert e.value.code == 2 and "(3, 5)" in capsys.readouterr().err
    assert not (tmp_path / "f").exists()  # refused before anything is written


def test_regularized_incomplete_beta_matches_closed_forms():
    for x in (0.05, 0.3, 0.5, 0.8, 0.99):
        assert pr.betainc(2.5, 1.0, x) == pytest.approx(x**2.5, rel=1e-10)
        assert pr.betainc(1.0, 3.0, x) == pytest.approx(1 - (1 - x) ** 3, rel=1e-10)
        assert pr.betainc(4.0, 4.0, 0.5) == pytest.approx(0.5, rel=1e-10)


def test_welch_p_value_matches_the_student_t_tail_with_two_degrees_of_freedom():
    # Two samples of two with equal variances: Welch's df is exactly 2, where the two-sided tail of the
    # t distribution is 1 - |t| / sqrt(2 + t^2).
    x, y = np.array([0.0, 2.0]), np.array([1.0, 3.0])
    t = -1 / math.sqrt(2)
    assert pr.welch_p(x, y) == pytest.approx(1 - abs(t) / math.sqrt(2 + t * t), rel=1e-9)
    assert pr.welch_p(np.array([0.1, 0.2, 0.15]), np.array([0.9, 0.95, 0.85])) < 0.01
    assert pr.welch_p(np.array([0.5, 0.6]), np.array([0.5, 0.6])) == pytest.approx(1.0)
    assert math.isnan(pr.welch_p(np.array([0.5]), np.array([0.5, 0.6])))


@pytest.mark.parametrize("n", [2, 4])
def test_welch_degrees_of_freedom_follow_the_unequal_variances(n):
    # y has no spread: Welch's df is (vx + 0)^2 / (vx^2 / (n - 1)) = n - 1, Student's would be n + 2 - 2 = n.
    # Two-sided tails of the t distribution in closed form: df 1, 1 - 2 atan|t| / pi; df 3, 1 - 2 / pi
    # (atan(|t| / sqrt 3) + (|t| / sqrt 3) / (1 + t^2 / 3)).
    x, y = np.arange(n, dtype=float), np.array([5.0, 5.0])
    t = (x.mean() - 5.0) / math.sqrt(x.var(ddof=1) / n)
    s = abs(t) / math.sqrt(3)
    expected = 1 - 2 * math.atan(abs(t)) / math.pi if n == 2 else 1 - 2 / math.pi * (math.atan(s) + s / (1 + s * s))
    assert pr.welch_p(x, y) == pytest.approx(expected, rel=1e-9)


def test_the_committed_social_partner_runs_still_plot_and_tabulate(tmp_path):
    # tests/data/sp_3blocks_sample: the first 30 epochs of the runs in results/sp_3blocks (docs/results.md),
    # so that plot_results.py keeps reading what gangstr_hme.py wrote for them.
    sample = ROOT / "tests" / "data" / "sp_3blocks_sample"
    social, alone = sorted(sample.glob("sp20_seed*")), sorted(sample.glob("sp0_seed*"))
    assert social and alone
    for run in [*social, *alone]:
        full = (ROOT / "results" / "sp_3blocks" / run.name / "progress.csv").read_text().splitlines()
        assert (run / "progress.csv").read_text().splitlines() == full[:31]  # the header and 30 epochs
    out = tmp_path / "figures"
    argv = ["--condition", "SP-20%", *map(str, social), "--condition", "SP-0%", *map(str, alone)]
    assert pr.main([*argv, "--reference", "SP-0%", "--out", str(out)]) == 0
    assert sorted(p.stem for p in out.glob("*.png")) == [
        "global_sr", "proposals_per_social_cycle", "sp_per_class", "sr_per_class", "sr_per_class_by_hour",
        "stepping_stones",
    ]  # fmt: skip
    cells = markdown_table_after((out / "tables.md").read_text(), "First epoch at SR 0.5")
    first = {row[0]: row[1:] for row in cells if row[0] in ("C1", "S2")}
    for cls in ("C1", "S2"):  # the first epoch at SR 0.5, read from the CSV files directly
        for run, cell in zip([*social, *alone], first[cls], strict=True):
            with (run / "progress.csv").open(newline="") as f:
                sr = [float(r[f"sr_{cls}"]) for r in csv.DictReader(f)]
            hits = [e for e, v in enumerate(sr) if v >= 0.5]
            assert cell == (str(hits[0]) if hits else f"never (max {max(sr):.2f})")


def markdown_table_after(text: str, heading: str) -> list[list[str]]:
    """The rows (cells) of the first Markdown table after the line starting with `heading`, its header first."""
    lines = text.splitlines()
    start = next(i for i, line in enumerate(lines) if line.startswith(heading))
    end = next((i for i, line in enumerate(lines[start + 2 :]) if not line.startswith("|")), None)
    table = lines[start + 2 : start + 2 + end] if end is not None else lines[start + 2 :]
    return [line.strip("| ").split(" | ") for line in table if not line.startswith("| ---")]


def test_the_committed_discovery_runs_plot_and_tabulate_what_the_partner_opens(tmp_path):
    # tests/data/discovery_5blocks_sample: the first 10 epochs of two seeds of each arm of results/discovery_5blocks
    # (docs/results.md), so that plot_results.py keeps reading what gangstr_hme.py wrote for them.
    sample = ROOT / "tests" / "data" / "discovery_5blocks_sample"
    arms = {name: sorted(sample.glob(f"{stem}_seed*")) for name, stem in
            (("SP-0", "sp0"), ("SP-0.2%", "sp0.2pct"), ("SP-20%", "sp20"))}  # fmt: skip
    runs = [run for folders in arms.values() for run in folders]
    assert all(len(folders) == 2 for folders in arms.values())
    for run in runs:
        full = (ROOT / "results" / "discovery_5blocks" / run.name / "progress.csv").read_text().splitlines()
        assert (run / "progress.csv").read_text().splitlines() == full[:11]  # the header and 10 epochs
    out = tmp_path / "figures"
    argv = [arg for name, folders in arms.items() for arg in ("--condition", name, *map(str, folders))]
    assert pr.main([*argv, "--reference", "SP-0", "--out", str(out)]) == 0
    # rendered here (the table tests build figures without rendering them: figures_not_rendered)
    assert {"discovered_per_class", "agent_nodes", "help_vs_discovery"} <= {p.stem for p in out.glob("*.png")}
    text = (out / "tables.md").read_text()
    csvs = {}
    for run in runs:
        with (run / "progress.csv").open(newline="") as f:
            csvs[run] = list(csv.DictReader(f))
    classes = list(og.evaluation_classes(5))
    first = markdown_table_after(text, "First epoch at whose end the class has a discovered configuration")
    assert first[0] == ["run", *classes] and len(first) == len(runs) + 1
    for run, row in zip(runs, first[1:], strict=True):  # read from the CSV files directly
        for cls, cell in zip(classes, row[1:], strict=True):
            found = [e for e, r in enumerate(csvs[run]) if int(r[f"agent_nodes_{cls}"]) > 0]
            assert cell == (str(found[0]) if found else "never"), (run.name, cls)
    final = markdown_table_after(text, "Discovered at epoch 9")
    assert final[0] == ["class", *arms, "Welch p, SP-0.2%", "Welch p, SP-20%", "Fisher p, SP-0.2%", "Fisher p, SP-20%"]
    for row in final[1:]:
        cls = row[0].split(" (of ")[0]
        for cell, folders in zip(row[1:4], arms.values(), strict=True):
            values = [int(csvs[run][-1][f"agent_nodes_{cls}"]) for run in folders]
            assert cell.startswith(f"{np.mean(values):.1f} +- "), (cls, cell)
            assert cell.endswith(f" ({sum(v > 0 for v in values)}/2)"), (cls, cell)


def test_help_vs_discovery_counts_each_runs_social_cycles_and_hard_configs(tmp_path, figures_not_rendered):
    sample = ROOT / "tests" / "data" / "discovery_5blocks_sample"
    runs = sorted(sample.glob("sp20_seed*")) + sorted(sample.glob("sp0_seed*"))
    asked = tmp_path / "asked_seed1"  # a run of the learner's query: the same rows, with its columns added
    asked.mkdir()
    (asked / "config.json").write_text((runs[0] / "config.json").read_text())
    with (runs[0] / "progress.csv").open(newline="") as f:
        rows = list(csv.DictReader(f))
    with (asked / "progress.csv").open("w", newline="") as f:
        w = csv.DictWriter(f, fieldnames=[*rows[0], "queries", "help_nothing"])
        w.writeheader()
        w.writerows(r | dict(queries=e % 3, help_nothing=int(e == 4)) for e, r in enumerate(rows))
    out = tmp_path / "figures"
    argv = ["--condition", "SP-20%", *map(str, runs[:2]), "--condition", "SP-0", *map(str, runs[2:])]
    assert pr.main([*argv, "--condition", "asked", str(asked), "--out", str(out)]) == 0
    assert "help_vs_discovery" in figures_not_rendered
    table = markdown_table_after((out / "tables.md").read_text(), "Help and discovery per run")
    assert table[0] == ["run", "social cycles", "queries", "help, nothing proposed", "hard configs", *pr.HARD]
    for run, row in zip([*runs, asked], table[1:], strict=True):
        with (run / "progress.csv").open(newline="") as f:
            csv_rows = list(csv.DictReader(f))
        social = sum(round(float(r["social_share"]) * 50) for r in csv_rows)  # 50 cycles of 10 segments an epoch
        hard = sum(int(csv_rows[-1][f"agent_nodes_{c}"]) for c in pr.HARD)
        assert row[1] == str(social) and row[4] == str(hard), (run.name, row)
        assert row[2:4] == (["9", "1"] if run == asked else ["-", "-"])  # queries 0+1+2+0+1+2+0+1+2+0
        assert int(row[1]) > 0 if "sp20" in run.name or run == asked else row[1] == "0"


def test_fishers_exact_test_matches_the_hypergeometric_tables_of_known_cases():
    assert pr.fisher_p(3, 4, 1, 4) == pytest.approx(34 / 70)  # the tea tasting: tables 3/1 and 1/3, 4/0 and 0/4
    assert pr.fisher_p(5, 5, 0, 5) == pytest.approx(2 / 252)  # all against none: the two extreme tables
    assert pr.fisher_p(0, 5, 5, 5) == pr.fisher_p(5, 5, 0, 5)
    assert pr.fisher_p(2, 5, 2, 5) == pytest.approx(1.0) and pr.fisher_p(0, 3, 0, 3) == 1.0


def test_proposals_per_social_cycle_are_each_runs_proposals_over_its_social_cycles_averaged_over_runs(tmp_path):
    # 500 segments an epoch, cycles of 10: 50 cycles, a social share of 0.2 makes 10 social cycles.
    resumed = pr.read_run(fake_run(tmp_path / "a1", 1, 0.5, True, epochs=5))
    for k in resumed:  # resumed from a version that did not log the proposals in epochs 0 and 1
        if k.startswith("sp_"):
            resumed[k][:2] = math.nan
    resumed["sp_beyond_S3"][2:], resumed["sp_frontier_S3"][2:] = [1, 2, 3], [3, 3, 3]  # 6 and 9 in 30 cycles
    shorter = pr.read_run(fake_run(tmp_path / "a2", 2, 0.5, True, epochs=3))
    shorter["social_share"] = np.array([0.1, 0.1, 0.2])  # 5 + 5 + 10 social cycles
    shorter["sp_beyond_S3"], shorter["sp_frontier_S3"] = np.array([0, 2, 0.0]), np.array([1, 1, 2.0])  # 2, 4 in 20
    older = pr.read_run(fake_run(tmp_path / "a3", 3, 0.5, True, epochs=5))
    older = {k: v for k, v in older.items() if not k.startswith("sp_")}  # no proposals logged: left out
    alone = [pr.read_run(fake_run(tmp_path / f"b{s}", s, 0.5, False, epochs=5)) for s in (1, 2)]
    text = pr.tables({"A": [resumed, shorter, older], "B": alone})
    table = markdown_table_after(text, "The social partner's proposals per social cycle")
    assert "(A: 2 of 3 runs; min-max over them)" in text
    assert table[0] == ["class", "A, beyond", "A, frontier"]  # B had no social cycle
    s3 = next(row for row in table if row[0] == "S3")
    assert s3[1:] == ["0.15 (0.1-0.2)", "0.25 (0.2-0.3)"]  # beyond (6/30 + 2/20) / 2, frontier (9/30 + 4/20) / 2
    rates = pr.proposal_rates_by_condition({"A": [resumed, shorter, older], "B": alone})
    assert list(rates) == ["A"] and rates["A"].shape == (2, 2, len(og.evaluation_classes(3)) + 1)


def test_first_discovery_of_each_hard_class_reads_epoch_and_social_cycles_up_to_it_or_a_dash(tmp_path):
    runs = [pr.read_run(fake_run(tmp_path / f"sp{s}", s, 0.5, True, epochs=e, blocks=5)) for s, e in ((1, 6), (2, 8))]
    for r in runs:
        r |= {f"agent_nodes_{c}": np.zeros(len(r["epoch"])) for c in og.evaluation_classes(5)}
    first, longer = runs
    first["social_share"] = np.array([0.2, 0, 0.1, math.nan, 0.4, 0.2])  # social cycles 10, 0, 5, ?, 20, 10
    first["agent_nodes_S3"] = np.array([0, 0, 0, 0, 2, 3.0])  # epoch 4: 10 + 0 + 5 + 20 social cycles
    first["agent_nodes_S4"] = np.array([math.nan, math.nan, 1, 1, 1, 1])  # logged from epoch 2 (a resumed run)
    first["agent_nodes_P3&S2"] = np.ones(6)  # epoch 0, its 10 social cycles
    longer["agent_nodes_S2&S2"][3:] = 4  # epoch 3: 4 x 10 social cycles
    longer["agent_nodes_S3"][7] = 1  # after epoch 5, the shorter run's last: not in the table
    table = markdown_table_after(pr.tables({"SP-20%": runs}), "Help and discovery per run")
    hard = {row[0]: dict(zip(table[0][5:], row[5:], strict=True)) for row in table[1:]}
    assert hard["SP-20% seed 1"] == {"S3": "4 (35)", "S2&S2": "—", "S2&S3": "—", "P3&S2": "0 (10)", "S4": "2 (15)",
                                     "S5": "—"}  # fmt: skip
    assert hard["SP-20% seed 2"] == dict.fromkeys(pr.HARD, "—") | {"S2&S2": "3 (40)"}


def test_practice_table_gives_per_construction_class_its_discovery_its_goals_pursued_and_reached_and_its_sr(
    tmp_path, figures_not_rendered
):
    # S2: first met at epoch 2 and a graph node from epoch 4; each epoch 10 own goals (1 reached), 4 frontier
    # goals (2 arrived) and 1 beyond goal (never reached); an epoch takes 0.1 h; S3 and P3 never met
    run = fake_run(tmp_path / "a", 0, 1.0, True, noise=0, seconds=(200, 100, 60))
    with (run / "progress.csv").open(newline="") as f:
        rows = list(csv.DictReader(f))
    for e, row in enumerate(rows):
        for c in og.evaluation_classes(3):
            s2 = c == "S2"
            row |= {f"encounters_{c}": int(s2 and e >= 2), f"agent_nodes_{c}": int(s2 and e >= 4), "agent_nodes": 4}
            row |= {f"own_{c}": 10 * s2, f"own_reached_{c}": int(s2), f"sp_frontier_{c}": 4 * s2}
            row |= {f"sp_frontier_arrived_{c}": 2 * s2, f"sp_beyond_{c}": int(s2), f"sp_beyond_reached_{c}": 0}
    write_rows(run, rows)
    pr.main(["--condition", "A", str(run), "--out", str(tmp_path / "out")])
    table = (tmp_path / "out" / "tables.md").read_text()
    assert "| S2 | A seed 0 | 2 (0.30 h) | 4 (0.50 h) | 120 + 48 + 12 | 0.10 / 0.50 / 0.00 | 0.92 | 0.70 h |" in table
    assert "| S3 | A seed 0 | never | never | 0 + 0 + 0 | - / - / - | 0.92 | 0.70 h |" in table
    assert "| C1 | A seed 0 |" not in table.split("Why the constructions")[1].split("\n\n")[1]  # constructions only
    for row in rows:  # a baseline's run (lp_baseline.py, vds_baseline.py): its own goals, no partner's
        for k in [k for k in row if k.startswith("sp_")]:
            del row[k]
    write_rows(run, rows)
    pr.main(["--condition", "A", str(run), "--out", str(tmp_path / "baseline")])
    table = (tmp_path / "baseline" / "tables.md").read_text()
    assert "| S2 | A seed 0 | 2 (0.30 h) | 4 (0.50 h) | 120 + - + - | 0.10 / - / - | 0.92 | 0.70 h |" in table
