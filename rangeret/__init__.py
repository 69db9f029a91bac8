"""RangeRet: range-image LiDAR semantic segmentation with Retentive Networks.

A plain library (numpy and torch): scan I/O, projection, models, kNN refinement, metrics and
SemanticKITTI submissions. `workers/` runs it on Ray and `service/` serves it over HTTP.
"""

from pathlib import Path

__version__ = "0.1.0"

#: The files the package ships: demo weights, the model registry, profiles and label configurations.
DATA_DIR = Path(__file__).with_name("data")
