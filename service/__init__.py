"""The HTTP gateway (FastAPI on uvicorn) in front of the RangeRet workers."""
