"""The web page's files: its HTML, its own modules and styles, the three.js modules it imports,
and the API page (`/docs`: Swagger UI, from the gateway itself).

The page's own files live in `service/web/src`; three.js and Swagger UI come from the npm packages
installed into `service/web/node_modules` by `make web` (`npm ci`, pinned by
`service/web/package-lock.json`).
Every file is served under `static/<version>/`, where the version is a hash of all their
contents, so they can be cached for good; the HTML names that version and is never cached. The
HTML's import map (an inline script) is allowed by its hash in the Content-Security-Policy,
which otherwise allows only the gateway's own origin. Without the installed package the page is
not built: the API still runs, and `/` says which command builds it.
"""

from __future__ import annotations

import base64
import hashlib
import re
import threading
from dataclasses import dataclass
from pathlib import Path

#: Where the page's sources and its installed npm packages live.
WEB_DIR = Path(__file__).resolve().parent / "web"
#: The command that installs the page's npm packages.
BUILD_COMMAND = "make web"
#: The three.js files the page imports, relative to `node_modules` (three.module.js imports
#: three.core.js; OrbitControls imports "three", which the import map resolves).
VENDOR_FILES = (
    "three/build/three.module.js",
    "three/build/three.core.js",
    "three/examples/jsm/controls/OrbitControls.js",
    "swagger-ui-dist/swagger-ui-bundle.js",
    "swagger-ui-dist/swagger-ui.css",
)
#: Content types of the page's files, by suffix.
MEDIA_TYPES = {
    ".js": "text/javascript; charset=utf-8",
    ".css": "text/css; charset=utf-8",
    ".svg": "image/svg+xml",
}
#: The placeholder of the version segment in `index.html`.
VERSION_MARK = "%VERSION%"
_IMPORT_MAP = re.compile(r'<script type="importmap">(.*?)</script>', re.S)


class PageNotBuilt(Exception):
    """The page's npm packages are not installed, so the page cannot be served."""


@dataclass(frozen=True)
class Asset:
    """One served file: its bytes and content type."""

    body: bytes
    media_type: str


@dataclass(frozen=True)
class PageAssets:
    """The HTML, its Content-Security-Policy, and every static file by its path under the version."""

    version: str
    html: bytes
    csp: str
    files: dict[str, Asset]
    #: The API page (`/docs`) and its policy.
    docs_html: bytes = b""
    docs_csp: str = ""


def content_security_policy(html: str, inline_styles: bool = False) -> str:
    """The page's policy: its own origin only, and the import map of `html` by its SHA-256;
    `inline_styles` lets the API page's Swagger UI set the style attributes it renders."""
    scripts = ["'self'"]
    for block in _IMPORT_MAP.findall(html):
        digest = base64.b64encode(hashlib.sha256(block.encode()).digest()).decode()
        scripts.append(f"'sha256-{digest}'")
    return "; ".join(
        [
            "default-src 'self'",
            f"script-src {' '.join(scripts)}",
            "style-src 'self' 'unsafe-inline'" if inline_styles else "style-src 'self'",
            "img-src 'self' data: blob:",
            "connect-src 'self'",
            "object-src 'none'",
            "base-uri 'none'",
            "form-action 'self'",
            "frame-ancestors 'none'",
        ]
    )


def _media_type(path: Path) -> str:
    try:
        return MEDIA_TYPES[path.suffix]
    except KeyError:
        raise ValueError(f"the page file {path.name} is of no served kind") from None


def load_page_assets(web_dir: Path = WEB_DIR) -> PageAssets:
    """Read the page's files and the vendor modules, and version them by their contents.

    Raises PageNotBuilt when an npm package file is missing.
    """
    files: dict[str, Asset] = {}
    for path in sorted((web_dir / "src").iterdir()):
        if path.is_file():
            files[f"app/{path.name}"] = Asset(path.read_bytes(), _media_type(path))
    for name in VENDOR_FILES:
        path = web_dir / "node_modules" / name
        if not path.is_file():
            raise PageNotBuilt(
                f"The web page is not built ({name} is missing under {web_dir}/node_modules): "
                f"run '{BUILD_COMMAND}' (npm ci in service/web)."
            )
        files[name] = Asset(path.read_bytes(), _media_type(path))
    digest = hashlib.sha256()
    for name, asset in files.items():
        digest.update(name.encode() + b"\0" + hashlib.sha256(asset.body).digest())
    version = digest.hexdigest()[:16]
    html = (web_dir / "index.html").read_text(encoding="utf-8").replace(VERSION_MARK, version)
    docs = (web_dir / "docs.html").read_text(encoding="utf-8").replace(VERSION_MARK, version)
    return PageAssets(
        version,
        html.encode(),
        content_security_policy(html),
        files,
        docs.encode(),
        content_security_policy(docs, inline_styles=True),
    )


class PageFiles:
    """The page's assets, read once they are there: a gateway started before `make web` serves
    the page as soon as the packages are installed."""

    def __init__(self, web_dir: Path = WEB_DIR) -> None:
        self.web_dir = web_dir
        self._assets: PageAssets | None = None
        self._lock = threading.Lock()

    @property
    def loaded(self) -> PageAssets | None:
        """The assets once read, else None (reading them is `get`'s work)."""
        return self._assets

    def get(self) -> PageAssets:
        """The assets; raises PageNotBuilt while the npm packages are not installed."""
        with self._lock:
            if self._assets is None:
                self._assets = load_page_assets(self.web_dir)
            return self._assets
