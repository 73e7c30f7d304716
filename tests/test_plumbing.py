"""plumbing.py, the module the three training scripts share for what is not the algorithm: its design
promises (it knows no training script or goal sampler; nothing is defined twice) and the console's
in-epoch progress line. The behaviour it carries (command line, checkpoints, resume, interruptions,
the paper's file, outputs) is tested once, through gangstr_hme.py, in test_gangstr.py and
test_paper_agent.py."""

import ast
import types
from pathlib import Path

import pytest

import plumbing

ROOT = Path(__file__).resolve().parent.parent
SCRIPTS = ("gangstr_hme.py", "lp_baseline.py", "vds_baseline.py")


def top_level_names(path: Path) -> set[str]:
    tree = ast.parse(path.read_text())
    names = {n.name for n in tree.body if isinstance(n, ast.FunctionDef | ast.ClassDef)}
    for n in tree.body:
        if isinstance(n, ast.Assign):
            names |= {t.id for t in n.targets if isinstance(t, ast.Name)}
    return names


def test_plumbing_imports_no_training_script_and_knows_no_goal_sampler():
    tree = ast.parse((ROOT / "plumbing.py").read_text())
    imported = {a.name for n in ast.walk(tree) if isinstance(n, ast.Import) for a in n.names}
    imported |= {n.module for n in ast.walk(tree) if isinstance(n, ast.ImportFrom)}
    assert not imported & {s.removesuffix(".py") for s in SCRIPTS}
    names = {n.id for n in ast.walk(tree) if isinstance(n, ast.Name)} | {
        n.attr for n in ast.walk(tree) if isinstance(n, ast.Attribute)
    }
    assert not names & {"GoalSampler", "SocialPartner", "social_cycle", "internalization_buffer", "heads"}


@pytest.mark.parametrize("script", SCRIPTS)
def test_no_top_level_name_is_defined_both_in_a_script_and_in_plumbing(script):
    assert not top_level_names(ROOT / script) & top_level_names(ROOT / "plumbing.py") - {"__doc__"}


@pytest.mark.parametrize("script", SCRIPTS)
def test_every_script_imports_plumbing_and_keeps_its_main_short(script):
    tree = ast.parse((ROOT / script).read_text())
    (main,) = [n for n in tree.body if isinstance(n, ast.FunctionDef) and n.name == "main"]
    assert "import plumbing" in (ROOT / script).read_text()
    assert main.end_lineno - main.lineno < 20


def fake_run(cycle: int, seconds: float, steps: int, epoch: int, last_eval: float | None):
    """What cycle_progress reads of a run: 10 cycles of 10-step segments per epoch, 3 epochs."""
    args = types.SimpleNamespace(n_cycles=10, n_epochs=3, segment_len=10, n_updates=30, freeze_normalizer=False)
    tally = dict(wall=seconds, env_steps_at_start=1000, losses=dict(critic_loss=0.25))
    rows = [] if last_eval is None else [dict(time_eval=last_eval)]
    learner = types.SimpleNamespace(segments=(1000 + steps) // 10, waiting=None)
    return types.SimpleNamespace(args=args, tally=tally, cycle=cycle, epoch=epoch, rows=rows, learner=learner)


def test_the_progress_line_shows_steps_per_second_and_the_time_left_in_the_epoch_and_the_run(capsys):
    # 4 cycles in 8 s (2 s a cycle), 400 steps: 50 steps/s. The epoch: 6 cycles (12 s) and an evaluation
    # as long as the last one (5 s) = 17 s. The run: that, then one more epoch of 10 cycles and its
    # evaluation (25 s) = 42 s.
    plumbing.cycle_progress(fake_run(cycle=4, seconds=8.0, steps=400, epoch=1, last_eval=5.0), "nodes 7")
    line = capsys.readouterr().out
    assert "epoch 1 cycle 4/10 | nodes 7 | critic loss 0.250 | train 50 steps/s | left: epoch 0:17, run 0:42" in line
    # Before any evaluation, the estimate counts the cycles alone: 12 s, then 2 x 20 s more.
    plumbing.cycle_progress(fake_run(cycle=4, seconds=8.0, steps=400, epoch=0, last_eval=None), "x")
    assert "left: epoch 0:12, run 0:52" in capsys.readouterr().out


def test_the_progress_line_comes_after_the_first_cycle_and_every_tenth_of_an_epoch(capsys):
    printed = []
    for cycle in range(1, 21):
        run = fake_run(cycle=cycle, seconds=2.0 * cycle, steps=100 * cycle, epoch=0, last_eval=None)
        run.args.n_cycles = 20
        plumbing.cycle_progress(run, "x")
        printed += [cycle] if capsys.readouterr().out else []
    assert printed == [1, 2, 4, 6, 8, 10, 12, 14, 16, 18, 20]


@pytest.mark.parametrize("seconds, shown", [(0, "0:00"), (59.6, "1:00"), (125, "2:05"), (3725, "1:02:05")])
def test_durations_read_as_minutes_and_seconds_then_hours(seconds, shown):
    assert plumbing.duration(seconds) == shown
