"""The person partner's page in a real browser: Debian's chromium, headless, driven by Selenium through
Debian's chromedriver. A tiny run with --partner person: the browser waits for a question, clicks a
candidate, and picks.csv names it as the person's and as the goal of the agent's next segment; a second
run is left alone with the page open and falls back on the oracle's draw by timeout; a third cannot render,
and the page says why beside the scene while its questions wait.

Without chromium these tests skip, except under CI (CI=true), where a missing browser is a failure:
`.ci/run` installs it. PERSON_PAGE_SCREENSHOT=path saves the page with its first question there (the
README's picture: docs/person_page.png)."""

import csv
import os
import re
import shutil
import subprocess
import sys
import time
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parent.parent
CHROMIUM, CHROMEDRIVER = shutil.which("chromium") or "/usr/bin/chromium", shutil.which("chromedriver")
TINY = ["--n-blocks", "3", "--n-epochs", "1", "--n-cycles", "1", "--n-segments", "2", "--n-updates", "1",
        "--batch-size", "16", "--segment-len", "6", "--stable-steps", "3", "--eval-goals-per-class", "1",
        "--threads", "1", "--sp-ratio", "1", "--partner", "person", "--person-port", "0"]  # fmt: skip


def missing() -> str | None:
    try:
        import selenium  # noqa: F401, PLC0415
    except ImportError:
        return "selenium is not installed (pip install -r requirements.txt)"
    if not (os.path.exists(CHROMIUM) and CHROMEDRIVER):
        return "Debian's chromium and chromium-driver are not installed (apt-get install chromium chromium-driver)"
    return None


@pytest.fixture
def browser(tmp_path):
    if (why := missing()) is not None:
        if os.environ.get("CI") == "true":
            pytest.fail(f"under CI the browser test must run: {why}")
        pytest.skip(why)
    from selenium import webdriver  # noqa: PLC0415
    from selenium.webdriver.chrome.service import Service  # noqa: PLC0415

    options = webdriver.ChromeOptions()
    options.binary_location = CHROMIUM
    for flag in ("--headless=new", "--no-sandbox", "--disable-gpu", "--disable-dev-shm-usage", "--no-first-run",
                 "--disable-background-networking", "--disable-component-update", "--disable-sync",
                 "--window-size=1400,1000", f"--user-data-dir={tmp_path / 'chromium'}"):  # fmt: skip
        options.add_argument(flag)
    driver = webdriver.Chrome(service=Service(CHROMEDRIVER), options=options)
    yield driver
    driver.quit()


def start(runs: Path, *argv, env: dict | None = None) -> tuple[subprocess.Popen, str]:
    """A tiny --partner person run, and the address it prints."""
    cmd = [sys.executable, "-u", "gangstr_hme.py", *TINY, *argv, "--runs-dir", str(runs)]
    env = (os.environ if env is None else env) | dict(PYTHONUNBUFFERED="1")
    proc = subprocess.Popen(cmd, cwd=ROOT, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True, env=env)
    for line in proc.stdout:
        if m := re.search(r"open (http://127\.0\.0\.1:\d+/\?token=\S+) in a browser", line):
            return proc, m.group(1)
    raise AssertionError(f"the run printed no address: {proc.communicate()[0]}")


def picks(runs: Path) -> list[dict]:
    (run,) = runs.iterdir()
    with (run / "picks.csv").open(newline="") as f:
        return list(csv.DictReader(f))


def wait_for(driver, css: str, seconds: float = 60):
    from selenium.webdriver.common.by import By  # noqa: PLC0415
    from selenium.webdriver.support.ui import WebDriverWait  # noqa: PLC0415

    return WebDriverWait(driver, seconds).until(lambda d: d.find_elements(By.CSS_SELECTOR, css))


def test_a_person_clicks_a_candidate_and_the_agent_pursues_it(browser, tmp_path):
    from selenium.webdriver.common.by import By  # noqa: PLC0415

    proc, address = start(tmp_path / "runs", "--person-timeout", "120")
    try:
        browser.get(address)
        buttons = wait_for(browser, "button.candidate")
        title = browser.find_element(By.ID, "title").text
        assert title.startswith("Question 1:") and "beyond" in title  # the empty graph: nothing known to go to
        assert browser.find_element(By.CSS_SELECTOR, "#frame img").get_attribute("naturalWidth") == "360"
        assert len(buttons) > 2 and all(b.find_elements(By.TAG_NAME, "svg") for b in buttons)  # drawn configs
        shot = tmp_path / "page.png"
        browser.save_screenshot(str(shot))
        assert shot.stat().st_size > 10_000
        if target := os.environ.get("PERSON_PAGE_SCREENSHOT"):
            shutil.copy(shot, target)
        stack = next((b for b in buttons if "on" in b.text.split("\n")[-1].split()), buttons[1])  # a tower if any
        goal = stack.get_attribute("data-goal")
        stack.click()
        handled = {1}
        while proc.poll() is None:  # later questions: "no goal this time", each once
            title = browser.find_element(By.ID, "title").text
            if (m := re.match(r"Question (\d+):", title)) and int(m.group(1)) not in handled:
                handled.add(int(m.group(1)))
                browser.find_element(By.CSS_SELECTOR, "button.skip").click()
            time.sleep(0.2)
        assert proc.wait(60) == 0
    finally:
        proc.kill()
        out = proc.communicate()[0]
    first = picks(tmp_path / "runs")[0]
    assert (first["question"], first["by"], first["picked"]) == ("1", "person", goal), out[-2000:]
    assert first["first_goal"] == goal  # the agent's next segment targeted the person's pick
    assert first["outcome"] in ("reached", "not reached") and first["segments"] == "1"
    assert all(p["by"] == "skipped" for p in picks(tmp_path / "runs")[1:])


def test_a_run_left_alone_with_the_page_open_finishes_by_timeouts(browser, tmp_path):
    from selenium.webdriver.common.by import By  # noqa: PLC0415

    proc, address = start(tmp_path / "runs", "--person-timeout", "2")
    try:
        browser.get(address)
        wait_for(browser, "button.candidate")
        assert "s left, then the oracle draws one" in browser.find_element(By.ID, "hint").text
        assert proc.wait(120) == 0
        time.sleep(1.5)  # the page's next poll finds the run gone
        assert "not answering" in browser.find_element(By.ID, "status").text
    finally:
        proc.kill()
        proc.communicate()
    rows = picks(tmp_path / "runs")
    assert rows and all(r["by"] == "timeout" and r["picked"] in r["offered"].split() for r in rows)


def test_without_pictures_the_reason_stays_beside_the_scene_while_a_question_waits_and_the_terminal_says_it_once(
    browser, tmp_path
):
    from selenium.webdriver.common.by import By  # noqa: PLC0415

    headless = {k: v for k, v in os.environ.items() if k not in ("DISPLAY", "MUJOCO_GL")}  # no GL chosen: none
    proc, address = start(tmp_path / "runs", "--person-timeout", "3", env=headless)
    try:
        browser.get(address)
        wait_for(browser, "button.candidate")  # a question waits, its countdown running
        assert "s left, then the oracle draws one" in browser.find_element(By.ID, "hint").text
        reason = browser.find_element(By.CSS_SELECTOR, "#scene #noframe")
        assert reason.is_displayed() and not browser.find_elements(By.CSS_SELECTOR, "#frame img")
        assert "no display, and MUJOCO_GL is not set" in reason.text and "MUJOCO_GL=osmesa" in reason.text
        assert proc.wait(120) == 0
    finally:
        proc.kill()
        out = proc.communicate()[0]
    about = [line for line in out.splitlines() if re.search("picture|GLFW|DISPLAY|render", line, re.IGNORECASE)]
    assert len(about) == 1 and "no display, and MUJOCO_GL is not set" in about[0], out[-2000:]
