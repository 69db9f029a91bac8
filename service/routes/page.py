"""The web page at `/`, the API page at `/docs`, and their static files under `static/<version>/`.

The page holds no data: it needs no token, and asks for one where the gateway has one (the API
calls it makes carry it). The HTML is never cached and carries the Content-Security-Policy; the
static files are versioned by their contents and cached for good. Every URL in the page is
relative, so it works behind a reverse proxy's path prefix (RANGERET_ROOT_PATH).
"""

from __future__ import annotations

import asyncio

from fastapi import APIRouter
from fastapi.responses import Response

from service.http.dependencies import GatewayDep
from service.http.errors import ApiError
from service.page_assets import PageAssets, PageNotBuilt

router = APIRouter(include_in_schema=False)

#: Cache-Control of the versioned static files, and of the HTML that names their version.
IMMUTABLE = "public, max-age=31536000, immutable"
NO_CACHE = "no-cache"


async def _assets(gw: GatewayDep) -> PageAssets:
    """The page's assets; 503 naming the build command while they are not built."""
    if gw.page.loaded is not None:
        return gw.page.loaded
    try:
        return await asyncio.to_thread(gw.page.get)
    except PageNotBuilt as exc:
        raise ApiError(503, str(exc)) from exc


def _html(body: bytes, csp: str) -> Response:
    """A page's HTML: never cached, under its Content-Security-Policy."""
    return Response(
        body,
        media_type="text/html; charset=utf-8",
        headers={
            "Content-Security-Policy": csp,
            "Cache-Control": NO_CACHE,
            "Referrer-Policy": "no-referrer",
        },
    )


@router.get("/")
async def page(gw: GatewayDep) -> Response:
    assets = await _assets(gw)
    return _html(assets.html, assets.csp)


@router.get("/docs")
async def api_page(gw: GatewayDep) -> Response:
    """Swagger UI over the gateway's OpenAPI description, every file from the gateway itself."""
    assets = await _assets(gw)
    return _html(assets.docs_html, assets.docs_csp)


@router.get("/static/{version}/{path:path}")
async def static_file(version: str, path: str, gw: GatewayDep) -> Response:
    assets = await _assets(gw)
    asset = assets.files.get(path) if version == assets.version else None
    if asset is None:
        raise ApiError(
            404, "There is no such page file in this version of the page; reload the page."
        )
    return Response(
        asset.body,
        media_type=asset.media_type,
        headers={"Cache-Control": IMMUTABLE},
    )
