"""RangeRet on Ray: the streaming batch pipeline, the job entrypoint and the single-scan actor pool."""
