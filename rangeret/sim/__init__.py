"""Synthetic LiDAR data: a ray-casting simulator of a spinning LiDAR in street scenes.

- `scene`: the street (labelled boxes, cylinders and ellipsoids over a classified ground plane)
  and its random generation, `make_scene`;
- `raycast`: the sensor, `SensorConfig` (`for_profile` gives a dataset profile's), and
  `simulate_scan`, which casts its beams against a scene into points, labels, remissions and
  laser ids;
- `classes`: from the scenes' SemanticKITTI labels to another profile's raw ids;
- `dataset`: `simulate_dataset`, which writes sequences of scans in the SemanticKITTI layout or a
  profile's, reproducible byte for byte from its seed.
"""

from rangeret.dataset.beams import beam_values
from rangeret.sim.dataset import simulate_dataset
from rangeret.sim.raycast import SensorConfig, simulate_scan
from rangeret.sim.scene import Boxes, Cylinders, Ellipsoids, Scene, ground_labels
from rangeret.sim.street import make_scene

__all__ = [
    "Boxes",
    "Cylinders",
    "Ellipsoids",
    "Scene",
    "SensorConfig",
    "beam_values",
    "ground_labels",
    "make_scene",
    "simulate_dataset",
    "simulate_scan",
]
