"""The gateway's HTTP plumbing: error answers and their handlers, who may address it, security
headers, uvicorn's protocol, request bodies under limits, the routes' dependencies and the
Prometheus metrics."""
