"""The project explains itself from its own files: every "SPEC §N" is a section of docs/SPEC.md, every page or
section a file names exists, and no text points outside the repository or speaks of how the project was made
(a tracker's numbers, the work behind it) rather than of its commits, versions and sections."""

import csv
import dataclasses
import re
import shlex
import subprocess
from pathlib import Path

import numpy as np
import pytest
from test_baselines import TINY

import gangstr_hme as gh
import lp_baseline as lp
import oracle_graph as og
import plot_results
import plumbing
import vds_baseline as vds

ROOT = Path(__file__).resolve().parent.parent
SPEC = ROOT / "docs/SPEC.md"
TEXT = {".py", ".md", ".txt", ".toml", ".json", ".csv", ".xml", ".cfg", ".yml", ".yaml", ".gitignore", ""}


IGNORED = {".git", "runs", "videos", "__pycache__", ".pytest_cache", ".ruff_cache", ".hypothesis", ".venv"}


def project_texts() -> dict[str, str]:
    """path -> text of every file git knows of (tracked, or untracked but not ignored) that is text; outside a
    git checkout (a copy of the files, as benchmarks/mutations.py makes), every file but .gitignore's."""
    git = subprocess.run(["git", "ls-files", "--cached", "--others", "--exclude-standard"], cwd=ROOT,
                         capture_output=True, text=True)  # fmt: skip
    if (ROOT / ".git").exists() and git.returncode == 0:
        listed = git.stdout.splitlines()
    else:
        listed = [p.relative_to(ROOT).as_posix() for p in ROOT.rglob("*")
                  if not IGNORED & set(p.relative_to(ROOT).parts)]  # fmt: skip
    texts = {}
    for name in listed:
        path = ROOT / name
        if path.suffix in TEXT and path.is_file():
            texts[name] = path.read_text(encoding="utf-8", errors="replace")
    return texts


def spec_sections() -> list[str]:
    """The section numbers of docs/SPEC.md, from its headings `## N. Title` and `### N.M Title`."""
    return re.findall(r"^#{2,3} (\d+(?:\.\d+)?)\.? ", SPEC.read_text(), flags=re.MULTILINE)


def test_docs_spec_numbers_its_sections_1_to_13_in_order_with_4_1_and_7_1():
    sections = spec_sections()
    top = [s for s in sections if "." not in s]
    assert top == [str(i) for i in range(1, 14)]
    assert {"4.1", "7.1"} <= set(sections)
    assert sections == sorted(sections, key=lambda s: [int(x) for x in s.split(".")])


def test_every_section_sign_in_the_project_is_a_section_of_docs_spec():
    sections = set(spec_sections())
    bad = [f"{name}:{text[: m.start()].count(chr(10)) + 1}: §{m.group(1)}"
           for name, text in project_texts().items()
           for m in re.finditer(r"§(\d+(?:\.\d+)?)", text) if m.group(1) not in sections]  # fmt: skip
    assert not bad, f"{len(bad)} references to no section of docs/SPEC.md: {bad[:10]}"


# What a user cannot follow: a tracker's numbers, words about the work behind the project, files beside the
# repository. (A letter of each word in brackets: the patterns do not match themselves.)
LOOSE = [
    r"\bi[s]sues?\s*#?\d",
    r"\bi[s]sue:",
    r"\bt[a]sks?\s+\d",
    r"\bse[s]sions?\b",
    r"\bhe[l]pers?\b",
    r"\bsu[b]agents?\b",
    r"\bsh[a]red folder\b",
    r"\.\./sh[a]red\b",
    r"\bSTYLE\.md\b",
    r"(?<![\w/])SPEC\.md\b",  # the specification is docs/SPEC.md
    r"(?<![\w.])/(?:work|home|root|Users)/",  # a path on the machine a run or a page was made on
]


def test_no_text_has_loose_references_or_points_outside_the_repository():
    bad = []
    for name, text in project_texts().items():
        for pattern in LOOSE:
            for m in re.finditer(pattern, text, flags=re.IGNORECASE):
                if pattern.startswith("(?<![") and name.startswith("docs/"):
                    continue  # a page beside docs/SPEC.md names it by its file name
                bad.append(f"{name}:{text[: m.start()].count(chr(10)) + 1}: {m.group(0)!r}")
    assert not bad, f"{len(bad)} loose references: {bad[:15]}"


def headings(path: Path) -> list[str]:
    return [line.lstrip("#").strip().replace("`", "") for line in path.read_text().splitlines()
            if re.match(r"#{1,6} ", line)]  # fmt: skip


def test_every_docs_page_and_section_named_in_the_project_exists():
    bad = []
    for name, text in project_texts().items():
        for m in re.finditer(r"\b(docs/[\w.-]+\.md|README(?:\.md)?)(?:,? (?:section|sections)?\s*\"([^\"]+)\")?", text):
            page = ROOT / (m.group(1) if m.group(1).startswith("docs/") else "README.md")
            if not page.is_file():
                bad.append(f"{name}: {m.group(0)!r} (no such page)")
            elif m.group(2) and m.group(2).replace("`", "") not in headings(page):  # the whole title
                bad.append(f"{name}: {m.group(0)!r} (no such section)")
    assert not bad, bad[:10]


@pytest.mark.parametrize("page", ["README.md", *sorted(p.relative_to(ROOT).as_posix() for p in ROOT.glob("docs/*.md"))])
def test_every_relative_link_of_a_page_reaches_a_file_in_the_repository(page):
    text, here = (ROOT / page).read_text(), (ROOT / page).parent
    bad = []
    for target in re.findall(r"\]\(([^)\s]+)\)", text):
        if re.match(r"[a-z]+:", target) or target.startswith("#"):
            continue  # a web address, or a place in this page
        path = (here / target.split("#")[0]).resolve()
        if not path.exists() or ROOT not in path.parents and path != ROOT:
            bad.append(target)
    assert not bad, f"{page}: links to nothing in the repository: {bad}"


def test_the_readme_is_short_and_opens_with_the_two_commands():
    text = (ROOT / "README.md").read_text()
    assert len(text.splitlines()) <= 300
    commands = re.findall(
        r"^python -m venv .venv && \. .venv/bin/activate && pip install -r requirements.txt && (.+)$",
        text,
        flags=re.MULTILINE,
    )
    assert commands[:2] == ["python gangstr_hme.py --sp-ratio 0.2", "python -m pytest -n 2"]


# ------------------------------------------------------------------------------------------------
# Every command the pages show passes the scripts' argument check
# ------------------------------------------------------------------------------------------------
SCRIPTS = {"gangstr_hme.py": gh, "lp_baseline.py": lp, "vds_baseline.py": vds}
PLACEHOLDERS = {"N": "5", "X": "0.2", "K": "50", "H": "3"}  # what the pages write for a number the reader picks
CALL = r"(?:\bpython3?|\btorchrun(?: --?[\w-]+(?: \d+)?)*) (gangstr_hme|lp_baseline|vds_baseline)\.py\b([^`]*)"
REDIRECTS = re.compile(r"^(&|&&|\|\|?|;|\d?>.*|>>.*)$")  # a command's end: the shell's, not the script's


def shown_commands(page: Path) -> list[tuple[str, list[str]]]:
    """(script, arguments) of every call of a training script on a page: each line of its code blocks (a
    trailing backslash continues it) and each inline code span, its shell variables ($common: the page's
    assignment; a loop's $seed: its first value) and placeholders filled in."""
    text = page.read_text()
    blocks = re.findall(r"^```[a-z]*\n(.*?)^```", text, flags=re.MULTILINE | re.DOTALL)
    lines = [line for b in blocks for line in b.replace("\\\n", " ").splitlines()]
    spans = re.findall(r"`([^`]+)`", re.sub(r"^```.*?^```", "", text, flags=re.MULTILINE | re.DOTALL))
    code = "\n".join(lines)
    variables = dict(re.findall(r'^\s*(\w+)="([^"]*)"', code, flags=re.MULTILINE))  # name="..."
    for name, values in re.findall(r"\bfor (\w+) in (.+?); do", code):  # a loop's first pass
        variables[name] = shlex.split(values)[0]
    for name in re.findall(r"\bset -- \$(\w+)", code):  # $1, $2, ... of that pass
        variables |= {str(i): v for i, v in enumerate(shlex.split(variables[name]), 1)}
    found = []
    for command in lines + [" ".join(span.split()) for span in spans]:
        for script, rest in re.findall(CALL, command):
            rest = re.sub(r"\$\{?(\w+)\}?", lambda m: variables.get(m[1], m[0]), rest)
            rest = rest.replace("[", "").replace("]", "")  # an optional flag: shown, so checked
            argv = []
            for token in shlex.split(rest, comments=True):
                if REDIRECTS.match(token):
                    break
                argv.append(PLACEHOLDERS.get(token, token))
            found.append((f"{script}.py", argv))
    return found


def test_every_command_the_pages_show_passes_the_argument_check(monkeypatch, tmp_path):
    """The README's and docs' commands, and the flag combinations they show (the learner's query and picks
    alone, with the coin, with a person...), are all accepted: a page never shows a refused command. (Not
    whether this machine has the GPU or bf16 instructions a command names: that is for its own machine.)"""
    monkeypatch.setattr(plumbing, "check_device", lambda a: None)
    checkpoint = tmp_path / "checkpoint.pt"  # runs/<run>/checkpoint.pt: a file the reader has
    checkpoint.touch()
    pages = [ROOT / "README.md", *sorted((ROOT / "docs").glob("*.md"))]
    commands = [(page.name, script, argv) for page in pages for script, argv in shown_commands(page)]
    picks_and_query_alone = ("training.md", "gangstr_hme.py", ["--ask-after", "50", "--learner-picks", "zpd"])
    assert len(commands) > 40 and picks_and_query_alone in commands
    for page, script, argv in commands:
        if "--help" in argv:
            continue
        module = SCRIPTS[script]
        argv = [str(checkpoint) if "<" in a else a for a in argv]
        try:
            plumbing.parse_args(module.Args, module.check_sampler_args, argv)
        except SystemExit as e:
            raise AssertionError(f"{page}: python {script} {shlex.join(argv)} is refused") from e


# ------------------------------------------------------------------------------------------------
# docs/training.md lists every flag and every progress.csv column, each under the scripts that have it
# ------------------------------------------------------------------------------------------------
def training_tables(section: str) -> dict[str, list[list[str]]]:
    """docs/training.md's `## {section}`: each `### ` heading -> the rows of its table (cells, stripped)."""
    text = (ROOT / "docs/training.md").read_text()
    (body,) = re.findall(rf"^## {re.escape(section)}\n(.*?)(?=^## |\Z)", text, flags=re.MULTILINE | re.DOTALL)
    tables = {}
    for part in re.split(r"^### ", body, flags=re.MULTILINE)[1:]:
        heading, _, rest = part.partition("\n")
        rows = [[c.strip() for c in line.strip().strip("|").split("|")] for line in rest.splitlines()
                if line.startswith("|")]  # fmt: skip
        tables[heading] = rows[2:]  # the header and its rule left out
    return tables


def listed(cell: str) -> list[str]:
    """The names a table's first cell lists, each in backticks: "`a`, `b`"."""
    names = re.findall(r"`([^`]+)`", cell)
    assert names and ", ".join(f"`{n}`" for n in names) == cell, f"not a list of names: {cell!r}"
    return names


def scripts_named(heading: str) -> set[str]:
    """The scripts a heading names; none: a flag or column every script has."""
    return {script for script in SCRIPTS if script in heading} or set(SCRIPTS)


def test_training_md_lists_every_flag_of_the_three_scripts_under_the_scripts_that_have_it_with_its_default():
    fields = {script: {f.name: f for f in dataclasses.fields(module.Args)} for script, module in SCRIPTS.items()}
    owners = {}  # flag -> the scripts whose Args has it
    for script, of_script in fields.items():
        for name in of_script:
            owners.setdefault("--" + name.replace("_", "-"), set()).add(script)
    pages, bad = {}, []
    for heading, rows in training_tables("Every flag").items():
        for flag, default, *_ in rows:
            (flag,) = listed(flag)
            if flag in pages:
                bad.append(f"{flag} listed twice")
            pages[flag] = scripts_named(heading)
            if pages[flag] != owners.get(flag, pages[flag]):
                bad.append(f"{flag} under '{heading}', but it is a flag of {sorted(owners[flag])}")
            for script in owners.get(flag, ()):
                value = fields[script][flag[2:].replace("-", "_")].default
                if re.fullmatch(r"`[^`]*`", default) and default != f"`{value!r}`":  # as --help prints it
                    bad.append(f"{flag}: default {default} on the page, {value!r} in {script}")
    assert not (missing := sorted(set(owners) - set(pages))), f"flags docs/training.md does not list: {missing}"
    assert not (extra := sorted(set(pages) - set(owners))), f"flags docs/training.md lists that no script has: {extra}"
    assert not bad, bad


EVERY_COLUMN = {  # flags that make a script write every column it has (a person who never answers: the oracle draws)
    "gangstr_hme.py": "--sp-ratio 0.5 --ask-after 1 --partner person --person-port 0 --person-timeout 0.05".split(),
    "lp_baseline.py": [],
    "vds_baseline.py": [],
}


@pytest.mark.parametrize("script", SCRIPTS)
def test_training_md_lists_every_progress_csv_column_a_tiny_run_writes(script, tmp_path):
    assert SCRIPTS[script].main([*TINY, "--n-blocks", "3", *EVERY_COLUMN[script], "--runs-dir", str(tmp_path)]) == 0
    (run,) = tmp_path.iterdir()
    written = (run / "progress.csv").read_text().splitlines()[0].split(",")
    classes = "|".join(re.escape(k) for k in [*og.evaluation_classes(5), "other"])
    documented = [name for heading, rows in training_tables("Every progress.csv column").items()
                  if script in scripts_named(heading) for row in rows for name in listed(row[0])]  # fmt: skip
    patterns = {name: re.compile(re.escape(name).replace(re.escape("<class>"), f"(?:{classes})"))
                for name in documented}  # fmt: skip
    undocumented = [c for c in written if not any(p.fullmatch(c) for p in patterns.values())]
    unwritten = [name for name, p in patterns.items() if not any(p.fullmatch(c) for c in written)]
    assert not undocumented, f"{script} writes columns docs/training.md does not list for it: {undocumented}"
    assert not unwritten, f"docs/training.md lists columns {script} does not write: {unwritten}"


def test_every_mutation_in_the_list_breaks_text_that_occurs_once_in_its_file():
    # benchmarks/mutations.py stops at the first stale entry; held here, a change to the code it breaks shows at once
    import importlib.util  # noqa: PLC0415

    spec = importlib.util.spec_from_file_location("mutations", ROOT / "benchmarks" / "mutations.py")
    mutations = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mutations)
    stale = [(m.name, old[:60]) for m in mutations.MUTATIONS for old, _ in m.edits()
             if (ROOT / m.file).read_text().count(old) != 1]  # fmt: skip
    assert not stale, f"mutations whose text does not occur exactly once: {stale}"


# ------------------------------------------------------------------------------------------------
# What the pages say of Adam's rates (SPEC §12) and of the committed runs is what the code and CSVs say
# ------------------------------------------------------------------------------------------------
def rate_whys() -> set[str]:
    """Every why the run's first line can give a rate (plumbing.adam_rates, and a resumed run's own)."""
    base = dict(num_envs=1, paper_rates=False, init_from="", init_lr_scale=0.1, init_warmup=2000)
    cases = [{}, dict(num_envs=24), dict(paper_rates=True), dict(lr_actor=5e-4), dict(init_from="agent.pt"),
             dict(init_from="agent.pt", lr_critic=2e-3, init_warmup=0)]  # fmt: skip
    whys = {"the run's own"}
    for case in cases:
        args = gh.Args(**{**base, **case})
        whys |= {why for _, why in plumbing.adam_rates(args)}
    return whys


def rates_pages() -> dict[str, str]:
    """The pages that state the rate rule or quote the first line, their whitespace joined (spans wrap lines)."""
    pages = ["README.md", "docs/SPEC.md", "docs/training.md", "docs/scaling.md", "docs/results.md", "docs/speed.md"]
    return {page: " ".join((ROOT / page).read_text().split()) for page in pages}


def test_every_rates_label_a_page_quotes_is_one_the_first_line_can_print(monkeypatch):
    monkeypatch.delenv("WORLD_SIZE", raising=False)
    whys, bad = rate_whys(), []
    for page, text in rates_pages().items():
        for span in re.findall(r"`([^`]*)`", text):  # code spans and blocks
            quoted = re.findall(r"rates [\d.e-]+ (?:\(([^()]*)\) )?/ [\d.e-]+ \(([^()]*)\)", span)
            labels = [why for pair in quoted for why in pair if why]
            if re.fullmatch(r"\([^()]*(?:paper|given|workers|own)[^()]*\)", span):
                labels.append(span[1:-1])  # a why on its own, as the pages list them
            bad += [f"{page}: {label!r}" for label in labels if label not in whys]
    assert not bad, f"labels no run prints (the first line's: {sorted(whys)}): {bad}"


def test_the_rate_rule_as_spec_and_training_md_state_it_is_the_codes():
    spec, training = rates_pages()["docs/SPEC.md"], rates_pages()["docs/training.md"]
    rule = spec[spec.index("**One machine's rates") : spec.index("Limits checked on the command line")]
    update = training[training.index("### The update, whatever the number of workers") :]
    update = update[: update.index(" ## ")]  # to the next section
    paper, few = plumbing.PAPER_RATE, plumbing.PAPER_RATE * plumbing.FEW_SCALE
    for name, text in (("SPEC §12", rule), ("training.md", update)):
        for said in (f"x{plumbing.FEW_SCALE:g} of the paper's", f"{plumbing.FEW_WORKERS} workers or more",
                     f"{paper:.0e}".replace("e-0", "e-"), f"{few:.0e}".replace("e-0", "e-"), "`--paper-rates`",
                     "`--init-from`", "refuse", "`--resume`", "each on its own"):  # fmt: skip
            assert said in text, f"{name} does not say {said!r}"
    assert gh.Args.lr_actor == gh.Args.lr_critic == 0  # "a rate not given (0, the default)"


def last_rows(path: str, column: str) -> np.ndarray:
    with (ROOT / path).open() as f:
        return np.array([float(r[column]) for r in csv.DictReader(f)])


def test_the_numbers_the_readme_quotes_from_the_committed_runs_are_the_csvs():
    readme = " ".join((ROOT / "README.md").read_text().split())
    main = "results/main_job/progress.csv"
    last10 = ", ".join(f"{c} {last_rows(main, f'sr_{c}')[-10:].mean():.2f}" for c in ("C1", "C2", "C3"))
    assert f"SR, last 10 epochs: {last10}" in readme
    stacks = max(last_rows(main, f"sr_{c}").max() for c in ("S2", "P3"))
    assert f"S2, P3 at most {stacks:.2f}" in readme
    hours = plot_results.own_hours(plot_results.read_run(ROOT / "results/main_job"))[-1]
    assert f"({hours:.2f} hours of its own)" in readme
    runs = [f"results/update_3blocks/w1_x0.3_seed{s}/progress.csv" for s in (1, 2)]
    own = [plot_results.own_hours(plot_results.read_run((ROOT / r).parent)) for r in runs]
    s2 = sorted((int(np.argmax(last_rows(r, "sr_S2") >= 0.8)), h) for r, h in zip(runs, own, strict=True))
    s2 = [(epoch, f"{h[epoch]:.2f}") for epoch, h in s2]
    assert f"S2 at 0.8 after {s2[0][1]} and {s2[1][1]} own hours, by epochs {s2[0][0]} and {s2[1][0]}" in readme
    halves = [int(np.argmax(last_rows(r, f"sr_{c}") >= 0.5)) for r in runs for c in ("C1", "C2", "C3")]
    assert f"C1, C2, C3 reach 0.5 by epochs {min(halves)}-{max(halves)}" in readme  # epochs count from 0
