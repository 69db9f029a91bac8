"""RangeRet: range-image LiDAR semantic segmentation with Retentive Networks.

A plain library (numpy and torch): scan I/O, projection, models, kNN refinement, metrics and
SemanticKITTI submissions. `workers/` runs it on Ray and `service/` serves it over HTTP.
"""

__version__ = "0.1.0"
