"""The bundled demo weights: they load without arguments and beat a majority-class baseline on
simulated validation scans they were not trained on."""

from __future__ import annotations

import numpy as np

from rangeret.dataset.distance import scan_bands
from rangeret.dataset.labels import semantickitti
from rangeret.dataset.layout import KITTI_LAYOUT, discover
from rangeret.dataset.profiles import load_profile
from rangeret.evaluation.counting import RawLabelEvaluator
from rangeret.inference.predictor import Predictor
from rangeret.io.scans import read_labels, read_scan
from rangeret.models.weights.demo import DEMO_CHECKPOINT, is_demo_checkpoint
from rangeret.sim import SensorConfig, simulate_dataset


def test_demo_weights_load_and_beat_the_majority_class(tmp_path):
    assert DEMO_CHECKPOINT.stat().st_size < 10 * 2**20
    predictor = Predictor.from_checkpoint(DEMO_CHECKPOINT, device="cpu")
    info = predictor.network.checkpoint_info
    assert not info.published and info.name == "rangeret-thesis"
    assert is_demo_checkpoint(info.sha256) and predictor.describe()["demo_weights"]

    simulate_dataset(
        tmp_path,
        {"08": 2},
        sensor=SensorConfig(beams=64, azimuth_steps=2048),
        seed=99,
        profile=load_profile("semantickitti"),
    )
    cfg = semantickitti()
    ours, majority = (
        RawLabelEvaluator(config=semantickitti()),
        RawLabelEvaluator(config=semantickitti()),
    )
    gts = []
    for entry in discover(tmp_path, ["08"], with_labels=True, layout=KITTI_LAYOUT).scans:
        gt = read_labels(entry.label_path)
        points = read_scan(entry.scan_path)
        gts.append((gt, scan_bands(points)))
        ours.add(predictor.predict(points).labels, gt, "08", gts[-1][1])
    counts = np.bincount(np.concatenate([cfg.to_class(g) for g, _ in gts]), minlength=20)
    counts[0] = 0
    top = cfg.to_raw(np.array([counts.argmax()]))[0]
    for gt, bands in gts:
        majority.add(np.full(gt.size, top, np.uint32), gt, "08", bands)
    assert ours.report().miou > 2 * majority.report().miou
