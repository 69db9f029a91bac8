"""The web page's files and routes in process: versioned static files, the policy's import-map
hash, the 503 that names the build command while the page is not built (the API still served),
GET /v1/profile under the token rule, and the root path setting."""

from __future__ import annotations

import base64
import hashlib
import os
import re
import shutil
from pathlib import Path

import pytest
from fastapi.testclient import TestClient

from rangeret.dataset.profiles import load_profile
from service.app import create_app
from service.page_assets import (
    BUILD_COMMAND,
    VENDOR_FILES,
    WEB_DIR,
    PageFiles,
    PageNotBuilt,
    load_page_assets,
)
from service.server import settings_from_args
from service.settings import Settings
from tests.support.apps import one_model, pooled

TOKEN = "page-test-token"
AUTH = {"Authorization": f"Bearer {TOKEN}"}


class FakeWorker:
    """A healthy scan worker that is never asked to label here."""

    def label_requests(self, requests):
        raise AssertionError("no scan is labelled in these tests")

    def info(self):
        return {"pid": os.getpid()}


class FakeExecutor:
    """Never asked to run a job here."""

    backend = "fake"
    precision = "fp32"

    def predict(self, entries, dataset, sequences, out, progress, cancel, model=None):
        raise AssertionError("no job runs in these tests")


@pytest.fixture(scope="module")
def built() -> Path:
    """The page's sources with its installed npm packages (`make web`)."""
    if not all((WEB_DIR / "node_modules" / name).is_file() for name in VENDOR_FILES):
        pytest.fail(f"The web page is not built: run '{BUILD_COMMAND}'.")
    return WEB_DIR


def _unbuilt_copy(tmp_path: Path) -> Path:
    """The page's sources without node_modules, as in a fresh clone."""
    web = tmp_path / "web"
    shutil.copytree(WEB_DIR, web, ignore=shutil.ignore_patterns("node_modules"))
    return web


def _app(tmp_path: Path, token: str | None = TOKEN, web: Path | None = None):
    settings = Settings(state_dir=tmp_path / "state", api_token=token)
    app = create_app(
        settings,
        pooled(FakeWorker()),
        FakeExecutor(),
        models=one_model(load_profile("semantickitti")),
    )
    if web is not None:
        app.state.gateway.page = PageFiles(web)
    return app


def test_assets_are_versioned_by_their_contents(built, tmp_path):
    assets = load_page_assets(built)
    assert re.fullmatch(r"[0-9a-f]{16}", assets.version)
    assert set(VENDOR_FILES) <= set(assets.files)
    assert {"app/app.js", "app/page.css", "app/scan-view.js"} <= set(assets.files)
    html = assets.html.decode()
    # Every file the HTML names is served under its version, and nothing else is named.
    named = re.findall(r'"\./static/([0-9a-f]{16})/([^"]+?)/?"', html)
    assert named and {version for version, _ in named} == {assets.version}
    for _, path in named:
        assert path in assets.files or path == "three/examples/jsm", path
    assert load_page_assets(built).version == assets.version
    # A change to any file gives another version.
    copy = tmp_path / "web"
    shutil.copytree(built, copy)
    (copy / "src" / "page.css").write_text((copy / "src" / "page.css").read_text() + "\n/* */\n")
    assert load_page_assets(copy).version != assets.version


def test_the_policy_allows_the_import_map_by_its_hash_and_nothing_inline(built):
    assets = load_page_assets(built)
    html = assets.html.decode()
    blocks = re.findall(r"<script([^>]*)>(.*?)</script>", html, flags=re.S)
    inline = [(attrs, body) for attrs, body in blocks if body.strip()]
    assert len(inline) == 1 and 'type="importmap"' in inline[0][0]
    digest = base64.b64encode(hashlib.sha256(inline[0][1].encode()).digest()).decode()
    assert f"'sha256-{digest}'" in assets.csp
    directives = dict(d.split(" ", 1) for d in assets.csp.split("; "))
    assert directives["default-src"] == "'self'"
    assert directives["script-src"] == f"'self' 'sha256-{digest}'"
    assert directives["style-src"] == "'self'" and directives["connect-src"] == "'self'"
    # No inline styles or event handlers either: the policy would refuse them.
    assert "<style" not in html and not re.search(r"<[^>]*\s(style|on[a-z]+)=", html)


def test_the_page_and_its_files_are_served_with_their_headers(built, tmp_path):
    assets = load_page_assets(built)
    with TestClient(_app(tmp_path)) as client:
        page = client.get("/")
        assert page.status_code == 200 and page.headers["cache-control"] == "no-cache"
        assert page.headers["content-security-policy"] == assets.csp
        assert page.headers["x-content-type-options"] == "nosniff"
        module = client.get(f"/static/{assets.version}/three/build/three.module.js")
        assert module.status_code == 200
        assert module.headers["content-type"] == "text/javascript; charset=utf-8"
        assert module.headers["cache-control"] == "public, max-age=31536000, immutable"
        assert module.content == (built / "node_modules/three/build/three.module.js").read_bytes()
        assert (
            client.get(f"/static/{assets.version}/app/page.css")
            .headers["content-type"]
            .startswith("text/css")
        )
        for path in (
            f"/static/{'0' * 16}/app/app.js",  # another version
            f"/static/{assets.version}/app/missing.js",
            f"/static/{assets.version}/three/package.json",  # installed, but not served
        ):
            answer = client.get(path)
            assert answer.status_code == 404, path
            assert answer.json() == {
                "detail": "There is no such page file in this version of the page; reload the page."
            }
        # The page's routes are no part of the API description.
        paths = client.get("/openapi.json").json()["paths"]
        assert "/" not in paths and not [p for p in paths if p.startswith("/static")]


def test_without_the_npm_packages_the_api_runs_and_the_page_names_the_build(built, tmp_path):
    web = _unbuilt_copy(tmp_path)
    with pytest.raises(PageNotBuilt):
        load_page_assets(web)
    with TestClient(_app(tmp_path, web=web), headers=AUTH) as client:
        page = client.get("/")
        assert page.status_code == 503
        detail = page.json()["detail"]
        assert f"run '{BUILD_COMMAND}'" in detail and detail.endswith(".")
        assert "\n" not in detail and detail[0].isupper()
        assert client.get("/v1/profile").status_code == 200
        assert client.get("/healthz").status_code == 200
        # Installing the packages is enough: the running gateway serves the page then.
        shutil.copytree(built / "node_modules", web / "node_modules")
        assert client.get("/").status_code == 200


def test_the_profile_endpoint_follows_the_token_rule_and_describes_the_profile(tmp_path):
    with TestClient(_app(tmp_path)) as client:
        refused = client.get("/v1/profile")
        assert refused.status_code == 401 and refused.headers["www-authenticate"] == "Bearer"
        body = client.get("/v1/profile", headers=AUTH).json()
    labels = load_profile(None).labels
    assert body["profile"] == "semantickitti" and body["point_bytes"] == 16
    assert body["point_fields"] == ["x", "y", "z", "remission"]
    assert [c["name"] for c in body["classes"]] == list(labels.class_names)
    car = body["classes"][1]
    # The label configuration keeps BGR (245, 150, 100) for car; the page gets RGB.
    assert car == {"index": 1, "name": "car", "raw_id": 10, "color": "#6496f5", "ignored": False}
    assert body["classes"][0]["ignored"] is True and body["unlabeled_class"] == 0
    assert {int(k): v for k, v in body["raw_to_class"].items()} == labels.raw_to_class
    assert body["raw_to_class"]["252"] == 1  # moving-car scores as car

    pandaset = load_profile("pandaset")
    settings = Settings(state_dir=tmp_path / "panda", api_token=None)
    with TestClient(
        create_app(settings, pooled(FakeWorker()), FakeExecutor(), models=one_model(pandaset)),
        base_url="http://localhost",  # a gateway without a token answers to loopback names only
    ) as client:
        body = client.get("/v1/profile").json()
    assert body["profile"] == "pandaset" and body["point_bytes"] == 20
    assert body["unlabeled_class"] == pandaset.labels.unlabeled_class == 14
    assert body["classes"][0]["name"] == "car" and not body["classes"][0]["ignored"]


def test_the_root_path_setting(monkeypatch):
    assert Settings(root_path="/rangeret/").root_path == "/rangeret"
    assert Settings().root_path == ""
    with pytest.raises(ValueError, match="starts with '/'"):
        Settings(root_path="rangeret")
    monkeypatch.setenv("RANGERET_ROOT_PATH", "/from-env")
    from rangeret.cli.main import build_parser

    args = build_parser().parse_args(["serve", "--root-path", "/proxy/rangeret"])
    assert settings_from_args(args).root_path == "/proxy/rangeret"
    assert settings_from_args(build_parser().parse_args(["serve"])).root_path == "/from-env"
    with pytest.raises(Exception, match="root_path"):
        settings_from_args(build_parser().parse_args(["serve", "--root-path", "no slash"]))
