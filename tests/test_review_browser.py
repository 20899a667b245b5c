# ruff: noqa: F811 (the tests take the imported fixture `bags` as an argument)
"""`playseg review` in a real browser (Debian's headless Chromium through Selenium): a user creates, drags,
relabels, accepts, rejects and saves; the saved sidecar file is what `playseg convert` reads back."""

from __future__ import annotations

import json
import shutil
import subprocess
import sys
import time
import urllib.error
import urllib.request
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest
import yaml
from selenium.common.exceptions import StaleElementReferenceException
from test_convert import write_mapping
from test_convert_segment import convert_cli, untrained_model
from test_review_times import bags  # noqa: F401 (the fixture: two robot bags and their mapping)

from playseg_core.data.dataset import PlayDataset

CHROMIUM, CHROMEDRIVER = shutil.which("chromium"), shutil.which("chromedriver")
pytestmark = pytest.mark.skipif(
    CHROMIUM is None or CHROMEDRIVER is None,
    reason="needs Debian's chromium and chromium-driver (scripts/setup_env.sh installs them)",
)
WAIT_S = 20.0


@pytest.fixture(scope="module")
def reviewed(bags: dict[str, Path], tmp_path_factory: pytest.TempPathFactory) -> dict[str, Path]:
    """The two bags converted with an untrained model's proposals for the unannotated one (all kept)."""
    root = tmp_path_factory.mktemp("review")
    assert convert_cli([bags["play"]], root / "plain", bags["mapping"]) == 0
    plain = PlayDataset.open(root / "plain")
    model = untrained_model(root / "ps.pt", plain.features, plain.episode(0, truth=True))
    both = [bags["play"], bags["annotated"]]
    assert convert_cli(both, root / "data", bags["mapping"], "--segment", str(model), "--keep", "all") == 0
    return {"data": root / "data", "model": model, "root": root}


@pytest.fixture(scope="module")
def server(reviewed: dict[str, Path]) -> Iterator[str]:
    """`playseg review DATA --port 0` as a user runs it; yields the URL it prints."""
    process = subprocess.Popen(
        [sys.executable, "-m", "playseg_ros.cli", "review", str(reviewed["data"]), "--port", "0"],
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
    )
    assert process.stdout is not None
    line = process.stdout.readline()
    try:
        assert line.startswith("playseg review: http://127.0.0.1:"), line + process.stderr.read()
        yield line.split()[2]
    finally:
        process.terminate()
        process.wait(timeout=10)


@pytest.fixture(scope="module")
def browser() -> Iterator[Any]:
    from selenium import webdriver
    from selenium.webdriver.chrome.service import Service

    options = webdriver.ChromeOptions()
    options.binary_location = CHROMIUM  # type: ignore[assignment]
    for argument in ("--headless=new", "--no-sandbox", "--disable-dev-shm-usage", "--window-size=1400,900"):
        options.add_argument(argument)
    driver = webdriver.Chrome(options=options, service=Service(CHROMEDRIVER))
    try:
        yield driver
    finally:
        driver.quit()


def wait_for(driver: Any, script: str, what: str, seconds: float = WAIT_S) -> Any:
    """Poll ``script`` (JavaScript returning a value) until it is truthy."""
    deadline = time.monotonic() + seconds
    while time.monotonic() < deadline:
        value = driver.execute_script(script)
        if value:
            return value
        time.sleep(0.1)
    raise AssertionError(f"timed out waiting for {what}: {driver.find_element('id', 'status').text!r}")


def queue(driver: Any) -> list[str]:
    """The queue's items as the user reads them, top to bottom (read at once: it may be redrawn)."""
    return driver.execute_script(
        "return Array.from(document.querySelectorAll('#episodes li')).map(li => li.innerText)"
    )


def state(driver: Any) -> dict[str, Any]:
    return driver.execute_script(
        "const s = window.review.state; return {labels: s.labels, proposals: s.proposals, step: s.step, ep: s.ep, selected: s.selected};"
    )


def open_episode(driver: Any, url: str, episode_id: str) -> None:
    driver.get(url)
    opened = wait_for(
        driver,
        "return window.review && window.review.state.ep && window.review.state.opened",
        "the queue's first episode",
    )
    for _ in range(5):  # the queue is redrawn when a background job ends: find the item again then
        try:
            driver.find_element(
                "xpath", f"//ul[@id='episodes']/li[div[text()[contains(., '{episode_id}')]]]"
            ).click()
            break
        except StaleElementReferenceException:
            time.sleep(0.2)
    wait_for(
        driver,
        f"return window.review.state.opened > {opened} && window.review.state.ep.episode_id === '{episode_id}'",
        episode_id,
    )


def lane_point(driver: Any, step: float, lane: str) -> tuple[int, int]:
    """Offsets from the detail canvas's centre of a step on a lane (what a user's mouse aims at)."""
    return driver.execute_script(
        """const c = document.getElementById('detail'), r = c.getBoundingClientRect();
        const [y, h] = window.review.laneY[arguments[1]];
        const x = window.review.xOfStep(arguments[0]) * r.width / c.width;
        return [Math.round(x - r.width / 2), Math.round(y + h / 2 - r.height / 2)];""",
        step,
        lane,
    )


def click_lane(driver: Any, step: float, lane: str) -> None:
    from selenium.webdriver import ActionChains

    dx, dy = lane_point(driver, step, lane)
    ActionChains(driver).move_to_element_with_offset(
        driver.find_element("id", "detail"), dx, dy
    ).click().perform()


def keys(driver: Any, *sequence: str) -> None:
    from selenium.webdriver import ActionChains

    chain = ActionChains(driver)
    for key in sequence:
        chain.send_keys(key)
    chain.perform()


def saved(driver: Any) -> str:
    driver.find_element("id", "save").click()
    return wait_for(
        driver,
        "const s = document.getElementById('status'); return s.className === 'ok' && s.textContent",
        "the save",
    )


def test_queue_puts_the_proposals_of_lowest_confidence_first(browser: Any, server: str) -> None:
    browser.get(server)
    wait_for(browser, "return window.review && window.review.state.ep", "the first episode")
    items = queue(browser)
    assert [item.split("\n")[0] for item in items] == ["play:0", "annotated:0"]
    assert "min conf" in items[0] and "76% labelled" in items[1]
    assert state(browser)["ep"]["episode_id"] == "play:0"  # the queue's first is opened
    ready = wait_for(
        browser,
        "const v = document.querySelector('#videos video'); return v && v.readyState >= 2 && v.readyState",
        "the video",
    )
    assert ready >= 2  # the browser decoded the MP4


def test_create_drag_relabel_save_and_reload(
    browser: Any, server: str, reviewed: dict[str, Path], tmp_path: Path, bags: dict[str, Path]
) -> None:
    from selenium.webdriver import ActionChains
    from selenium.webdriver.common.keys import Keys

    open_episode(browser, server, "annotated:0")
    assert [(lab["start"], lab["end"]) for lab in state(browser)["labels"]] == [(3, 12), (12, 25)]
    shown = browser.find_element("id", "episode-source").text  # the bag it was recorded in
    assert shown.startswith(f"source: bag {bags['annotated']} (/annotations, /camera/image_raw"), shown
    # drag the shared boundary at 12 to 15: both neighbours follow
    detail = browser.find_element("id", "detail")
    (x0, y0), (x1, _) = lane_point(browser, 12, "label"), lane_point(browser, 15, "label")
    ActionChains(browser).move_to_element_with_offset(detail, x0, y0).click_and_hold().move_by_offset(
        x1 - x0, 0
    ).release().perform()
    assert [(lab["start"], lab["end"]) for lab in state(browser)["labels"]] == [(3, 15), (15, 25)]
    # a new segment from the playhead: in at 26, three steps on, out; its instruction typed
    click_lane(browser, 26.2, "label")
    assert state(browser)["step"] == 26
    keys(browser, "i", Keys.ARROW_RIGHT, Keys.ARROW_RIGHT, Keys.ARROW_RIGHT, "o")
    relabel = browser.find_element("id", "relabel")
    relabel.send_keys("wave hello", Keys.ENTER)
    # relabel the first segment with autocomplete from the vocabulary (a datalist of the instructions)
    options = browser.execute_script(
        "return Array.from(document.querySelectorAll('#vocabulary option')).map(o => o.value)"
    )
    assert "pick up the cup" in options and "put the cup down" in options
    click_lane(browser, 5, "label")
    relabel.clear()
    relabel.send_keys("grab the cup", Keys.ENTER)
    browser.find_element("id", "reviewer").send_keys("ana")
    assert "saved 3 label(s)" in saved(browser)

    labels_file = reviewed["data"].with_name("data.review") / "labels" / "annotated.yaml"
    entries = yaml.safe_load(labels_file.read_text())["annotations"]
    times = PlayDataset.open(reviewed["data"]).timestamps(_index(reviewed["data"], "annotated:0"))
    assert [(e["start"], e["end"], e["instruction"], e["provenance"]) for e in entries] == [
        (times[3], times[15], "grab the cup", "human"),
        (times[15], times[25], "put the cup down", "human"),
        (times[26], times[29], "wave hello", "human"),
    ]
    # reload: the page shows what was saved
    open_episode(browser, server, "annotated:0")
    assert [(lab["start"], lab["end"], lab["instruction"]) for lab in state(browser)["labels"]] == [
        (3, 15, "grab the cup"), (15, 25, "put the cup down"), (26, 29, "wave hello")
    ]  # fmt: skip
    # and `playseg convert` reads the file as these segments
    mapping = write_mapping(
        tmp_path / "m.yaml", annotations={"file": str(labels_file.parent / "{name}.yaml")}
    )
    assert convert_cli([bags["annotated"]], tmp_path / "again", mapping) == 0
    again = PlayDataset.open(tmp_path / "again")
    assert [(s.start, s.end, s.instruction) for s in again.segments(0)] == [
        (3, 15, "grab the cup"), (15, 25, "put the cup down"), (26, 29, "wave hello")
    ]  # fmt: skip


def _index(data: Path, episode_id: str) -> int:
    return [r.episode_id for r in PlayDataset.open(data).records].index(episode_id)


def test_accept_reject_accept_above_undo_and_save_proposals(
    browser: Any, server: str, reviewed: dict[str, Path]
) -> None:
    open_episode(browser, server, "play:0")
    proposals = state(browser)["proposals"]
    assert len(proposals) >= 3
    first, second = proposals[0], proposals[1]
    click_lane(browser, (first["start"] + first["end"]) / 2, "proposal")
    keys(browser, "a")
    after = state(browser)
    assert [(lab["start"], lab["end"], lab["instruction"]) for lab in after["labels"]] == [
        (first["start"], first["end"], first["instruction"])
    ]
    assert after["labels"][0]["provenance"] == first["provenance"]
    click_lane(browser, (second["start"] + second["end"]) / 2, "proposal")
    keys(browser, "x")
    assert len(state(browser)["proposals"]) == len(proposals) - 2
    # accept everything left at confidence >= 0, then undo it
    browser.find_element("id", "threshold").clear()
    browser.find_element("id", "threshold").send_keys("0")
    browser.find_element("id", "accept-above").click()
    assert len(state(browser)["labels"]) == len(proposals) - 1 and not state(browser)["proposals"]
    browser.find_element("tag name", "body").click()
    keys(browser, "z")
    assert len(state(browser)["labels"]) == 1
    browser.find_element("id", "reviewed").click()
    assert "saved 1 label(s)" in saved(browser)
    entries = yaml.safe_load(
        (reviewed["data"].with_name("data.review") / "labels" / "play.yaml").read_text()
    )["annotations"]
    assert len(entries) == 1 and entries[0]["instruction"] == first["instruction"]
    assert entries[0]["confidence"] == pytest.approx(first["confidence"], abs=1e-6)
    review_state = json.loads(
        (reviewed["data"].with_name("data.review") / "labels" / "review.json").read_text()
    )
    assert review_state["play:0"]["reviewed"] is True
    assert review_state["play:0"]["rejected"] == [[second["start"], second["end"], second["instruction"]]]
    # the queue now puts the reviewed episode last
    browser.refresh()
    wait_for(browser, "return window.review.state.info", "the episode list")
    assert queue(browser)[-1].startswith("play:0")


def test_two_tabs_never_overwrite_each_other(browser: Any, server: str) -> None:
    open_episode(browser, server, "annotated:0")
    page = state(browser)["ep"]
    # another tab saves first
    other = json.dumps(
        {"labels": [{"start": 0, "end": 2, "instruction": "other tab"}], "version": page["version"]}
    )
    request = urllib.request.Request(
        f"{server}api/episode/{page['index']}/save", other.encode(), {"Content-Type": "application/json"}
    )
    with urllib.request.urlopen(request, timeout=10) as response:
        assert json.loads(response.read())["saved"] == 1
    # this tab's save is refused with one clear message, and nothing of the other tab's is lost
    click_lane(browser, 5, "label")
    keys(browser, "Delete")
    browser.find_element("id", "save").click()
    message = wait_for(
        browser,
        "const s = document.getElementById('status'); return s.className === 'error' && s.textContent",
        "the refusal",
    )
    assert "changed since this page loaded it" in message
    with pytest.raises(urllib.error.HTTPError) as refused:
        urllib.request.urlopen(request, timeout=10)
    assert refused.value.code == 409


@pytest.mark.slow  # trains a model
def test_retrain_and_export_from_the_page(browser: Any, server: str, reviewed: dict[str, Path]) -> None:
    open_episode(browser, server, "annotated:0")
    steps = browser.find_element("id", "retrain-steps")
    steps.clear()
    steps.send_keys("12")
    browser.find_element("id", "retrain").click()
    jobs = "return document.getElementById('jobs').textContent"
    wait_for(browser, jobs + ".includes('retrain: done')", "the retraining", seconds=600)
    work = reviewed["data"].with_name("data.review")
    assert (work / "models" / "ps-0.pt").is_file()
    assert "retrain: done" in browser.execute_script(jobs) and "failed" not in browser.execute_script(jobs)
    browser.find_element("id", "export-preview").click()
    preview = wait_for(browser, "return document.getElementById('preview').textContent", "the preview")
    # each labelled episode with its rows; annotated:0 holds what the other tab saved in the test above
    assert "play:0" in preview and "annotated:0" in preview and '"content":"other tab"' in preview
    browser.find_element("id", "export").click()
    wait_for(browser, jobs + ".includes('export: done')", "the export", seconds=300)
    exported = json.loads((work / "lerobot" / "meta" / "info.json").read_text())
    assert exported["codebase_version"] == "v3.0"


CODED_BITS = 7
"""Each frame of the coded video shows its observation's index in binary, one wide bar per bit."""


def coded_frames(count: int) -> Any:
    import numpy as np

    frames = np.full((count, 16, 8 * CODED_BITS, 3), 20, np.uint8)
    for k in range(count):
        for bit in range(CODED_BITS):
            if k >> bit & 1:
                frames[k, :, 8 * bit : 8 * bit + 8] = 230
    return frames


def shown_observation(driver: Any) -> int:
    """The observation the first video shows, read off its pixels as a user's eye would."""
    values = driver.execute_script(
        """const v = document.querySelector('#videos video'), c = document.createElement('canvas');
        c.width = v.videoWidth; c.height = v.videoHeight;
        const g = c.getContext('2d'); g.drawImage(v, 0, 0);
        const row = g.getImageData(0, 8, c.width, 1).data, bits = [];
        for (let b = 0; b < arguments[0]; b++) bits.push(row[4 * (8 * b + 4)]);
        return bits;""",
        CODED_BITS,
    )
    return sum(1 << bit for bit, value in enumerate(values) if value > 128)


def settled(driver: Any, chunk: int) -> None:
    """Wait until the first video holds ``chunk`` and shows a decoded frame at rest."""
    wait_for(
        driver,
        f"const v = document.querySelector('#videos video'); return v && v.dataset.chunk === '{chunk}' "
        "&& v.readyState >= 2 && !v.seeking",
        f"video chunk {chunk}",
    )


def test_a_long_episode_plays_and_seeks_across_video_chunks(browser: Any, tmp_path: Path) -> None:
    """With 20 observations a video file, the page shows the right frame wherever the playhead goes, and
    playing runs on from one file into the next."""
    import numpy as np
    from selenium.webdriver import ActionChains
    from selenium.webdriver.common.keys import Keys

    from playseg_core.data.dataset import DatasetWriter
    from playseg_core.data.episode import Episode

    with DatasetWriter(tmp_path / "coded", ["reach"], features=None) as writer:
        actions = np.zeros((64, 1), np.float32)
        writer.add(Episode("coded", actions, images={"observation.images.top": coded_frames(65)}), "play")
    process = subprocess.Popen(
        [sys.executable, "-m", "playseg_ros.cli", "review", str(tmp_path / "coded"), "--port", "0",
         "--video-chunk", "20"],
        stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
    )  # fmt: skip
    assert process.stdout is not None
    try:
        line = process.stdout.readline()
        assert line.startswith("playseg review: http://127.0.0.1:"), line + process.stderr.read()
        open_episode(browser, line.split()[2], "coded")
        settled(browser, 0)
        assert shown_observation(browser) == 0
        keys(browser, Keys.ARROW_RIGHT, Keys.ARROW_RIGHT, Keys.ARROW_RIGHT)
        wait_for(browser, "return window.review.state.step === 3", "step 3")
        settled(browser, 0)
        assert shown_observation(browser) == 3
        for _ in range(4):  # shift+right: ten steps on, into the third file
            ActionChains(browser).key_down(Keys.SHIFT).send_keys(Keys.ARROW_RIGHT).key_up(
                Keys.SHIFT
            ).perform()
        wait_for(browser, "return window.review.state.step === 43", "step 43")
        settled(browser, 2)
        assert shown_observation(browser) == 43
        keys(browser, Keys.ARROW_LEFT * 5)  # back into the second file
        settled(browser, 1)
        assert shown_observation(browser) == 38
        # play on past the end of the second file: the third one takes over
        keys(browser, " ")
        wait_for(browser, "return window.review.state.step >= 44", "playing into the third file")
        keys(browser, " ")
        step = browser.execute_script("return window.review.state.step")
        settled(browser, step // 20)
        assert shown_observation(browser) == step
    finally:
        process.terminate()
        process.wait(timeout=10)
