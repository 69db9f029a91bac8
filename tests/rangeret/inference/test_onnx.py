"""ONNX exports (`rangeret export`) and the onnxruntime backend (`--backend onnxruntime`).

Small networks (32 x 256, 2 blocks) of both kinds, exported through the command line; the
backend's labels on the real scan against torch's, in `rangeret predict` and in the gateway.
"""

from __future__ import annotations

import contextlib
import hashlib
import io
import json
import logging
import re
import threading
import time
from collections.abc import Iterator
from pathlib import Path

import numpy as np
import pytest
import torch

from rangeret.cli.main import main as rangeret_main
from rangeret.dataset.labels import semantickitti
from rangeret.dataset.layout import KITTI_LAYOUT, prediction_path, velodyne_dir
from rangeret.dataset.projection import CHANNEL_MEANS, CHANNEL_STDS
from rangeret.inference.loaded_weights import load_weights
from rangeret.inference.predictor import Predictor
from rangeret.inference.runtime import onnx_backend
from rangeret.inference.runtime.onnx_backend import (
    CACHE_VARIABLE,
    export_heartbeat,
    export_progress,
)
from rangeret.inference.runtime.onnx_export import (
    INPUT_NAME,
    MAX_LOGIT_DIFFERENCE,
    OUTPUT_NAME,
    read_metadata,
)
from rangeret.inference.runtime.onnx_session import make_session, providers_for
from rangeret.inference.runtime.precision import auto_choice, resolve_precision
from rangeret.inference.spec import InferenceSpec
from rangeret.io.scans import KITTI_RECORD, read_labels, read_scan, write_scan
from rangeret.models import build_model
from tests.support.gateway import NET, OCTET, gateway_env, start_gateway
from tests.support.paths import data_path
from tests.support.workers import small_weights

SIZE = ["--height", "32", "--width", "256"]


def thesis_weights(folder: Path) -> Path:
    """A random 2-block rangeret-thesis state_dict (32 x 256), saved alone like a release file."""
    torch.manual_seed(0)
    network = build_model("rangeret-thesis", 32, 256, layers=2)
    path = folder / "thesis-small.pt"
    torch.save(network.state_dict(), path)
    return path


@pytest.fixture(scope="module")
def setup(tmp_path_factory) -> Iterator[dict]:
    """Weights of both networks, a tree holding the real scan, and a cache folder of this module."""
    base = tmp_path_factory.mktemp("onnx")
    real = base / "real"
    write_scan(
        velodyne_dir(real, "08", layout=KITTI_LAYOUT) / "000000.bin",
        read_scan(data_path("semantickitti-scan", "000000.bin")),
        record=KITTI_RECORD,
    )
    with pytest.MonkeyPatch.context() as patch:
        patch.setenv(CACHE_VARIABLE, str(base / "cache"))
        yield {
            "base": base,
            "weights": {
                "rangeret-cir": small_weights(base),
                "rangeret-thesis": thesis_weights(base),
            },
            "real": real,
            "cache": base / "cache",
        }


@pytest.fixture(scope="module")
def exports(setup) -> dict:
    """Each network exported by `rangeret export`: cir with a dynamic batch, thesis for batch 1;
    the path and what the command printed."""
    done = {}
    for name, dynamic in (("rangeret-cir", True), ("rangeret-thesis", False)):
        out = setup["base"] / f"{name}.onnx"
        args = ["export", "--checkpoint", str(setup["weights"][name]), *SIZE, "--out", str(out)]
        printed, errors = io.StringIO(), io.StringIO()
        with contextlib.redirect_stdout(printed), contextlib.redirect_stderr(errors):
            code = rangeret_main([*args, "--dynamic-batch"] if dynamic else args)
        assert code == 0, errors.getvalue()
        done[name] = {"path": out, "stdout": printed.getvalue(), "dynamic": dynamic}
    return done


def _predict(setup, out: Path, *options: str) -> Path:
    args = ["predict", "-q", "--dataset", str(setup["real"]), "--sequences", "08", "--out"]
    weights = setup["weights"]["rangeret-cir"]
    code = rangeret_main([*args, str(out), "--checkpoint", str(weights), *NET, *options])
    assert code == 0
    return out


class Lines(logging.Handler):
    """The messages of the records it is given."""

    def __init__(self) -> None:
        super().__init__(logging.INFO)
        self.lines: list[str] = []

    def emit(self, record: logging.LogRecord) -> None:
        self.lines.append(record.getMessage())


@pytest.fixture(scope="module")
def ort_run(setup) -> tuple[Path, list[str]]:
    """`rangeret predict -q --backend onnxruntime` of the real scan, the first run to export
    this network into the module's cache, with a heartbeat far shorter than its export: the
    tree and the backend's log lines."""
    lines = Lines()
    backend_log = logging.getLogger(onnx_backend.__name__)
    level = backend_log.level
    backend_log.addHandler(lines)
    backend_log.setLevel(logging.INFO)
    try:
        with pytest.MonkeyPatch.context() as patch:
            patch.setattr(onnx_backend, "HEARTBEAT_S", 0.01)
            tree = _predict(setup, setup["base"] / "pred-ort", "--backend", "onnxruntime")
    finally:
        backend_log.setLevel(level)
        backend_log.removeHandler(lines)
    return tree, lines.lines


@pytest.fixture(scope="module")
def predictions(setup, ort_run) -> dict[str, Path]:
    """`rangeret predict` of the real scan with each backend."""
    return {"torch": _predict(setup, setup["base"] / "pred-torch"), "onnxruntime": ort_run[0]}


# Export --------------------------------------------------------------------------------------


@pytest.mark.parametrize("name", ["rangeret-cir", "rangeret-thesis"])
def test_export_is_checked_and_carries_its_metadata(setup, exports, name):
    export = exports[name]
    found = re.search(r"max \|logit difference\| (\S+), argmax equal on (\S+) %", export["stdout"])
    assert found, export["stdout"]
    assert float(found.group(1)) <= MAX_LOGIT_DIFFERENCE
    assert float(found.group(2)) >= 99.9
    meta = read_metadata(export["path"])
    labels = semantickitti()
    assert meta["profile"] == "semantickitti"
    assert meta["class_names"] == list(labels.class_names)
    assert meta["class_raw_ids"] == list(labels.class_raw_ids)
    assert meta["label_config"]["unlabeled_class"] == labels.unlabeled_class
    assert meta["means"] == list(CHANNEL_MEANS) and meta["stds"] == list(CHANNEL_STDS)
    assert meta["projection"] == {
        "height": 32,
        "width": 256,
        "fov_up": 3.0,
        "fov_down": -25.0,
        "row": "pitch",
    }
    weights = setup["weights"][name].read_bytes()
    assert meta["checkpoint_sha256"] == hashlib.sha256(weights).hexdigest()
    assert meta["network"] == name and meta["blocks"] == 2
    batch = "N" if export["dynamic"] else 1
    assert meta["input"]["name"] == INPUT_NAME and meta["input"]["shape"] == [batch, 5, 32, 256]
    assert meta["output"]["name"] == OUTPUT_NAME and meta["output"]["shape"] == [batch, 20, 32, 256]
    assert meta["input"]["layout"] == "N,5,H,W" and meta["output"]["layout"] == "N,C,H,W"
    assert meta["version"]


def test_a_dynamic_batch_model_gives_each_scan_the_rows_of_batch_one(exports):
    session = make_session(exports["rangeret-cir"]["path"], torch.device("cpu"))
    images = np.random.default_rng(1).standard_normal((3, 5, 32, 256)).astype(np.float32)
    alone = [session.run([OUTPUT_NAME], {INPUT_NAME: images[i : i + 1]})[0] for i in range(3)]
    together = session.run([OUTPUT_NAME], {INPUT_NAME: images})[0]
    assert together.shape == (3, 20, 32, 256)
    np.testing.assert_allclose(together, np.concatenate(alone), rtol=0, atol=1e-5)
    assert not np.allclose(alone[0], alone[1])


def test_a_batch_one_model_takes_batch_one_only(exports):
    session = make_session(exports["rangeret-thesis"]["path"], torch.device("cpu"))
    image = np.zeros((1, 5, 32, 256), np.float32)
    assert session.run([OUTPUT_NAME], {INPUT_NAME: image})[0].shape == (1, 20, 32, 256)
    with pytest.raises(Exception, match="dimension"):
        session.run([OUTPUT_NAME], {INPUT_NAME: np.zeros((3, 5, 32, 256), np.float32)})


def test_an_export_takes_the_default_form_without_fixing_the_batch(monkeypatch):
    from rangeret.models.blocks import kernels

    monkeypatch.setattr(kernels, "MEASURED", ("cpu",))
    monkeypatch.setattr(torch.compiler, "is_exporting", lambda: True)
    kernels.forget()
    q, v = torch.zeros(2, 1, 4, 2), torch.zeros(2, 1, 4, 2)
    candidates = {"slow": lambda: q, "fast": lambda: v}
    assert kernels.choose("op", candidates, "slow", q, v) == "slow"
    assert kernels.choices() == {}


# The onnxruntime backend ---------------------------------------------------------------------


def test_onnxruntime_labels_the_real_scan_as_torch_does(setup, predictions):
    torch_labels = read_labels(prediction_path(predictions["torch"], "08", "000000"))
    ort_labels = read_labels(prediction_path(predictions["onnxruntime"], "08", "000000"))
    assert (
        torch_labels.size
        == ort_labels.size
        == len(read_scan(data_path("semantickitti-scan", "000000.bin")))
    )
    assert np.mean(torch_labels == ort_labels) >= 0.9999
    for backend, tree in predictions.items():
        run = json.loads((tree / "run.json").read_text())
        assert run["backend"] == backend and run["precision"] == "fp32"
    assert len(list((setup["cache"] / "onnx").glob("rangeret-cir-32x256-*.onnx"))) == 1


def test_a_driver_exports_once_for_the_predictors_its_workers_build(
    setup, tmp_path, monkeypatch, caplog
):
    """The first use exports, saying so with its cache file, that it is still at it while it
    runs and how long it took; the predictor built next loads the file without a word."""
    monkeypatch.setenv(CACHE_VARIABLE, str(tmp_path))
    monkeypatch.setattr(onnx_backend, "HEARTBEAT_S", 0.01)
    spec = InferenceSpec(
        checkpoint=str(setup["weights"]["rangeret-cir"]),
        height=32,
        width=256,
        device="cpu",
        backend="onnxruntime",
    )
    with caplog.at_level(logging.INFO, logger=onnx_backend.__name__):
        load_weights(spec).export_onnx()  # what the Ray job and the gateway do before workers
    exported = list((tmp_path / "onnx").glob("*.onnx"))
    assert len(exported) == 1
    said = [r.getMessage() for r in caplog.records if r.name == onnx_backend.__name__]
    assert said[0] == (
        f"exporting rangeret-cir to ONNX for onnxruntime (first use; cached at {exported[0]})"
    )
    assert re.fullmatch(r"still exporting rangeret-cir to ONNX \(\d+ s\)", said[1])
    done = [line for line in said if line.startswith("exported ")]
    assert len(done) == 1 and re.fullmatch(
        rf"exported rangeret-cir to ONNX in \d+ s; later runs load {re.escape(str(exported[0]))}",
        done[0],
    )
    caplog.clear()
    with caplog.at_level(logging.INFO, logger=onnx_backend.__name__):
        predictor = Predictor.from_spec(spec)
    assert not [r for r in caplog.records if "export" in r.getMessage()]
    assert predictor.onnx is not None and predictor.onnx.path == exported[0]
    assert predictor.describe()["backend"] == "onnxruntime"
    without_knn = predictor.with_knn(None)
    assert without_knn.onnx is predictor.onnx and without_knn.knn is None
    assert next(predictor.network.parameters()).device.type == "cpu"


def test_the_ray_job_and_the_gateway_take_the_backend(setup):
    import argparse

    from service.server import add_serve_arguments
    from workers.predict_job import build_parser

    weights = str(setup["weights"]["rangeret-cir"])
    selection = ["--dataset", "d", "--split", "valid", "--out", "p"]
    job = build_parser().parse_args(
        [*selection, "--checkpoint", weights, "--backend", "onnxruntime"]
    )
    serve = argparse.ArgumentParser()
    add_serve_arguments(serve)
    gateway = serve.parse_args(["--checkpoint", weights, "--backend", "onnxruntime"])
    gateway.batch_size = 1
    for args in (job, gateway):
        assert InferenceSpec.from_args(args).backend == "onnxruntime"
    default = serve.parse_args(["--checkpoint", weights, "--batch-size", "1"])
    assert InferenceSpec.from_args(default).backend == "torch"


def test_the_gateway_labels_with_onnxruntime_as_torch_does(setup, predictions):
    base = setup["base"]
    env = gateway_env(base / "state", [setup["real"]], **{CACHE_VARIABLE: str(setup["cache"])})
    weights = setup["weights"]["rangeret-cir"]
    gw = start_gateway(weights, env, base / "gateway.log", "--backend", "onnxruntime")
    try:
        body = (setup["real"] / "sequences" / "08" / "velodyne" / "000000.bin").read_bytes()
        with gw.client() as client:
            answer = client.post("/v1/scans", content=body, headers=OCTET)
            health = client.get("/healthz").json()
    finally:
        gw.stop()
    assert answer.status_code == 200, answer.text
    labels = np.frombuffer(answer.content, dtype=np.uint32)
    expected = read_labels(prediction_path(predictions["torch"], "08", "000000"))
    assert labels.size == expected.size and np.mean(labels == expected) >= 0.9999
    assert [w["backend"] for w in health["workers"]] == ["onnxruntime"]
    assert health["precision"] == "fp32"
    assert health["precision_reason"] == "auto's pick here: onnxruntime runs fp32 only"
    # the gateway's check of the weights and its worker found the export `rangeret predict` made
    assert len(list((setup["cache"] / "onnx").glob("*.onnx"))) == 1


# Bad input -----------------------------------------------------------------------------------


def test_export_formats_other_than_onnx_are_refused(tmp_path, capsys):
    with pytest.raises(SystemExit) as exit_:
        rangeret_main(["export", "--format", "tflite", "--out", str(tmp_path / "m.tflite")])
    assert exit_.value.code == 2
    assert "invalid choice: 'tflite'" in capsys.readouterr().err


@pytest.mark.parametrize("precision", ["fp16", "bf16"])
def test_onnxruntime_refuses_half_precision_in_one_sentence(tmp_path, capsys, precision):
    args = ["predict", "--dataset", str(tmp_path), "--sequences", "08", "--out", str(tmp_path)]
    code = rangeret_main([*args, "--backend", "onnxruntime", "--precision", precision])
    err = capsys.readouterr().err
    assert code == 1 and "Traceback" not in err
    assert err.strip().splitlines() == [
        f"rangeret predict: error: --precision {precision} cannot run with --backend onnxruntime: "
        "its exported graph is fp32 and onnxruntime has no autocast, so it runs fp32 only (pass "
        "--precision fp32 or auto, or --backend torch for fp16 and bf16)"
    ]


def test_onnxruntime_resolves_auto_to_fp32_on_every_device():
    for device in ("cpu", "cuda"):
        assert resolve_precision("auto", torch.device(device), "onnxruntime") == "fp32"
    assert resolve_precision("auto", torch.device("cpu"), "torch") == auto_choice("cpu").precision
    with pytest.raises(ValueError, match="--backend onnxruntime"):
        resolve_precision("bf16", torch.device("cpu"), "onnxruntime")


@pytest.mark.skipif(torch.cuda.is_available(), reason="needs a machine without CUDA")
def test_cuda_without_a_gpu_keeps_its_error_with_onnxruntime(setup, tmp_path, capsys):
    args = ["predict", "--dataset", str(setup["real"]), "--sequences", "08", "--out", str(tmp_path)]
    weights = str(setup["weights"]["rangeret-cir"])
    code = rangeret_main(
        [*args, "--checkpoint", weights, *SIZE, "--device", "cuda", "--backend", "onnxruntime"]
    )
    err = capsys.readouterr().err
    assert code == 1 and "Traceback" not in err
    assert err.strip().splitlines()[-1] == (
        "rangeret predict: error: --device cuda was asked for but torch sees no CUDA device"
    )


def test_cuda_without_the_gpu_package_names_onnxruntime_gpu(monkeypatch):
    import onnxruntime

    monkeypatch.setattr(onnxruntime, "get_available_providers", lambda: ["CPUExecutionProvider"])
    with pytest.raises(ValueError, match="install onnxruntime-gpu in its place"):
        providers_for(torch.device("cuda"))
    assert providers_for(torch.device("cpu")) == ["CPUExecutionProvider"]


def test_read_metadata_refuses_a_file_that_is_not_an_export(tmp_path):
    path = tmp_path / "not.onnx"
    path.write_bytes(b"not a model")
    with pytest.raises(ValueError, match=r"not\.onnx is not an ONNX model"):
        read_metadata(path)


def test_a_cached_export_of_other_weights_is_made_again(setup, tmp_path, monkeypatch, caplog):
    """The export of one checkpoint copied over the cache file of another: the run exports its
    own again (naming both hashes) and labels as torch does with its own weights."""
    import logging
    import shutil

    from rangeret.inference.runtime.onnx_backend import cached_export
    from rangeret.inference.runtime.onnx_export import read_metadata
    from rangeret.models.weights.hub import file_sha256

    monkeypatch.setenv(CACHE_VARIABLE, str(tmp_path))
    first = InferenceSpec(
        checkpoint=str(setup["weights"]["rangeret-cir"]), height=32, width=256, device="cpu"
    )
    other = tmp_path / "other.pt"
    state = torch.load(first.checkpoint, weights_only=True)
    torch.manual_seed(1)
    torch.save(
        {
            k: v + 0.05 * torch.randn_like(v) if v.is_floating_point() else v
            for k, v in state.items()
        },
        other,
    )
    second = InferenceSpec(checkpoint=str(other), height=32, width=256, device="cpu")
    made = []
    for spec in (first, second):
        predictor = Predictor.from_spec(spec)
        made.append(
            cached_export(predictor.network, predictor.profile, file_sha256(Path(spec.checkpoint)))
        )
    shutil.copyfile(made[0], made[1])  # the first checkpoint's export in the second's place
    with caplog.at_level(logging.WARNING, logger="rangeret.inference.runtime.onnx_backend"):
        predictor = Predictor.from_spec(second.replace(backend="onnxruntime"))
    warned = " ".join(r.getMessage() for r in caplog.records)
    assert file_sha256(other) in warned and file_sha256(Path(first.checkpoint)) in warned, warned
    assert read_metadata(made[1])["checkpoint_sha256"] == file_sha256(other)
    scan = read_scan(data_path("semantickitti-scan", "000000.bin"))
    torch_labels = Predictor.from_spec(second).predict(scan).labels
    assert np.array_equal(predictor.predict(scan).labels, torch_labels)


def test_with_q_a_first_export_names_its_start_and_end_only(ort_run):
    """`rangeret predict -q`: the export is announced and closed, with no "still exporting"
    lines, though it ran far longer than the heartbeat."""
    said = ort_run[1]
    assert said[0].startswith("exporting rangeret-cir to ONNX for onnxruntime (first use;")
    assert any(line.startswith("exported rangeret-cir to ONNX in ") for line in said)
    assert not [line for line in said if line.startswith("still exporting")]


def test_the_heartbeat_beats_while_an_export_runs_unless_turned_off(tmp_path, caplog):
    path = tmp_path / "n.onnx"
    with caplog.at_level(logging.INFO, logger=onnx_backend.__name__):
        with export_progress("net", path, interval=0.02):
            time.sleep(0.2)
        beats = [r for r in caplog.records if r.getMessage().startswith("still exporting net")]
        assert len(beats) >= 2
        caplog.clear()
        with export_heartbeat(False), export_progress("net", path, interval=0.02):
            time.sleep(0.2)
    said = [r.getMessage() for r in caplog.records]
    assert len(said) == 2 and said[0].startswith("exporting net") and said[1].startswith("exported")
    assert not [t for t in threading.enumerate() if t.name == "onnx-export-progress"]


# An export given with --onnx -----------------------------------------------------------------


def test_predict_runs_the_export_it_is_given_and_exports_nothing(
    setup, exports, predictions, tmp_path, monkeypatch, capsys
):
    """`--onnx FILE`: the file `rangeret export` wrote runs as it is (nothing is exported into
    an empty cache) and labels as the cached export does; an export of other weights, a batch-1
    export for batches of 2, `--onnx` without onnxruntime, and an export given as `--checkpoint`
    are one line each, never torch's advice about `weights_only`."""
    empty = tmp_path / "empty-cache"
    monkeypatch.setenv(CACHE_VARIABLE, str(empty))
    given = exports["rangeret-cir"]["path"]
    ort = ("--backend", "onnxruntime")
    out = _predict(setup, tmp_path / "given", *ort, "--onnx", str(given))
    assert not list(empty.rglob("*.onnx"))
    labels = prediction_path(out, "08", "000000").read_bytes()
    assert labels == prediction_path(predictions["onnxruntime"], "08", "000000").read_bytes()

    single = tmp_path / "cir-batch1.onnx"
    weights = setup["weights"]["rangeret-cir"]
    args = ["export", "--checkpoint", str(weights), *SIZE, "--out", str(single)]
    assert rangeret_main(args) == 0
    capsys.readouterr()
    base = ["predict", "-q", "--dataset", str(setup["real"]), "--sequences", "08"]
    base += ["--out", str(tmp_path / "refused"), *NET]
    other = exports["rangeret-thesis"]["path"]
    cases = [
        ([*ort, "--onnx", str(other), "--checkpoint", str(weights)], "was made from checkpoint"),
        (
            [*ort, "--onnx", str(single), "--checkpoint", str(weights), "--batch-size", "2"],
            "takes batches of 1 scan and this run makes batches of 2",
        ),
        (["--onnx", str(given), "--checkpoint", str(weights)], "is an export for --backend"),
        (["--checkpoint", str(given)], "is an ONNX export, not a checkpoint"),
    ]
    for extra, words in cases:
        assert rangeret_main([*base, *extra]) == 1, extra
        err = capsys.readouterr().err
        assert words in err and err.count("\n") == 1, err
        assert "weights_only" not in err.replace("weights_only=True", "")
    assert not (tmp_path / "refused").exists()


def test_an_export_whose_metadata_was_copied_from_another_is_refused(
    setup, exports, tmp_path, capsys
):
    """Flipped weights exported, then given the real export's metadata: the metadata names the
    right checkpoint, but the digest of the graph's own weights gives it away."""
    import onnx

    weights = setup["weights"]["rangeret-cir"]
    state = torch.load(weights, weights_only=True)
    flipped = {k: -v if v.is_floating_point() else v for k, v in state.items()}
    torch.save(flipped, tmp_path / "flipped.pt")
    made = tmp_path / "flipped.onnx"
    args = ["export", "--checkpoint", str(tmp_path / "flipped.pt"), *SIZE, "--dynamic-batch"]
    assert rangeret_main([*args, "--out", str(made)]) == 0
    forged = onnx.load(str(made))
    del forged.metadata_props[:]
    forged.metadata_props.extend(onnx.load(str(exports["rangeret-cir"]["path"])).metadata_props)
    onnx.save(forged, str(tmp_path / "forged.onnx"))
    capsys.readouterr()
    base = ["predict", "-q", "--dataset", str(setup["real"]), "--sequences", "08", *NET]
    base += ["--out", str(tmp_path / "out"), "--backend", "onnxruntime"]
    code = rangeret_main(
        [*base, "--onnx", str(tmp_path / "forged.onnx"), "--checkpoint", str(weights)]
    )
    err = capsys.readouterr().err
    assert code == 1 and "its metadata was copied from another export" in err, err
    assert err.count("\n") == 1 and not (tmp_path / "out").exists()
    # the genuine export of the same weights still runs
    code = rangeret_main(
        [*base, "--onnx", str(exports["rangeret-cir"]["path"]), "--checkpoint", str(weights)]
    )
    assert code == 0, capsys.readouterr().err
