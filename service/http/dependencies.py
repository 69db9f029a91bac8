"""What the routes get from FastAPI: the request's `Gateway`, its job manager, and the token check."""

from __future__ import annotations

import hmac
from typing import Annotated

from fastapi import Depends, Request
from fastapi.security import HTTPAuthorizationCredentials, HTTPBearer

from service.gateway import Gateway
from service.http.errors import ApiError
from service.jobs import JobManager

BEARER = HTTPBearer(auto_error=False, description="the gateway's RANGERET_API_TOKEN")


async def get_gateway(request: Request) -> Gateway:
    """The gateway of the app serving this request (set by `create_app`)."""
    return request.app.state.gateway


GatewayDep = Annotated[Gateway, Depends(get_gateway)]


async def get_jobs(gateway: GatewayDep) -> JobManager:
    """The gateway's job manager; 503 while the gateway is still starting."""
    return gateway.manager()


JobsDep = Annotated[JobManager, Depends(get_jobs)]


def token_matches(gateway: Gateway, credentials: HTTPAuthorizationCredentials | None) -> bool:
    """Whether the request carries the gateway's bearer token (compared in constant time)."""
    token = gateway.settings.token
    if token is None or credentials is None:
        return False
    return hmac.compare_digest(credentials.credentials.encode(), token.encode())


async def require_token(
    gateway: GatewayDep,
    credentials: Annotated[HTTPAuthorizationCredentials | None, Depends(BEARER)],
) -> None:
    """401 unless the request carries `Authorization: Bearer <the gateway's token>`.

    The token is compared in constant time; a gateway without a token lets every request through.
    """
    token = gateway.settings.token
    if token is None:
        return
    if credentials is None:
        raise ApiError(
            401,
            "This endpoint needs the header 'Authorization: Bearer <token>'.",
            {"WWW-Authenticate": "Bearer"},
        )
    if not token_matches(gateway, credentials):
        raise ApiError(401, "The bearer token is wrong.", {"WWW-Authenticate": "Bearer"})
