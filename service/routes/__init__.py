"""The gateway's endpoints, one module per resource, each a module-level `APIRouter`.

- `scans`: POST /v1/scans, label one scan;
- `jobs`: /v1/jobs, start, list, follow, download and cancel jobs over whole sequences;
- `health`: /healthz and /metrics, for probes and Prometheus (never behind the token).
"""
