"""The gateway's web page in a real browser (Debian's chromium, headless, driven by Playwright)
against a real `rangeret serve` with a token and RANGERET_ROOT_PATH=/rangeret.

The real scan is dropped and drawn with the gateway's labels, counts and scores; its screenshot
shows the palette; an uploaded archive is followed to its report, the status line to the job's
end; the colour modes wrap inside their panel; the demo weights are named beside the model; the
token rule holds; the page works behind a reverse proxy's path prefix; the policy header is sent
and the console stays clean. With "find its objects", a scan is coloured by object and its objects
listed as the gateway found them, and a panoptic archive job shows its panoptic report.
The screenshots are kept in runs/page/ for a person to look at.
"""

from __future__ import annotations

import io
import re
import zipfile
from collections.abc import Iterator
from pathlib import Path

import httpx
import numpy as np
import pytest
from PIL import Image
from playwright.sync_api import Browser, Page, sync_playwright

from rangeret.dataset.labels import semantickitti
from rangeret.evaluation.metrics import ConfusionMatrix
from rangeret.io.scans import KITTI_RECORD, read_labels, read_scan, write_scan
from tests.support.browser import CHROMIUM_ARGS, PageLog, chromium_path, prefix_proxy
from tests.support.gateway import TOKEN, Gateway, gateway_env, start_gateway
from tests.support.paths import REPO, data_path
from tests.support.workers import build_tree, small_weights

pytestmark = pytest.mark.slow

SCREENSHOTS = REPO / "runs" / "page"
PREFIX = "/rangeret"
VIEWPORT = {"width": 1400, "height": 900}
#: The viewer's background (RGB), as page.css and scan-view.js draw it.
BACKGROUND = (0x10, 0x14, 0x18)


# The gateway, the data, the browser -------------------------------------------------------------


@pytest.fixture(scope="module")
def setup(tmp_path_factory) -> Iterator[dict]:
    """One gateway (token, path prefix) for the module, an archive of two labelled scans, a small
    scan, and the gateway's own JSON answer for the real scan."""
    base = tmp_path_factory.mktemp("page")
    weights = small_weights(base)
    tree = build_tree(base / "tree", labelled=2, unlabelled=0)
    archive = base / "sequence-08.zip"
    with zipfile.ZipFile(archive, "w") as zf:
        for path in sorted(tree.rglob("*")):
            if path.is_file():
                zf.write(path, path.relative_to(tree).as_posix())
    small = base / "small.bin"
    write_scan(
        small, read_scan(data_path("semantickitti-scan", "000000.bin"))[::7], record=KITTI_RECORD
    )
    env = gateway_env(base / "state", [base], RANGERET_ROOT_PATH=PREFIX)
    gw = start_gateway(weights, env, base / "gateway.log")
    try:
        with gw.client() as client:
            answer = client.post(
                "/v1/scans",
                content=data_path("semantickitti-scan", "000000.bin").read_bytes(),
                headers={"Content-Type": "application/octet-stream", "Accept": "application/json"},
            )
        assert answer.status_code == 200, answer.text
        yield {"gateway": gw, "archive": archive, "small": small, "answer": answer.json()}
    finally:
        gw.stop()


@pytest.fixture(scope="module")
def browser() -> Iterator[Browser]:
    with sync_playwright() as playwright:
        chromium = playwright.chromium.launch(executable_path=chromium_path(), args=CHROMIUM_ARGS)
        try:
            yield chromium
        finally:
            chromium.close()


@pytest.fixture
def page(browser: Browser) -> Iterator[tuple[Page, PageLog]]:
    """A fresh tab (its own sessionStorage) whose console errors and failed requests are kept."""
    context = browser.new_context(viewport=VIEWPORT, accept_downloads=True)
    tab = context.new_page()
    log = PageLog()
    log.watch(tab)
    try:
        yield tab, log
    finally:
        context.close()


def sign_in(tab: Page, token: str = TOKEN) -> None:
    tab.wait_for_selector("#sign-in:not([hidden])")
    tab.fill("#sign-in-form input[name=token]", token)
    tab.click("#sign-in-form button[type=submit]")


def state(tab: Page, part: str = "") -> object:
    """The page's own record of what it shows (`window.rangeretPage.state`)."""
    return tab.evaluate(f"() => window.rangeretPage.state{part}")


def shoot(tab: Page, name: str, capsys) -> Path:
    """A full-page screenshot kept in runs/page/, its path printed."""
    SCREENSHOTS.mkdir(parents=True, exist_ok=True)
    path = SCREENSHOTS / name
    tab.screenshot(path=str(path), full_page=True)
    with capsys.disabled():
        print(f"\n  screenshot: {path}")
    return path


def viewer_pixels(tab: Page) -> np.ndarray:
    """The 3D view's pixels (H, W, 3) as the screen shows them."""
    png = tab.locator("#viewer").screenshot()
    return np.asarray(Image.open(io.BytesIO(png)).convert("RGB"))


def pixels_of(pixels: np.ndarray, rgb: tuple[int, int, int], tolerance: int = 2) -> int:
    """How many pixels show the colour `rgb`."""
    diff = np.abs(pixels.astype(np.int16) - np.asarray(rgb, dtype=np.int16))
    return int((diff.max(axis=-1) <= tolerance).sum())


def hex_rgb(color: str) -> tuple[int, int, int]:
    return tuple(int(color[i : i + 2], 16) for i in (1, 3, 5))


# The page's headers --------------------------------------------------------------------------------


def test_the_page_carries_its_policy_and_cache_headers(setup):
    gw: Gateway = setup["gateway"]
    page = httpx.get(gw.url + "/")
    assert page.status_code == 200 and page.headers["content-type"].startswith("text/html")
    policy = page.headers["content-security-policy"]
    assert "default-src 'self'" in policy and "connect-src 'self'" in policy
    assert "unsafe-inline" not in policy and "unsafe-eval" not in policy
    assert page.headers["cache-control"] == "no-cache"
    assets = re.findall(r'(?:href|src)="\./(static/[^"]+)"', page.text)
    assets += re.findall(r'"\./(static/[^"]+\.js)"', page.text)  # the import map's targets
    assert any(a.endswith("three.module.js") for a in assets), assets
    for asset in assets:
        answer = httpx.get(f"{gw.url}/{asset}")
        assert answer.status_code == 200, asset
        assert answer.headers["cache-control"] == "public, max-age=31536000, immutable"
    stale = httpx.get(gw.url + "/static/0000000000000000/app/app.js")
    assert stale.status_code == 404 and stale.json()["detail"].endswith("reload the page.")


# The token rule ------------------------------------------------------------------------------------


def test_without_the_token_the_page_shows_the_sign_in_and_no_data(setup, page):
    tab, log = page
    requests: list[tuple[str, str | None]] = []
    tab.on("request", lambda r: requests.append((r.url, r.headers.get("authorization"))))
    tab.goto(setup["gateway"].url + "/")
    tab.wait_for_selector("#sign-in:not([hidden])")
    assert tab.is_hidden("#tabs") and tab.is_hidden("#sign-out")
    assert all(tab.is_hidden(f"#tab-{name}") for name in ("scan", "jobs", "health"))
    assert state(tab, ".signedIn") is False and state(tab, ".profile") is None
    assert tab.inner_text("#health") == "" and tab.inner_text("#served") == ""
    assert not [url for url, _ in requests if "/v1/" in url]

    sign_in(tab, "not-the-token")
    tab.wait_for_function(
        "() => document.getElementById('sign-in-error').textContent.includes('does not accept')"
    )
    assert tab.is_hidden("#tabs") and state(tab, ".profile") is None
    assert tab.evaluate("() => sessionStorage.getItem('rangeret.token')") is None

    sign_in(tab)
    tab.wait_for_selector("#tabs:not([hidden])")
    tab.click("nav button[data-tab=health]")
    tab.wait_for_selector("#health dd[data-field='labelled by']")
    assert tab.inner_text("#health dd[data-field='labelled by']") == "the gateway's own process"
    assert tab.inner_text("#health dd[data-field=model]") == "rangeret-cir"
    assert tab.inner_text("#health dd[data-field=profile]") == "semantickitti"
    assert state(tab, ".model")["demo_weights"] is False and tab.is_hidden("#model-note")
    assert tab.inner_text("#health dd[data-field='queue depth']") == "0"
    assert tab.evaluate("() => sessionStorage.getItem('rangeret.token')") == TOKEN
    assert tab.evaluate("() => localStorage.length") == 0
    api_calls = [(url, auth) for url, auth in requests if "/v1/" in url]
    assert api_calls and all(auth == f"Bearer {TOKEN}" for _, auth in api_calls)

    tab.reload()  # the same tab keeps its token
    tab.wait_for_selector("#tabs:not([hidden])")
    tab.click("#sign-out")
    tab.wait_for_selector("#sign-in:not([hidden])")
    assert tab.evaluate("() => sessionStorage.getItem('rangeret.token')") is None
    assert log.errors == [] and log.failed == []


# Label a scan ---------------------------------------------------------------------------------------


def test_the_real_scan_is_labelled_drawn_and_scored(setup, page, capsys):
    tab, log = page
    answer = setup["answer"]
    tab.goto(setup["gateway"].url + "/")
    sign_in(tab)
    tab.wait_for_selector("#tabs:not([hidden])")
    profile = state(tab, ".profile")
    scan = data_path("semantickitti-scan", "000000.bin")
    truth_path = data_path("semantickitti-scan", "000000.label")
    tab.set_input_files("#scan-files", [str(scan), str(truth_path)])
    tab.wait_for_function("() => window.rangeretPage.state.scan.rendered", timeout=180_000)
    shown = state(tab, ".scan")

    # What the page holds is what the gateway answered, and what the label file says.
    config = semantickitti()
    truth = read_labels(truth_path)
    predicted = np.asarray(answer["labels"], dtype=np.uint32)
    assert shown["points"] == answer["num_points"] == len(truth) == 123_389
    assert shown["drawnPoints"] == 123_389
    assert shown["classCounts"] == answer["class_counts"]
    names = config.class_names
    truth_counts = np.bincount(config.to_class(truth), minlength=config.num_classes)
    assert shown["truthCounts"] == {names[c]: int(n) for c, n in enumerate(truth_counts) if n}
    confusion = ConfusionMatrix.for_config(config=config)
    confusion.add(config.to_class(predicted), config.to_class(truth))
    scores = shown["scores"]
    assert scores["miou"] == pytest.approx(confusion.miou(), abs=1e-12)
    assert scores["accuracy"] == pytest.approx(confusion.accuracy(), abs=1e-12)
    assert scores["points"] == confusion.evaluated_points()
    iou = confusion.iou()
    assert scores["iou"] == pytest.approx({names[c]: iou[c] for c in confusion.include}, abs=1e-12)
    assert tab.locator("#iou-table tbody tr").count() == len(confusion.include)
    first_render_ms = shown["firstRenderMs"]

    # The picture: not blank, and in the profile's palette.
    palette = {cls["name"]: hex_rgb(cls["color"]) for cls in profile["classes"]}
    pixels = viewer_pixels(tab)
    drawn = pixels.shape[0] * pixels.shape[1] - pixels_of(pixels, BACKGROUND, tolerance=3)
    assert drawn > 0.05 * pixels.shape[0] * pixels.shape[1]
    frequent = [name for name, n in answer["class_counts"].items() if n >= 0.02 * len(truth)]
    assert len(frequent) >= 2
    for name in frequent:
        assert pixels_of(pixels, palette[name]) >= 50, name
    shoot(tab, "scan.png", capsys)

    tab.check("#color-modes input[value=truth]")
    truth_pixels = viewer_pixels(tab)
    common = [names[c] for c, n in enumerate(truth_counts) if n >= 0.02 * len(truth)]
    found = [name for name in common if pixels_of(truth_pixels, palette[name]) >= 50]
    assert len(found) >= 5 and len(found) >= len(common) - 1, (common, found)

    # Hiding a class takes its colour off the screen, and showing it brings it back.
    largest = max(answer["class_counts"], key=answer["class_counts"].get)
    tab.check("#color-modes input[value=prediction]")
    tab.uncheck(f"#legend input[data-class='{largest}']")
    assert state(tab, ".scan.hidden") == [largest]
    assert pixels_of(viewer_pixels(tab), palette[largest]) == 0
    tab.click("#show-all")
    assert pixels_of(viewer_pixels(tab), palette[largest]) >= 50

    tab.check("#color-modes input[value=error]")
    errors = viewer_pixels(tab)
    assert pixels_of(errors, (214, 39, 40)) >= 50 and pixels_of(errors, (160, 160, 160)) >= 50

    frame_ms = tab.evaluate("() => window.rangeretPage.scans.view.orbitFrames(60)")
    with capsys.disabled():
        print(
            f"\n  the real scan (123,389 points): dropped to first render in "
            f"{first_render_ms:.0f} ms (labelling included); orbiting, median "
            f"{frame_ms:.1f} ms per frame (headless chromium, software WebGL)"
        )
    assert log.errors == [] and log.failed == []


def test_a_scan_of_the_wrong_size_gets_one_sentence(setup, page, tmp_path):
    tab, log = page
    bad = tmp_path / "bad.bin"
    bad.write_bytes(b"\0" * 17)
    tab.goto(setup["gateway"].url + "/")
    sign_in(tab)
    tab.wait_for_selector("#tabs:not([hidden])")
    tab.set_input_files("#scan-files", str(bad))
    tab.wait_for_selector("#scan-status.error")
    text = tab.inner_text("#scan-status")
    assert text.startswith("bad.bin is not a scan") and text.endswith(".") and "17 bytes" in text
    assert state(tab, ".scan.rendered") is False
    assert log.errors == []


# Jobs -----------------------------------------------------------------------------------------------


def test_an_archive_job_from_upload_to_report(setup, page, capsys):
    tab, log = page
    gw: Gateway = setup["gateway"]
    tab.goto(gw.url + "/")
    sign_in(tab)
    tab.wait_for_selector("#tabs:not([hidden])")
    tab.click("nav button[data-tab=jobs]")
    tab.set_input_files("#archive-file", str(setup["archive"]))
    tab.click("#archive-form button[type=submit]")
    tab.wait_for_function(
        "() => window.rangeretPage.state.jobs.some((job) => job.kind === 'archive')"
    )
    job_id = next(j["id"] for j in state(tab, ".jobs") if j["kind"] == "archive")
    row = f"#jobs-table tr[data-job='{job_id}']"
    tab.wait_for_selector(f"{row}[data-state=succeeded]", timeout=180_000)
    assert "2 / 2" in tab.inner_text(row)
    # The status line follows the job it announced to its end.
    status = tab.inner_text("#jobs-status")
    shown = re.fullmatch(rf"Job {job_id[:8]} succeeded: 2 / 2 scans, mIoU (\d+\.\d) %\.", status)
    assert shown, status

    tab.click(f"{row} button:text-is('Report')")
    tab.wait_for_selector("#report-distance tbody tr")
    with gw.client() as client:
        report = client.get(f"/v1/jobs/{job_id}/report").json()
        plots = client.get(f"/v1/jobs/{job_id}").json()["plots"]
        png = client.get(f"/v1/jobs/{job_id}/plots/iou-by-distance.png")
        missing = client.get(f"/v1/jobs/{job_id}/plots/nothing.png")
    assert plots == ["confusion.png", "iou-by-distance.png", "iou.png", "miou-by-sequence.png"]
    assert png.headers["content-type"] == "image/png" and png.content.startswith(b"\x89PNG")
    assert missing.status_code == 404
    tab.wait_for_function(f"() => window.rangeretPage.state.report.plots.length === {len(plots)}")
    tab.wait_for_function(
        "() => [...document.querySelectorAll('#report-plots img')]"
        ".every((img) => img.complete && img.naturalWidth > 0 && img.hasAttribute('width'))"
    )
    # Every plot is drawn at one scale: shown width over its pixels' width alike.
    scales = tab.evaluate(
        "() => [...document.querySelectorAll('#report-plots img')]"
        ".map((img) => img.getBoundingClientRect().width / img.naturalWidth)"
    )
    assert len(scales) == len(plots) and max(scales) - min(scales) < 0.01, scales
    assert state(tab, ".report") == {
        "job": job_id,
        "miou": report["miou"],
        "sequences": ["08"],
        "bands": 6,
        "plots": plots,
    }
    sequences = tab.locator("#report-sequences tbody tr")
    assert sequences.count() == 1 and sequences.first.inner_text().startswith("08")
    bands = tab.locator("#report-distance tbody tr").all_inner_texts()
    assert [b.split()[0] for b in bands] == ["0-10", "10-20", "20-30", "30-40", "40-50", "50+"]
    assert tab.locator("#report-classes tbody tr").count() == len(report["iou"])
    assert float(shown.group(1)) == pytest.approx(100 * report["miou"], abs=0.051)
    overall = tab.inner_text("#report-overall")
    assert f"{100 * report['miou']:.1f}" in overall and "semantickitti" in overall
    shoot(tab, "job-report.png", capsys)

    with tab.expect_download() as download:
        tab.click(f"{row} a[data-download=predictions]")
    with zipfile.ZipFile(download.value.path()) as zf:
        labels = [n for n in zf.namelist() if n.endswith(".label")]
    assert labels == [
        "sequences/08/predictions/000000.label",
        "sequences/08/predictions/000001.label",
    ]
    assert log.errors == [] and log.failed == []


def test_a_dataset_job_is_started_from_the_page(setup, page):
    tab, log = page
    tab.goto(setup["gateway"].url + "/")
    sign_in(tab)
    tab.wait_for_selector("#tabs:not([hidden])")
    tab.click("nav button[data-tab=jobs]")
    tab.fill("#dataset-form input[name=dataset]", "missing")
    tab.select_option("#dataset-form select[name=split]", "valid")
    tab.click("#dataset-form button[type=submit]")
    tab.wait_for_selector("#jobs-status.error")
    assert tab.inner_text("#jobs-status") == (
        "There is no dataset folder at that path under the data roots."
    )
    tab.fill("#dataset-form input[name=dataset]", "tree")
    tab.select_option("#dataset-form select[name=split]", "")
    tab.fill("#dataset-form input[name=sequences]", "8")
    tab.click("#dataset-form button[type=submit]")
    tab.wait_for_function(
        "() => window.rangeretPage.state.jobs.some((job) => job.kind === 'dataset')"
    )
    job = next(j for j in state(tab, ".jobs") if j["kind"] == "dataset")
    assert job["sequences"] == ["08"]
    row = f"#jobs-table tr[data-job='{job['id']}']"
    tab.wait_for_selector(f"{row}[data-state=succeeded]", timeout=180_000)
    assert "2 / 2" in tab.inner_text(row)
    tab.click(f"{row} button:text-is('Remove')")
    tab.wait_for_selector(row, state="detached")
    # The 404 of the missing dataset was the gateway's answer to a request the page made.
    assert [f for f in log.failed if "/v1/jobs" in f] == [f"404 {setup['gateway'].url}/v1/jobs"]
    assert [e for e in log.errors if "404" not in e] == []


# Layout ---------------------------------------------------------------------------------------------


def test_the_colour_modes_wrap_inside_the_side_panel(setup, page):
    """At 1400 px the colour modes wrap as wholes (each button on one line with its words)
    inside their box and the side panel, and nothing overflows sideways."""
    tab, log = page
    tab.goto(setup["gateway"].url + "/")
    sign_in(tab)
    tab.wait_for_selector("#tab-scan:not([hidden])")
    boxes = tab.evaluate(
        """() => {
          const box = (node) => {
            const r = node.getBoundingClientRect();
            return { left: r.left, right: r.right, top: r.top, bottom: r.bottom };
          };
          const side = document.querySelector('.scan-side');
          const modes = document.getElementById('color-modes');
          return {
            page: [document.documentElement.scrollWidth, window.innerWidth],
            side: { ...box(side), scroll: side.scrollWidth, client: side.clientWidth },
            modes: box(modes),
            labels: [...modes.querySelectorAll('label')].map((label) => ({
              ...box(label),
              lines: label.getClientRects().length,
            })),
          };
        }"""
    )
    assert boxes["page"][0] <= boxes["page"][1] == VIEWPORT["width"]
    side, modes = boxes["side"], boxes["modes"]
    assert side["scroll"] <= side["client"]
    assert side["left"] <= modes["left"] and modes["right"] <= side["right"]
    assert len(boxes["labels"]) == 4  # prediction, objects, ground truth, error
    for label in boxes["labels"]:
        assert label["lines"] == 1, boxes["labels"]
        assert modes["left"] <= label["left"] and label["right"] <= modes["right"], label
        assert modes["top"] <= label["top"] and label["bottom"] <= modes["bottom"], label
    assert log.errors == []


# The demo weights -------------------------------------------------------------------------------------


def test_the_demo_weights_are_named_beside_the_model(browser, tmp_path, capsys):
    """A gateway on the bundled demo weights: the API says so, and the page shows it beside
    the model's name with how to serve a published model."""
    from rangeret.models.weights.demo import DEMO_CHECKPOINT

    env = gateway_env(tmp_path / "state", [tmp_path], token=None)
    gw = start_gateway(DEMO_CHECKPOINT, env, tmp_path / "gateway.log", net=["--device", "cpu"])
    context = browser.new_context(viewport=VIEWPORT)
    try:
        with gw.client(auth=False) as client:
            model = client.get("/v1/model").json()
        assert model["demo_weights"] is True and model["name"] == "rangeret-thesis"
        tab = context.new_page()
        log = PageLog()
        log.watch(tab)
        tab.goto(gw.url + "/")
        tab.wait_for_selector("#model-note:not([hidden])")
        tab.wait_for_function(
            "() => document.getElementById('served').textContent.includes('rangeret-thesis')"
        )
        note = tab.inner_text("#model-note")
        assert note == model["note"]
        assert note.startswith("Demo weights: trained on simulated scenes only")
        assert "--checkpoint rangeret-kitti-657" in note and "rangeret weights list" in note
        served = tab.locator("#served").bounding_box()
        shown = tab.locator("#model-note").bounding_box()
        # Beside the model's name: on its row, right after it.
        assert shown["x"] >= served["x"] + served["width"]
        assert (
            shown["y"] < served["y"] + served["height"]
            and served["y"] < shown["y"] + shown["height"]
        )
        assert shown["x"] + shown["width"] <= VIEWPORT["width"]
        shoot(tab, "demo-weights.png", capsys)
        assert log.errors == [] and log.failed == []
    finally:
        context.close()
        gw.stop()


# Behind a reverse proxy's path prefix ----------------------------------------------------------------


def test_the_page_works_under_a_path_prefix(setup, page):
    tab, log = page
    gw: Gateway = setup["gateway"]
    requests: list[str] = []
    tab.on("request", lambda r: requests.append(r.url))
    with prefix_proxy(gw.url, PREFIX) as base:
        assert base.endswith("/rangeret/")
        tab.goto(base)
        sign_in(tab)
        tab.wait_for_selector("#tabs:not([hidden])")
        tab.set_input_files("#scan-files", str(setup["small"]))
        tab.wait_for_function("() => window.rangeretPage.state.scan.rendered", timeout=120_000)
        assert state(tab, ".scan.points") == len(read_scan(setup["small"]))
        tab.click("nav button[data-tab=health]")
        tab.wait_for_selector("#health dd[data-field='labelled by']")
        static = [url for url in requests if "/static/" in url]
        assert any(url.endswith("three.module.js") for url in static)
        assert any(url.endswith("OrbitControls.js") for url in static)
        assert all(url.startswith(base) for url in requests), requests
        assert base + "v1/scans?model=default" in requests and base + "v1/jobs" in requests
        # uvicorn knows the prefix, so the API description names it as the server.
        servers = httpx.get(base + "openapi.json").json()["servers"]
        assert servers == [{"url": PREFIX}]
    assert log.errors == [] and log.failed == []


def test_the_api_page_comes_from_the_gateway_alone(setup, page):
    """`/docs` renders the operations with Swagger UI's files served by the gateway: no request
    leaves its origin, under a same-origin policy; every answer says nosniff."""
    tab, log = page
    gw: Gateway = setup["gateway"]
    requested: list[str] = []
    tab.on("request", lambda r: requested.append(r.url))
    tab.goto(gw.url + "/docs")
    tab.wait_for_selector(".opblock-summary-path", timeout=60_000)
    tab.wait_for_load_state("networkidle")
    paths = tab.locator(".opblock-summary-path").all_inner_texts()
    assert any("/v1/scans" in p for p in paths), paths
    assert requested and all(url.startswith(gw.url + "/") for url in requested), requested
    assert not log.errors and not log.failed, (log.errors, log.failed)
    docs = httpx.get(gw.url + "/docs")
    assert "default-src 'self'" in docs.headers["content-security-policy"]
    assert "http" not in docs.text.replace("http-equiv", "")
    for path in ("/docs", "/", "/healthz", "/v1/jobs", "/openapi.json", "/redoc", "/metrics"):
        answer = httpx.get(gw.url + path)
        assert answer.headers.get("x-content-type-options") == "nosniff", path
    assert httpx.get(gw.url + "/redoc").status_code == 404


def test_another_origins_page_cannot_start_a_job_on_a_gateway_without_a_token(
    setup, browser, tmp_path
):
    """A page served from another origin posts an archive to a loopback gateway without a token
    (`fetch` with `mode: "no-cors"`, as a form would): the browser marks it cross-site, the
    gateway answers 403, and no job is made. A script without a browser's headers still can."""
    import http.server
    import threading

    env = gateway_env(tmp_path / "state", [tmp_path], token=None)
    gw = start_gateway(small_weights(tmp_path), env, tmp_path / "gateway.log")
    archive = setup["archive"].read_bytes()
    evil = tmp_path / "evil"
    evil.mkdir()
    (evil / "index.html").write_text(
        "<!doctype html><html><body><script>\n"
        "window.sent = (async () => {\n"
        f"  const bytes = new Uint8Array({list(archive)});\n"
        "  const form = new FormData();\n"
        "  form.append('archive', new Blob([bytes]), 'evil.zip');\n"
        f"  await fetch('{gw.url}/v1/jobs', {{method: 'POST', mode: 'no-cors', body: form}});\n"
        "  return 'sent';\n"
        "})();\n"
        "</script></body></html>\n"
    )
    handler = lambda *a: http.server.SimpleHTTPRequestHandler(*a, directory=str(evil))  # noqa: E731
    server = http.server.ThreadingHTTPServer(("127.0.0.1", 0), handler)
    threading.Thread(target=server.serve_forever, daemon=True).start()
    context = browser.new_context()
    try:
        tab = context.new_page()
        statuses: list[int] = []
        tab.on("response", lambda r: statuses.append(r.status) if "/v1/jobs" in r.url else None)
        tab.goto(f"http://localhost:{server.server_address[1]}/index.html")
        assert tab.evaluate("() => window.sent") == "sent"
        tab.wait_for_timeout(500)
        with gw.client(auth=False) as client:
            assert client.get("/v1/jobs").json()["jobs"] == []
            made = client.post("/v1/jobs", files={"archive": ("a.zip", archive, "application/zip")})
            assert made.status_code == 202, made.text  # curl and scripts send no Origin
        assert statuses == [403], statuses
    finally:
        context.close()
        server.shutdown()
        gw.stop()


# Several models --------------------------------------------------------------------------------------


def test_the_page_labels_a_scan_with_the_model_chosen_in_its_selector(
    setup, page, tmp_path, capsys
):
    """A gateway of three models: the selector offers them, a scan dropped after choosing the
    second is labelled by it (its answer, not the default's), and a nuScenes `.pcd.bin` dropped
    after choosing the nuScenes model is drawn with its class indices as they are."""
    import torch

    from rangeret.models import build_model
    from tests.support.nuscenes import network, write_tree

    tab, _ = page
    torch.manual_seed(7)
    other = tmp_path / "other.pt"
    torch.save(build_model("rangeret-cir", 32, 256, num_classes=20, layers=1).state_dict(), other)
    models = tmp_path / "models.yaml"
    first = small_weights(tmp_path)
    models.write_text(f"default: first\nmodels:\n  first: {{checkpoint: {first}}}\n")
    models.write_text(models.read_text() + f"  second: {{checkpoint: {other}}}\n")
    torch.save(network(0).state_dict(), tmp_path / "nu.pt")
    nu = tmp_path / "nu.pt"
    models.write_text(models.read_text() + f"  nu: {{checkpoint: {nu}, profile: nuscenes}}\n")
    sweep = sorted(write_tree(tmp_path / "nu", {"scene-0061": 1}).rglob("*.pcd.bin"))[0]
    env = gateway_env(tmp_path / "state", [tmp_path])
    gw = start_gateway(None, env, tmp_path / "gateway.log", "--models", str(models))
    try:
        body = setup["small"].read_bytes()
        with gw.client() as client:
            answers = {
                name: client.post(
                    "/v1/scans",
                    params={"model": name, "format": "json"},
                    content=body,
                    headers={"Content-Type": "application/octet-stream"},
                ).json()
                for name in ("first", "second")
            }
            answers["nu"] = client.post(
                "/v1/scans",
                params={"model": "nu", "format": "json"},
                content=sweep.read_bytes(),
                headers={"Content-Type": "application/octet-stream"},
            ).json()
        assert answers["first"]["class_counts"] != answers["second"]["class_counts"]
        tab.goto(gw.url + "/")
        sign_in(tab)
        tab.wait_for_selector("#tabs:not([hidden])")
        assert tab.locator("#model-choice").is_visible()
        options = tab.locator("#model-select option")
        assert [options.nth(i).get_attribute("value") for i in range(options.count())] == [
            "first",
            "second",
            "nu",
        ]
        assert state(tab, ".modelId") == "first"
        tab.select_option("#model-select", "second")
        tab.wait_for_function("() => window.rangeretPage.state.modelId === 'second'")
        assert state(tab, ".model.id") == "second"
        tab.set_input_files("#scan-files", [str(setup["small"])])
        tab.wait_for_function("() => window.rangeretPage.state.scan.rendered", timeout=180_000)
        shown = state(tab, ".scan")
        assert shown["points"] == answers["second"]["num_points"]
        assert shown["classCounts"] == answers["second"]["class_counts"]
        shoot(tab, "second-model.png", capsys)
        tab.select_option("#model-select", "nu")
        tab.wait_for_function("() => window.rangeretPage.state.model.id === 'nu'")
        tab.set_input_files("#scan-files", [str(sweep)])
        tab.wait_for_function(
            "() => window.rangeretPage.state.scan.name.endsWith('.pcd.bin') && "
            "window.rangeretPage.state.scan.rendered",
            timeout=180_000,
        )
        shown = state(tab, ".scan")
        assert shown["points"] == answers["nu"]["num_points"]
        assert len(answers["nu"]["class_counts"]) > 1
        assert shown["classCounts"] == answers["nu"]["class_counts"]
    finally:
        gw.stop()


# Panoptic: objects ---------------------------------------------------------------------------------


@pytest.fixture(scope="module")
def panoptic(setup, tmp_path_factory) -> Iterator[dict]:
    """A gateway of random weights that find dozens of objects in the real scan, and its own
    JSON answer with `panoptic=true` for the small scan."""
    from tests.service.panoptic_weights import panoptic_weights

    base = tmp_path_factory.mktemp("page-panoptic")
    env = gateway_env(base / "state", [base])
    gw = start_gateway(panoptic_weights(base), env, base / "gateway.log")
    try:
        with gw.client() as client:
            answer = client.post(
                "/v1/scans",
                params={"panoptic": "true", "format": "json"},
                content=setup["small"].read_bytes(),
                headers={"Content-Type": "application/octet-stream"},
            )
        assert answer.status_code == 200, answer.text
        yield {"gateway": gw, "answer": answer.json()}
    finally:
        gw.stop()


def _rgb(css: str) -> tuple[int, int, int]:
    """An `rgb(r, g, b)` colour of the computed style."""
    return tuple(int(v) for v in re.findall(r"\d+", css)[:3])


def test_a_panoptic_scan_is_coloured_by_object_and_its_objects_are_listed(
    setup, panoptic, page, capsys
):
    tab, log = page
    answer = panoptic["answer"]
    objects = answer["objects"]
    assert len(objects) > 5
    tab.goto(panoptic["gateway"].url + "/")
    sign_in(tab)
    tab.wait_for_selector("#panoptic-choice:not([hidden])")
    tab.check("#panoptic")
    tab.set_input_files("#scan-files", [str(setup["small"])])
    tab.wait_for_function("() => window.rangeretPage.state.scan.rendered", timeout=180_000)
    shown = state(tab, ".scan")
    assert shown["objects"] == objects and shown["mode"] == "objects"
    assert shown["classCounts"] == answer["class_counts"]
    assert tab.is_checked("#color-modes input[value=objects]")
    assert tab.inner_text("#objects-title") == f"Objects ({len(objects)})"
    assert tab.locator("#object-list tbody tr").count() == len(objects)
    largest = max(objects, key=lambda o: o["points"])
    row = tab.locator(f"#object-list tr[data-object='{largest['instance']}']")
    assert row.inner_text().split() == [
        str(largest["instance"]),
        largest["class_name"],
        f"{largest['points']:,}",
    ]
    color = _rgb(
        row.locator(".swatch").evaluate("(node) => getComputedStyle(node).backgroundColor")
    )
    shoot(tab, "panoptic-scan.png", capsys)

    # Thing points take their object's colour, the others their class's.
    profile = state(tab, ".profile")
    palette = {cls["name"]: hex_rgb(cls["color"]) for cls in profile["classes"]}
    stuff = [n for n in answer["class_counts"] if n not in profile["panoptic"]["things"]]
    by_object = viewer_pixels(tab)
    assert pixels_of(by_object, color) >= 10
    common = max(stuff, key=answer["class_counts"].get)
    assert pixels_of(by_object, palette[common]) >= 50
    swatches = tab.locator("#object-list .swatch").evaluate_all(
        "(nodes) => nodes.map((node) => getComputedStyle(node).backgroundColor)"
    )
    assert len({_rgb(c) for c in swatches}) >= len(objects) - 1  # a colour per object, nearly
    tab.check("#color-modes input[value=prediction]")
    assert pixels_of(viewer_pixels(tab), color) < pixels_of(by_object, color)
    assert log.errors == [] and log.failed == []


def test_a_panoptic_archive_job_shows_its_panoptic_report(setup, panoptic, page, capsys):
    tab, log = page
    gw: Gateway = panoptic["gateway"]
    tab.goto(gw.url + "/")
    sign_in(tab)
    tab.wait_for_selector("#tabs:not([hidden])")
    tab.click("nav button[data-tab=jobs]")
    tab.set_input_files("#archive-file", str(setup["archive"]))
    tab.check("#archive-form input[name=panoptic]")
    tab.click("#archive-form button[type=submit]")
    tab.wait_for_function("() => window.rangeretPage.state.jobs.some((job) => job.panoptic)")
    job_id = next(j["id"] for j in state(tab, ".jobs") if j["panoptic"])
    row = f"#jobs-table tr[data-job='{job_id}']"
    tab.wait_for_selector(f"{row}[data-state=succeeded]", timeout=180_000)
    assert "archive, panoptic" in tab.inner_text(row)
    status = tab.inner_text("#jobs-status")
    pattern = rf"Job {job_id[:8]} succeeded: 2 / 2 scans, mIoU \d+\.\d %, PQ \d+\.\d %\."
    assert re.fullmatch(pattern, status), status
    tab.click(f"{row} button:text-is('Report')")
    tab.wait_for_selector("#report-distance tbody tr")
    with gw.client() as client:
        report = client.get(f"/v1/jobs/{job_id}/report").json()
    shown = state(tab, ".report")
    assert shown["panoptic"] is True and shown["job"] == job_id
    assert shown["pq"] == report["pq_mean"] == report["headline"]["pq"]
    assert shown["miou"] == report["iou_mean"] and shown["sequences"] == ["08"]
    assert shown["bands"] == 6 and shown["plots"] == []
    assert tab.locator("#report-classes tbody tr").count() == len(report["classes"])
    things = set(state(tab, ".profile.panoptic.things"))
    marked = tab.locator("#report-classes tr[data-thing=true]").count()
    assert marked == len(things & set(report["classes"])) > 0
    overall = tab.inner_text("#report-overall")
    assert f"{100 * report['pq_mean']:.1f}" in overall and "semantickitti-panoptic" in overall
    shoot(tab, "panoptic-report.png", capsys)
    # A nuScenes-panoptic report's parts (`all`, then a key per class) read the same way.
    devkit = {
        "min_m": 0,
        "max_m": 10,
        "all": {"PQ": 0.5, "SQ": 0.6, "RQ": 0.7, "mIoU": 0.4, "PQ_dagger": 0.45},
        "car": {"PQ": 0.9, "SQ": 0.95, "RQ": 0.92, "IoU": 0.8},
    }
    read = tab.evaluate(
        """async (part) => {
          const app = document.querySelector('script[type=module]').src;
          const { panopticScores } = await import(app.replace(/app\\.js$/, 'report.js'));
          return panopticScores(part);
        }""",
        devkit,
    )
    assert read == {
        "pq": 0.5,
        "sq": 0.6,
        "rq": 0.7,
        "pq_dagger": 0.45,
        "miou": 0.4,
        "classes": {"car": {"pq": 0.9, "sq": 0.95, "rq": 0.92, "iou": 0.8}},
    }
    assert log.errors == [] and log.failed == []
