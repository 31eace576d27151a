"""`matfit serve`: the JSON API through a real server, then the page in a real browser (headless Chromium).

The server runs in a thread (`server.running`) with a tiny random model; the browser tests skip with
the reason where Debian's Chromium or Playwright is not installed (CI installs both).
"""

import asyncio
import concurrent.futures
import json
import os
import shutil
import subprocess
import sys
import threading
import time
import urllib.error
import urllib.request
import uuid

import numpy as np
import pytest
from helpers import random_model

from matfit import files, images, params, shipped
from matfit.app.serve import uploads, watch
from matfit.app.serve.routes import create_app
from matfit.app.serve.server import check_listen, running
from matfit.app.serve.studio import Studio
from matfit.app.serve.watch import check_watch, settled
from matfit.errors import ImageError, OutputError
from matfit.fitting import fitfile, search
from matfit.rendering import presets

EXAMPLE = str(shipped.EXAMPLES / "recoloured.png")
OTHER = str(shipped.EXAMPLES / "desaturated.png")
CHROMIUM = "/usr/bin/chromium"


def run_to_end(coroutine):
    """Returns what a coroutine returns, run on a thread of its own: the browser tests' event loop may be running on
    this one, and asyncio.run refuses to start inside a running loop."""
    with concurrent.futures.ThreadPoolExecutor(1) as pool:
        return pool.submit(asyncio.run, coroutine).result()


def request(url: str, data: bytes | None = None, headers: dict | None = None) -> tuple[int, bytes]:
    """Returns (status, body) of a GET, or of a POST when `data` is given; 4xx and 5xx are answers too."""
    try:
        with urllib.request.urlopen(urllib.request.Request(url, data=data, headers=headers or {}), timeout=60) as reply:
            return reply.status, reply.read()
    except urllib.error.HTTPError as error:
        return error.code, error.read()


def multipart(fields: dict[str, tuple[str, bytes] | str]) -> tuple[bytes, dict]:
    """Returns a multipart/form-data body and its headers: a tuple is a file (name, bytes), a string a field."""
    boundary = uuid.uuid4().hex
    parts = []
    for key, value in fields.items():
        if isinstance(value, tuple):
            head = f'Content-Disposition: form-data; name="{key}"; filename="{value[0]}"\r\n'
            head += "Content-Type: application/octet-stream\r\n\r\n"
            parts.append(f"--{boundary}\r\n{head}".encode() + value[1] + b"\r\n")
        else:
            parts.append(f'--{boundary}\r\nContent-Disposition: form-data; name="{key}"\r\n\r\n{value}\r\n'.encode())
    body = b"".join(parts) + f"--{boundary}--\r\n".encode()
    return body, {"Content-Type": f"multipart/form-data; boundary={boundary}"}


def post_json(url: str, document: dict) -> tuple[int, bytes]:
    return request(url, json.dumps(document).encode(), {"Content-Type": "application/json"})


def post_job(url: str, document: dict) -> tuple[int, dict]:
    code, answer = post_json(url, document)
    return code, json.loads(answer)


def start_fit(url: str, path: str, name: str | None = None, **fields) -> tuple[int, dict]:
    with open(path, "rb") as file:
        body, headers = multipart({"image": (name or os.path.basename(path), file.read()), **fields})
    status, answer = request(url + "api/fit", body, headers)
    return status, json.loads(answer)


def wait(url: str, job: str, seconds: float = 120) -> tuple[int, dict]:
    deadline = time.monotonic() + seconds
    while time.monotonic() < deadline:
        status, answer = request(f"{url}api/jobs/{job}")
        answer = json.loads(answer)
        if answer["state"] not in ("queued", "running"):
            return status, answer
        time.sleep(0.05)
    raise AssertionError(f"job {job} did not finish")


@pytest.fixture(scope="module")
def studio(tmp_path_factory):
    studio = Studio(random_model(), "memory", search.Settings(iterations=10))
    studio.worker.submit(studio.warm_up).result()
    yield studio
    studio.close()


@pytest.fixture(scope="module")
def watched(tmp_path_factory):
    folder = tmp_path_factory.mktemp("watched")
    path = folder / "edit.png"
    shutil.copy(EXAMPLE, path)
    return str(path)


@pytest.fixture(scope="module")
def url(studio, watched):
    with running(studio, watched) as address:
        yield address


@pytest.fixture(scope="module")
def alone(url):
    """Returns {picture: (status, job id, (status, finished job))} of one fit through the API of each example picture,
    one after the other: what a fit of the same picture at the same time as another, or of the watched file, must give.
    Each fit is verified in Mitsuba (seconds), so the tests share these."""
    fits = {}
    for path in (EXAMPLE, OTHER):
        status, answer = start_fit(url, path)
        fits[path] = (status, answer["job"], wait(url, answer["job"]))
    return fits


def test_a_fit_through_the_api_is_the_fit_the_library_makes(url, studio, alone):
    status, job, (status_done, done) = alone[EXAMPLE]
    assert status == 202
    assert status_done == 200 and done["state"] == "done", done
    result = done["result"]
    assert set(result["pictures"]) == {"target", "start", "neural", "mitsuba", "difference"}
    assert all(picture.startswith("data:image/png;base64,") for picture in result["pictures"].values())
    expected = search.neural_search(studio.model, studio_target(studio), settings=studio.settings)
    assert result["start"] == expected.chosen and result["start_rmse"] == pytest.approx(expected.start_rmse, abs=1e-3)
    assert result["mitsuba_rmse"] <= result["start_rmse"] + 50  # a figure, not a placeholder
    document = json.loads(request(f"{url}api/jobs/{job}/files/params.json")[1])
    np.testing.assert_allclose(params.from_mapping(document["params"]), result["values"], atol=1e-6)
    assert document["target"] == "recoloured.png" and document["model"] == "memory"
    status, xml = request(f"{url}api/jobs/{job}/files/material.xml")
    assert status == 200 and b"matfit-material" in xml
    status, script = request(f"{url}api/jobs/{job}/files/material.py")
    assert status == 200 and b"bpy" in script
    status, report = request(f"{url}api/jobs/{job}/files/report.png")
    assert status == 200 and report.startswith(b"\x89PNG")


def test_a_running_fit_shows_the_neural_answer_at_once_and_its_own_answer_replaces_it(url, studio, alone):
    job = start_fit(url, EXAMPLE)[1]["job"]
    seen = []  # (state, its answer's stage, whether Mitsuba checked it, the answer) each time one of them changes
    deadline = time.monotonic() + 120
    while time.monotonic() < deadline:
        answer = json.loads(request(f"{url}api/jobs/{job}")[1])
        result = answer.get("result")
        now = (answer["state"], result and result["stage"], result and result["mitsuba_checked"])
        if not seen or seen[-1][:3] != now:
            seen.append((*now, result))
        if answer["state"] not in ("queued", "running"):
            break
        time.sleep(0.005)
    stages = [stage for _, stage, _, _ in seen if stage is not None]
    assert stages == sorted(stages, key=["neural", "verified", "clean"].index), seen  # in the order they land
    assert ("running", "neural", False) in [each[:3] for each in seen] and seen[-1][:3] == ("done", "clean", True)
    # the search's answer, marked as not yet checked in Mitsuba: no Mitsuba figure, render or ranges
    neural = next(result for _, stage, _, result in seen if stage == "neural")
    assert neural["mitsuba_rmse"] is None and neural["kept"] is None and neural["ranges"] is None
    assert neural["pictures"]["mitsuba"] is None and neural["pictures"]["difference"] is None
    assert neural["pictures"]["target"] == alone[EXAMPLE][2][1]["result"]["pictures"]["target"]
    expected = search.neural_search(studio.model, studio_target(studio), settings=studio.settings)
    np.testing.assert_allclose(neural["values"], params.from_unit(expected.unit), atol=1e-5)
    assert neural["neural_rmse"] == round(expected.rmse, 3) and neural["start"] == expected.chosen
    # replaced by the fit's own answer, the same as a fit's before answers were shown as they landed
    done = seen[-1][3]
    assert done["values"] == alone[EXAMPLE][2][1]["result"]["values"] and done["mitsuba_rmse"] is not None


def test_a_fit_cancelled_once_its_neural_answer_shows_ends_at_its_next_answer_and_the_next_fit_is_whole(url, alone):
    job = start_fit(url, EXAMPLE)[1]["job"]
    deadline, cancelled = time.monotonic() + 120, False
    while time.monotonic() < deadline:
        answer = json.loads(request(f"{url}api/jobs/{job}")[1])
        if not cancelled and (answer.get("result") or {}).get("stage") == "neural":
            request(f"{url}api/jobs/{job}/cancel", b"")  # as a newer save does: the rest of the fit is not run
            cancelled = True
        if answer["state"] not in ("queued", "running"):
            break
        time.sleep(0.005)
    assert cancelled and answer["state"] == "cancelled" and answer.get("result") is None, answer
    status, _ = request(f"{url}api/jobs/{job}/files/params.json")
    assert status >= 400  # nothing to download: the fit wrote nothing
    again = start_fit(url, EXAMPLE)[1]["job"]
    deadline = time.monotonic() + 120
    while time.monotonic() < deadline:
        done = json.loads(request(f"{url}api/jobs/{again}")[1])
        if done["state"] not in ("queued", "running"):
            break
        time.sleep(0.05)
    assert done["state"] == "done" and done["result"]["values"] == alone[EXAMPLE][2][1]["result"]["values"]


def test_a_fit_through_the_api_carries_what_the_picture_decides_as_its_params_json_says(url, alone):
    _, job, (_, done) = alone[EXAMPLE]
    found = done["result"]["ranges"]
    section = json.loads(request(f"{url}api/jobs/{job}/files/params.json")[1])["ranges"]
    assert found["threshold_rmse"] == section["threshold_rmse"] > 0
    assert len(found["parameters"]) == params.COUNT
    for p, shown in zip(params.PARAMETERS, found["parameters"], strict=True):
        written = section["parameters"][p.name]
        assert shown == {"low": written["low"], "high": written["high"], "verdict": written["verdict"]}
        assert p.low <= shown["low"] <= shown["high"] <= p.high  # the sliders' physical units
    assert found["look_alikes"] and len(found["look_alikes"]) == len(section["look_alikes"])
    for shown, written in zip(found["look_alikes"], section["look_alikes"], strict=True):
        assert shown["label"] == written["move"] and shown["rmse"] == written["rmse"] <= found["threshold_rmse"]
        assert len(shown["values"]) == params.COUNT
        np.testing.assert_array_equal(shown["values"], params.from_mapping(written["params"]))


def studio_target(studio):
    target, _, _ = fitfile.read_target(EXAMPLE, studio.model.resolution)
    return target


@pytest.mark.parametrize(
    ("name", "content", "status", "message"),
    [
        ("broken.png", b"\x89PNG\r\n\x1a\n this is not the rest of a PNG", 400, "the uploaded picture"),
        ("notes.txt", b"hello", 400, "upload a PNG, JPEG, TIFF or EXR"),
        ("empty.png", b"", 400, "is empty"),
    ],
)
def test_bad_uploads_are_4xx_with_a_message_and_the_next_upload_works(url, tmp_path, name, content, status, message):
    body, headers = multipart({"image": (name, content)})
    code, answer = request(url + "api/fit", body, headers)
    assert code == status and message in json.loads(answer)["error"]
    code, answer = start_fit(url, EXAMPLE)
    assert code == 202 and wait(url, answer["job"])[1]["state"] == "done"


def test_a_picture_with_too_many_pixels_is_refused_before_it_is_decoded(url, tmp_path, monkeypatch):
    monkeypatch.setattr(uploads, "MAX_UPLOAD_PIXELS", 100)
    code, answer = start_fit(url, EXAMPLE)
    assert code == 413 and "the picture is 256x256, more than" in answer["error"]


def test_params_json_uploads_are_checked_and_join_the_fit(url):
    good = json.dumps(params.params_document(presets.preset("gold"))).encode()
    body, headers = multipart({"params": ("gold.json", good)})
    code, answer = request(url + "api/params", body, headers)
    assert code == 200
    np.testing.assert_allclose(json.loads(answer)["values"], presets.preset("gold"), atol=1e-6)
    body, headers = multipart({"params": ("bad.json", b'{"params": {"roughness": 7}}')})
    code, answer = request(url + "api/params", body, headers)
    assert code == 400 and "roughness" in json.loads(answer)["error"]
    code, answer = start_fit(url, EXAMPLE, init=json.dumps(presets.preset("gold").tolist()))
    assert code == 202
    _, done = wait(url, answer["job"])
    document = json.loads(request(f"{url}api/jobs/{answer['job']}/files/params.json")[1])
    assert done["state"] == "done" and document["init"] == "uploaded params.json"


def test_the_preview_is_the_decoders_picture_and_follows_the_values(url, studio):
    values = presets.preset("gold")
    code, png = post_json(url + "api/preview", {"values": values.tolist()})
    assert code == 200 and png.startswith(b"\x89PNG")
    path = os.path.join(studio.folder, "preview.png")
    with open(path, "wb") as file:
        file.write(png)
    shown = images.srgb_encode(images.read(path))
    np.testing.assert_allclose(shown, studio.model.decode(params.to_unit(values))[0], atol=1 / 255 + 1e-6)
    other = post_json(url + "api/preview", {"values": presets.preset("red-plastic").tolist()})[1]
    assert other != png
    code, answer = post_json(url + "api/preview", {"values": [0.5] * 18})
    assert code == 400 and "list of 19 numbers" in json.loads(answer)["error"]


def test_a_mitsuba_render_reports_progress_and_can_be_cancelled(url):
    code, answer = post_job(url + "api/render", {"values": presets.preset("gold").tolist(), "size": 16, "spp": 16})
    assert code == 202
    _, done = wait(url, answer["job"])
    assert done["state"] == "done" and done["progress"] == 1.0 and done["result"]["spp"] == 16
    code, answer = post_job(url + "api/render", {"values": presets.preset("jade").tolist(), "size": 32, "spp": 2048})
    job = answer["job"]
    deadline = time.monotonic() + 60
    while json.loads(request(f"{url}api/jobs/{job}")[1])["progress"] == 0 and time.monotonic() < deadline:
        time.sleep(0.02)
    request(f"{url}api/jobs/{job}/cancel", b"")
    _, stopped = wait(url, job)
    assert stopped["state"] == "cancelled" and 0 < stopped["progress"] < 1
    code, answer = post_job(url + "api/render", {"values": presets.preset("gold").tolist(), "size": 5000, "spp": 4})
    assert code == 400 and "render size 5000 is out of range" in answer["error"]


def test_two_fits_at_once_each_get_their_own_result(url, alone):
    answers = [{}, {}]

    def run(k, path):
        answers[k] = wait(url, start_fit(url, path)[1]["job"])[1]

    threads = [threading.Thread(target=run, args=(k, path)) for k, path in enumerate((EXAMPLE, OTHER))]
    for thread in threads:
        thread.start()
    for thread in threads:
        thread.join()
    for together, single in zip(answers, [alone[path][2][1] for path in (EXAMPLE, OTHER)], strict=True):
        assert together["state"] == "done"
        assert together["result"]["values"] == single["result"]["values"]
        assert together["result"]["pictures"]["target"] == single["result"]["pictures"]["target"]
    assert answers[0]["result"]["values"] != answers[1]["result"]["values"]


def watch_events(url: str, received: list, stop: threading.Event) -> None:
    with urllib.request.urlopen(url + "api/watch", timeout=30) as stream:
        for line in stream:
            if stop.is_set():
                return
            if line.startswith(b"data: "):
                received.append(json.loads(line[6:]))


def test_saving_the_watched_file_refits_it_and_deleting_it_is_a_410(url, watched, alone):
    received, stop = [], threading.Event()
    threading.Thread(target=watch_events, args=(url, received, stop), daemon=True).start()
    time.sleep(0.5)
    shutil.copy(OTHER, watched)
    deadline = time.monotonic() + 30
    while not received and time.monotonic() < deadline:
        time.sleep(0.05)
    assert received and received[0]["file"] == "edit.png"
    _, done = wait(url, received[0]["job"])
    expected = alone[OTHER][2][1]  # the same picture uploaded (under its own name: the values do not depend on it)
    assert done["state"] == "done" and done["result"]["values"] == expected["result"]["values"]
    os.unlink(watched)
    deadline = time.monotonic() + 30
    while len(received) < 2 and time.monotonic() < deadline:
        time.sleep(0.05)
    status, gone = wait(url, received[-1]["job"])
    stop.set()
    assert status == 410 and "was deleted: save it again" in gone["error"]
    shutil.copy(EXAMPLE, watched)


def test_a_half_written_watched_file_is_waited_for_not_reported(tmp_path):
    path = str(tmp_path / "edit.png")
    with open(EXAMPLE, "rb") as file:
        data = file.read()
    with open(path, "wb") as file:
        file.write(data[: len(data) // 2])

    def finish():
        time.sleep(0.5)
        with open(path, "wb") as file:
            file.write(data)

    threading.Thread(target=finish).start()
    assert run_to_end(settled(path)) is None


@pytest.mark.parametrize("extension", [".png", ".jpg", ".tif", ".exr"])
def test_a_whole_picture_is_read_at_once_and_one_cut_short_is_waited_for(tmp_path, monkeypatch, extension):
    # `settled` takes a picture that decodes without waiting for its size to hold: safe because a picture cut short
    # either fails to decode or, cut only in what follows its pixels (a TIFF's last tags), decodes to the same pixels
    whole = str(tmp_path / f"whole{extension}")
    images.write(whole, images.load(EXAMPLE).pixels[:48, :64])
    pixels = images.load(whole).pixels
    with open(whole, "rb") as file:
        data = file.read()
    failed = []
    for fraction in (0.99, 0.9, 0.6, 0.3):
        cut = str(tmp_path / f"cut-{fraction}{extension}")
        with open(cut, "wb") as file:
            file.write(data[: int(len(data) * fraction)])
        try:
            np.testing.assert_array_equal(images.load(cut).pixels, pixels)
        except ImageError as error:
            assert "damaged or truncated" in str(error) or "not an image OpenImageIO can read" in str(error)
            failed.append(cut)
    assert len(failed) >= 3
    waits, mine, sleep = [], set(), asyncio.sleep

    async def no_wait(seconds, *args, **kwargs):
        if threading.get_ident() not in mine:  # another loop in this worker (the page's server) sleeps as it would
            return await sleep(seconds, *args, **kwargs)
        waits.append(seconds)

    async def counted(coroutine):
        mine.add(threading.get_ident())
        return await coroutine

    monkeypatch.setattr(asyncio, "sleep", no_wait)
    monkeypatch.setattr(watch, "RETRY_SECONDS", 0.2)
    assert run_to_end(counted(settled(whole))) is None and waits == []  # no SETTLE_SECONDS for a whole picture
    assert run_to_end(counted(settled(failed[-1]))) is not None and waits  # a cut one is waited for, then refused


def test_a_port_in_use_is_refused_with_the_fix(url):
    port = int(url.rsplit(":", 1)[1].strip("/"))
    with pytest.raises(OutputError, match=f"cannot listen on 127.0.0.1:{port} .*choose another --port"):
        check_listen("127.0.0.1", port)


def test_bad_watch_paths_are_refused_with_the_fix(tmp_path):
    with pytest.raises(ImageError, match="is not a picture or a folder"):
        check_watch(str(tmp_path / "notes.txt"))
    with pytest.raises(ImageError, match="its folder does not exist"):
        check_watch(str(tmp_path / "missing" / "edit.png"))


# --- the page in a real browser ---------------------------------------------------------------------------------


@pytest.fixture(scope="module")
def browser():
    if not os.path.exists(CHROMIUM):
        pytest.skip(f"no browser: {CHROMIUM} is missing (apt-get install chromium; CI installs it)")
    playwright_api = pytest.importorskip(
        "playwright.sync_api", reason="Playwright is a dev extra: pip install -e .[dev]"
    )
    with playwright_api.sync_playwright() as playwright:
        browser = playwright.chromium.launch(executable_path=CHROMIUM, args=["--no-sandbox"])
        yield browser
        browser.close()


def open_page(browser, url):
    page = browser.new_page()
    page.goto(url)
    page.wait_for_selector("body[data-ready=yes]", timeout=30_000)
    return page


def fit_in_page(page, path):
    page.set_input_files("#picture", path)
    page.wait_for_function("document.getElementById('figures').textContent.includes('Mitsuba RMSE')", timeout=60_000)


def test_the_page_fits_an_upload_and_its_params_json_renders(browser, url, tmp_path):
    page = open_page(browser, url)
    fit_in_page(page, EXAMPLE)
    figures = page.text_content("#figures")
    assert figures.startswith("recoloured.png: neural RMSE") and "kept" in figures
    for name in ("target", "start", "neural", "mitsuba", "difference"):
        assert page.eval_on_selector(f"#pic-{name}", "img => img.complete && img.naturalWidth") == 32
    with page.expect_download() as download:
        page.click("#dl-params")
    saved = tmp_path / "params.json"
    download.value.save_as(saved)
    render = [sys.executable, "-m", "matfit", "render", str(saved), "--size", "16", "--spp", "4"]
    finished = subprocess.run([*render, "-o", str(tmp_path / "r.png")], capture_output=True, text=True, check=False)
    assert finished.returncode == 0, finished.stderr
    assert images.read(str(tmp_path / "r.png")).shape == (16, 16, 3)
    page.close()


def test_the_page_draws_the_ranges_and_a_look_alike_sets_the_sliders_and_the_preview(browser, url):
    page = open_page(browser, url)
    fit_in_page(page, EXAMPLE)
    bands = page.eval_on_selector_all(".band", "bands => bands.map(b => [b.hidden, b.dataset.verdict, b.offsetWidth])")
    assert len(bands) == params.COUNT
    assert all(
        not hidden and verdict in ("decided", "partly", "free") and width > 0 for hidden, verdict, width in bands
    )
    for name, (_, verdict, _) in zip(params.NAMES, bands, strict=True):
        assert page.get_attribute(f"#slider-{name}", "title").startswith(f"{verdict} by the picture")
    job = page.get_attribute("#figures", "data-job")
    alike = json.loads(request(f"{url}api/jobs/{job}")[1])["result"]["ranges"]["look_alikes"][0]
    assert page.text_content("#look-alikes button") == alike["label"]
    page.wait_for_function("Number(document.getElementById('preview').dataset.count || 0) >= 1")
    count, before = int(page.get_attribute("#preview", "data-count")), page.get_attribute("#preview", "src")
    page.click("#look-alikes button")
    page.wait_for_function(f"Number(document.getElementById('preview').dataset.count) > {count}")
    assert page.get_attribute("#preview", "src") != before
    for p, value in zip(params.PARAMETERS, alike["values"], strict=True):
        assert float(page.text_content(f"#value-{p.name}")) == pytest.approx(value, abs=5e-4 + 1e-9)  # toFixed(3)
        slider = float(page.eval_on_selector(f"#slider-{p.name}", "s => s.value"))
        assert slider == pytest.approx(value, abs=(p.high - p.low) / 1000)  # the slider's step
    # A starting point: the next fit sends the look-alike's values, which join its candidates.
    assert page.text_content("#init-note").startswith(f"look-alike {alike['label']}")
    page.set_input_files("#picture", EXAMPLE)
    page.wait_for_function(f"(document.getElementById('figures').dataset.job || '{job}') !== '{job}'", timeout=60_000)
    again = page.get_attribute("#figures", "data-job")
    assert json.loads(request(f"{url}api/jobs/{again}/files/params.json")[1])["init"] == "uploaded params.json"
    page.close()


def test_moving_a_slider_changes_the_preview(browser, url):
    page = open_page(browser, url)
    page.wait_for_function("Number(document.getElementById('preview').dataset.count || 0) >= 1")
    before = page.get_attribute("#preview", "src")
    count = int(page.get_attribute("#preview", "data-count"))
    page.fill("#slider-metallic", "1")  # fires `input`, as dragging does
    page.wait_for_function(f"Number(document.getElementById('preview').dataset.count) > {count}")
    assert page.get_attribute("#preview", "src") != before
    assert page.text_content("#value-metallic") == "1.000"
    page.close()


def test_the_page_follows_the_watched_file(browser, url, watched):
    page = open_page(browser, url)
    assert "watching" in page.text_content("#watching")
    shutil.copy(OTHER, watched)
    page.wait_for_function("document.getElementById('figures').textContent.startsWith('edit.png')", timeout=60_000)
    shutil.copy(EXAMPLE, watched)
    page.close()


@pytest.mark.slow
def test_a_broken_upload_shows_its_message_and_the_next_one_works(browser, url, tmp_path):
    page = open_page(browser, url)
    broken = tmp_path / "broken.png"
    broken.write_bytes(b"\x89PNG\r\n\x1a\n not a picture")
    page.set_input_files("#picture", str(broken))
    page.wait_for_selector("#error:not([hidden])")
    assert "the uploaded picture" in page.text_content("#error")
    fit_in_page(page, EXAMPLE)
    assert page.is_hidden("#error")
    page.close()


@pytest.mark.slow
def test_two_pages_fitting_at_once_each_show_their_own(browser, url):
    pages = [open_page(browser, url), open_page(browser, url)]
    pages[0].set_input_files("#picture", EXAMPLE)
    pages[1].set_input_files("#picture", OTHER)
    for page, name in zip(pages, ("recoloured.png", "desaturated.png"), strict=True):
        page.wait_for_function(f"document.getElementById('figures').textContent.startsWith('{name}')", timeout=60_000)
    assert pages[0].text_content("#figures") != pages[1].text_content("#figures")
    for page in pages:
        page.close()


@pytest.mark.slow
def test_the_page_benchmark_reports_every_figure():
    from matfit.app.bench import page

    # Two of each: every figure is a median of several, and each fit (verified in Mitsuba) costs seconds.
    table = page.serve_speed(random_model(), "memory", fits=2, previews=5, log=lambda _: None, samples=2)
    rows = table.splitlines()[2:]
    assert [row.split(" | ")[0] for row in rows] == [
        "| warm fit through the library, `matfit.Fitter.fit` (median of 2)",
        "| watched file saved -> first answer (the neural search's) read by the page's client (median of 2)",
        "| watched file saved -> result read by the page's client (median of 2)",
        "| the page's own: saved -> result less the library's fit of the same picture (median of 2)",
        "| slider -> neural preview round trip (median of 5)",
        "| resident memory after 2 fits / after 2",
    ]
    warm, first, latency = (float(row.split(" | ")[1].split()[0]) for row in rows[:3])
    # All are measured and positive; which of the fits is larger is a benchmark's finding, not the test's (on a
    # loaded machine the medians of 3 fits crossed: 4.75 s against 4.57 s). The first answer is read on the way.
    assert warm > 0 and 0 < first <= latency
    assert rows[5].endswith("(+0.0%) |")  # the same reading twice


def test_a_mask_painted_in_the_page_weights_the_fit(browser, url):
    page = open_page(browser, url)
    fit_in_page(page, EXAMPLE)
    unmasked = page.text_content("#figures")
    page.click("#masking summary")
    box = page.locator("#mask-view").bounding_box()
    page.mouse.move(box["x"] + 20, box["y"] + 20)
    page.mouse.down()
    page.mouse.move(box["x"] + 230, box["y"] + 230, steps=20)
    page.mouse.up()
    page.click("#mask-fit")
    page.wait_for_function("document.getElementById('figures').textContent.endsWith(', masked')", timeout=60_000)
    assert page.text_content("#figures") != unmasked + ", masked"  # other weights, other figures
    page.close()


def uploads_left(studio) -> set[str]:
    """Returns the uploads in the studio's private folder once the jobs that end meanwhile have removed theirs."""
    deadline = time.monotonic() + 10
    while (left := set(os.listdir(studio.folder)) - {"preview.png"}) and time.monotonic() < deadline:
        time.sleep(0.05)
    return left


def test_a_bad_mask_is_a_400_at_upload_naming_the_upload_and_leaves_no_copy(url, studio):
    # It was answered 202, then the job failed naming the server's private copy (/tmp/matfit-serve-.../tmpab.png).
    with open(EXAMPLE, "rb") as file:
        picture = file.read()
    small = images.encode(np.full((8, 8, 3), 1.0, np.float32), ".png")
    black = images.encode(np.zeros((256, 256, 3), np.float32), ".png")
    for mask, message in [
        (
            ("small.png", small),
            "the mask 'small.png' is 8x8, the target is 256x256: make the mask the same size as the target",
        ),
        (("black.png", black), "the mask 'black.png' is black everywhere: paint white where the fit should look"),
    ]:
        body, headers = multipart({"image": ("edit.png", picture), "mask": mask})
        code, answer = request(url + "api/fit", body, headers)
        assert code == 400 and json.loads(answer) == {"error": message}
    assert uploads_left(studio) == set()


def test_uploads_are_removed_when_refused_and_when_their_job_ends(url, studio):
    # Refused and accepted uploads stayed in the server's folder until it stopped.
    with open(EXAMPLE, "rb") as file:
        picture = file.read()
    refused = [
        {"image": ("broken.png", b"\x89PNG\r\n\x1a\n this is not the rest of a PNG")},
        {"image": ("program.png", b"\x7fELF\x02\x01\x01" + bytes(200))},
        {"image": ("edit.png", picture), "mask": ("mask.png", b"\x7fELF\x02\x01\x01" + bytes(200))},
        {"image": ("edit.png", picture), "init": '{"values": [1, 2]}'},
    ]
    for fields in refused:
        code, answer = request(url + "api/fit", *multipart(fields))
        assert code == 400, answer
    assert uploads_left(studio) == set()
    white = images.encode(np.ones((256, 256, 3), np.float32), ".png")
    body, headers = multipart({"image": ("edit.png", picture), "mask": ("mask.png", white)})
    code, answer = request(url + "api/fit", body, headers)
    assert code == 202 and wait(url, json.loads(answer)["job"])[1]["state"] == "done"
    assert uploads_left(studio) == set()


def test_a_new_server_removes_the_folders_of_servers_that_are_gone():
    # After `kill -9` the folder stayed for good, even after the next `serve`.
    script = (
        "from matfit.app.serve import uploads; import sys, time; folder = uploads.private_folder(); "
        f"uploads.save_upload(folder, open({EXAMPLE!r}, 'rb').read(), 'edit.png', 'picture'); "
        "print(folder, flush=True); time.sleep(60)"
    )
    server = subprocess.Popen([sys.executable, "-c", script], stdout=subprocess.PIPE, text=True)
    folder = server.stdout.readline().strip()
    assert len(os.listdir(folder)) == 1
    assert folder not in uploads.remove_orphans(os.path.dirname(folder))  # its server still runs: kept
    os.kill(server.pid, 9)
    server.wait()
    server.stdout.close()
    mine = uploads.private_folder()  # a new server: the folder of the one killed is gone, its own is made
    try:
        assert not os.path.exists(folder) and os.path.isdir(mine)
    finally:
        os.rmdir(mine)


def test_an_orphan_folder_holding_a_link_costs_no_one_a_file(tmp_path):
    precious = tmp_path / "precious.png"
    precious.write_bytes(b"someone's")
    dead = subprocess.Popen(["true"])
    dead.wait()
    folder = tmp_path / f"{uploads.FOLDER_PREFIX}{dead.pid}@{files.owner().partition('@')[2]}-abc123"
    folder.mkdir()
    (folder / "tmpab12cd.png").symlink_to(precious)
    (folder / "tmpef34gh.png").write_bytes(b"an upload")
    assert uploads.remove_orphans(str(tmp_path)) == []  # the link is not an upload: the folder stays
    assert precious.read_bytes() == b"someone's" and os.listdir(folder) == ["tmpab12cd.png"]


def test_every_api_error_is_json_naming_the_fix(url):
    # Starlette answered plain text ("Method Not Allowed", "Not Found") where every other error of the API is JSON.
    for path, data, status, message in [
        ("api/preview", None, 405, "GET /api/preview is not served: /api/preview takes POST"),
        ("api/parameters", b"", 405, "POST /api/parameters is not served: /api/parameters takes GET"),
        ("api/nowhere", None, 404, "no /api/nowhere here: open / for the page (its API: /api/parameters"),
        ("nowhere/else", b"", 404, "no /nowhere/else here"),
    ]:
        code, answer = request(url + path, data)
        assert code == status and json.loads(answer)["error"].startswith(message), answer


def test_a_whole_number_of_5000_digits_is_refused_for_what_it_is(url):
    # It was a 400 advising sys.set_int_max_str_digits(), a Python setting, not what is wrong with the value.
    gold = json.dumps(presets.preset("gold").tolist())
    body = ('{"values": ' + gold + ', "size": ' + "9" * 5000 + ', "spp": 4}').encode()
    code, answer = request(url + "api/render", body, {"Content-Type": "application/json"})
    message = json.loads(answer)["error"]
    assert code == 400 and message == (
        "the request: the whole number 999999999999... has 5000 digits, more than any value matfit takes: "
        "give one in the field's range"
    )


def test_the_init_field_takes_the_form_its_error_asks_for(url):
    # {"values": [19 numbers]}, the form VALUES_FIX names, was refused: only the bare list was taken.
    gold = presets.preset("gold").tolist()
    for init in (json.dumps({"values": gold}), json.dumps(gold)):
        code, answer = start_fit(url, EXAMPLE, init=init)
        assert code == 202, answer
        assert wait(url, answer["job"])[1]["state"] == "done"
    code, answer = start_fit(url, EXAMPLE, init=json.dumps({"values": gold[:18]}))
    assert code == 400 and answer["error"].startswith("values must be a list of 19 numbers")


def test_an_upload_over_the_byte_cap_is_a_413_saying_its_size_and_the_cap(url):
    # A 53.5 MB picture was "52 MB, more than 52 MB": the size counted was the part read, one byte over the cap.
    body, headers = multipart({"image": ("huge.png", bytes(int(53.5 * 2**20)))})
    code, answer = request(url + "api/fit", body, headers)
    assert code == 413
    assert json.loads(answer)["error"] == "the picture is 53.5 MB, more than the 50 MB an upload may be: scale it down"


def test_a_malformed_form_is_a_400_and_the_server_carries_on(url):
    headers = {"Content-Type": "multipart/form-data; boundary=xyz"}
    code, answer = request(url + "api/fit", b"--nonsense without an end", headers)
    assert code == 400 and "could not be read" in json.loads(answer)["error"]
    assert start_fit(url, EXAMPLE)[0] == 202


def test_a_truncated_jpeg_upload_is_a_400_before_it_is_queued(url, tmp_path):
    images.write(str(tmp_path / "edit.jpg"), images.read(EXAMPLE))
    data = (tmp_path / "edit.jpg").read_bytes()
    body, headers = multipart({"image": ("edit.jpg", data[: (data.index(b"\xff\xda") + len(data)) // 2])})
    code, answer = request(url + "api/fit", body, headers)
    message = json.loads(answer)["error"]
    assert code == 400 and message.startswith("the uploaded picture is damaged or truncated (JPEG error: Premature")
    assert message.endswith(": export it again") and "\n" not in message
    code, answer = start_fit(url, str(tmp_path / "edit.jpg"))
    assert code == 202 and wait(url, answer["job"])[1]["state"] == "done"


def test_json_nested_too_deeply_is_a_400_in_every_endpoint(url):
    deep = "[" * 100000
    code, answer = request(url + "api/preview", deep.encode(), {"Content-Type": "application/json"})
    assert code == 400 and json.loads(answer)["error"].startswith("the request is not valid JSON (nested too deeply")
    code, answer = request(url + "api/render", deep.encode(), {"Content-Type": "application/json"})
    assert code == 400 and "nested too deeply" in json.loads(answer)["error"]
    body, headers = multipart({"params": ("deep.json", deep.encode())})
    code, answer = request(url + "api/params", body, headers)
    assert code == 400 and json.loads(answer)["error"].startswith("deep.json is not valid JSON (nested too deeply")
    with open(EXAMPLE, "rb") as file:
        body, headers = multipart({"image": ("edit.png", file.read()), "init": deep})
    code, answer = request(url + "api/fit", body, headers)
    assert code == 400 and json.loads(answer)["error"].startswith("the init field is not valid JSON (nested")
    code, png = post_json(url + "api/preview", {"values": presets.preset("gold").tolist()})
    assert code == 200 and png.startswith(b"\x89PNG")


def call(app, path: str, chunks: list[bytes], headers: dict) -> tuple[int, dict, int]:
    """Returns (status, JSON answer, how many body chunks the app did not read) of a POST sent straight to the app."""
    messages = [{"type": "http.request", "body": chunk, "more_body": True} for chunk in chunks]
    messages.append({"type": "http.request", "body": b"", "more_body": False})
    sent = []

    async def receive():
        return messages.pop(0) if messages else {"type": "http.disconnect"}

    async def send(message):
        sent.append(message)

    scope = {
        "type": "http",
        "method": "POST",
        "path": path,
        "raw_path": path.encode(),
        "query_string": b"",
        "headers": [(key.lower().encode(), value.encode()) for key, value in headers.items()],
        "http_version": "1.1",
        "scheme": "http",
        "server": ("127.0.0.1", 80),
        "client": ("127.0.0.1", 1),
        "root_path": "",
    }
    run_to_end(app(scope, receive, send))
    body = b"".join(message.get("body", b"") for message in sent if message["type"] == "http.response.body")
    return sent[0]["status"], json.loads(body), len(messages)


def test_request_bodies_over_their_cap_are_a_413_and_not_read_beyond_it(studio):
    app = create_app(studio)
    json_type = {"Content-Type": "application/json"}
    chunks = [b'{"values": [', *[b"0.5, " * 20_000] * 60, b"0.5]}"]  # 6 MB, sent without a Content-Length
    status, answer, unread = call(app, "/api/preview", chunks, json_type)
    assert status == 413 and answer["error"] == (
        "the request body is more than 1 MB, the most it may be: "
        'send {"values": [19 numbers]}, one per parameter of `matfit params`'
    )
    assert unread >= 50  # counted as it arrived: refused once past 1 MB, the rest never read
    status, answer, unread = call(app, "/api/render", chunks, {**json_type, "Content-Length": "6000007"})
    assert status == 413 and unread == len(chunks) + 1  # its length said so: nothing read at all
    form = {"Content-Type": "multipart/form-data; boundary=xyz", "Content-Length": str(2 * 2**20)}
    status, answer, _ = call(app, "/api/params", [b"--xyz"], form)
    assert status == 413 and "choose a params.json that matfit wrote" in answer["error"]
    form["Content-Length"] = str(uploads.MAX_FIT_BYTES + 1)
    status, answer, _ = call(app, "/api/fit", [b"--xyz"], form)
    assert status == 413 and answer["error"].startswith(
        f"the request body is more than {uploads.MAX_FIT_BYTES / 2**20:g}"
    )
    body = json.dumps({"values": presets.preset("gold").tolist(), "size": 16, "spp": 1}).encode()
    status, _, _ = call(app, "/api/render", [body[:100], body[100:]], json_type)
    assert status == 202  # a body under the cap, in pieces, is read whole


def test_a_params_upload_is_read_as_the_command_line_reads_it(studio):
    # A byte order mark was refused by the page and accepted by `matfit render`; 30 000 keys held the event loop.
    app = create_app(studio)
    body, headers = multipart({"params": ("notepad.json", b'\xef\xbb\xbf{"roughness": 0.3}')})
    status, answer, _ = call(app, "/api/params", [body], headers)
    assert status == 200 and answer["values"][params.INDEX["roughness"]] == pytest.approx(0.3)
    many = ("{" + ", ".join(f'"k{i}": 0.5' for i in range(30_000)) + ', "k7": 0.5}').encode()
    body, headers = multipart({"params": ("many.json", many)})
    started = time.perf_counter()
    status, answer, _ = call(app, "/api/params", [body], headers)
    assert status == 400 and answer["error"] == "many.json: 'k7' given more than once: keep one value"
    assert time.perf_counter() - started < 5


def quiet(studio, seconds: float = 1.0, limit: float = 120) -> None:
    """Waits until every fit of the watched file has ended and no save of it is still on its way to the studio (no
    new one for `seconds`): an earlier test's last save of it, fitted late, holds a snapshot in the studio's folder
    and supersedes any watched job queued meanwhile."""
    deadline = time.monotonic() + limit
    while time.monotonic() < deadline:
        count = len(studio.watch_jobs)
        if all(studio.jobs[job].state not in ("queued", "running") for job in studio.watch_jobs):
            time.sleep(seconds)
            if len(studio.watch_jobs) == count:
                return
        time.sleep(0.05)
    raise AssertionError(f"the watched file's fits did not end in {limit} s")


def test_a_watched_file_deleted_before_its_fit_ends_the_job_with_a_410(url, studio, tmp_path):
    path = tmp_path / "edit.png"
    shutil.copy(EXAMPLE, path)
    quiet(studio)
    before = set(os.listdir(studio.folder))
    busy = threading.Event()
    studio.worker.submit(busy.wait, 60)  # the worker is busy: the watched file's fit waits in the queue
    job = studio.watched_change(str(path))
    os.unlink(path)
    busy.set()
    status, answer = wait(url, job.id)
    assert status == 410 and answer["state"] == "error"
    assert (
        answer["error"] == f"the watched file {path} was deleted before it was fitted: save it again from your editor"
    )
    assert set(os.listdir(studio.folder)) == before  # no snapshot left behind
