"""Single scans: their bodies, admission, and the labellers that answer POST /v1/scans (in this
process, batched, over a pool of models, or through the Serve application)."""
