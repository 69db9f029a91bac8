"""The gateway's endpoints, one module per resource, each a module-level `APIRouter`.

- `scans`: POST /v1/scans, label one scan;
- `jobs`: /v1/jobs, start, list, follow, download and cancel jobs over whole sequences;
- `profile`: GET /v1/profile, the served profile's classes, palette and label map;
- `model`: GET /v1/model, the served network, its checkpoint and whether it is the demo's;
- `health`: /healthz and /metrics, for probes and Prometheus (never behind the token).
"""
