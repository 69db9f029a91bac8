"""RangeRet on Ray: the streaming batch pipeline and its job entrypoint, the Serve application
for single scans, Ray Train, and the demo."""
