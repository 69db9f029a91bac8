"""Fine-tuning: `rangeret train --init-from` starts from a checkpoint's weights (a new head where
the class count differs), `--freeze-backbone-steps` keeps the loaded tensors as loaded, the
checkpoints record their parent and label set, and `rangeret weights info` prints them.

The parent is a one-block circular-retention network (it has BatchNorm layers) trained one step
for SemanticKITTI's 20 classes on a tiny simulated tree; the runs fine-tune it for PandaSet's 15
classes, or for SemanticKITTI again, at 16 x 128."""

from __future__ import annotations

import argparse
import dataclasses
import hashlib
import json
import math
from pathlib import Path

import pytest
import torch
import yaml

from rangeret.cli.main import main
from rangeret.cli.train import add_train_arguments
from rangeret.dataset.profiles import load_profile
from rangeret.models import CheckpointError, build_model, load_checkpoint
from rangeret.sim import SensorConfig, simulate_dataset
from rangeret.train_options import config_from_args
from rangeret.training import TrainConfig, Trainer
from rangeret.training.config import TrainConfigError
from rangeret.training.data import collate
from rangeret.training.state import TrainingStateError, seed_everything

TINY = {"height": 16, "width": 128}
#: The parent's network: one block of width 16 with two heads.
NET = (("layers", 1), ("heads", 2), ("dim", 16))
NEW_HEAD = ("head.mlp2.weight", "head.mlp2.bias")


@pytest.fixture(autouse=True)
def one_thread():
    """One torch thread, as in the other training tests: steady step times on busy machines."""
    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(threads)


@pytest.fixture(scope="module")
def trees(tmp_path_factory) -> dict[str, Path]:
    """Two scans each: SemanticKITTI's sequence 00 and PandaSet's sequence 001, at 16 x 128."""
    roots = {}
    kitti = tmp_path_factory.mktemp("kitti")
    simulate_dataset(
        kitti,
        {"00": 2},
        sensor=SensorConfig(beams=16, azimuth_steps=128),
        seed=3,
        profile=load_profile("semantickitti"),
    )
    roots["semantickitti"] = kitti
    panda = load_profile("pandaset")
    root = tmp_path_factory.mktemp("pandaset")
    sensor = SensorConfig.for_profile(panda.with_overrides(**TINY), azimuth_steps=128)
    simulate_dataset(root, {"001": 2}, labelled=["001"], sensor=sensor, seed=4, profile=panda)
    roots["pandaset"] = root
    return roots


def run_config(trees: dict[str, Path], profile: str, out: Path, **changes) -> TrainConfig:
    """A CPU run of the parent's network on the profile's tree, without validation."""
    values = {
        "dataset": str(trees[profile]),
        "profile": profile,
        "train_sequences": ("00",) if profile == "semantickitti" else ("1",),
        "val_sequences": (),
        "out": str(out),
        "model": "rangeret-cir",
        "epochs": 1,
        "loader_workers": 0,
        "progress": False,
        "device": "cpu",
        **TINY,
        **changes,
    }
    return TrainConfig(**values)


@pytest.fixture(scope="module")
def parent(trees, tmp_path_factory) -> Path:
    """The project's own checkpoint of the parent network, trained one step for SemanticKITTI."""
    out = tmp_path_factory.mktemp("parent")
    Trainer(run_config(trees, "semantickitti", out, model_overrides=NET, max_steps=1)).fit()
    return out / "last.pt"


def train_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser()
    add_train_arguments(parser)
    return parser


def test_a_frozen_backbone_stays_bit_identical_while_the_new_head_trains(trees, parent, tmp_path):
    config = run_config(
        trees, "pandaset", tmp_path / "run", init_from=str(parent), freeze_backbone_steps=3
    )
    trainer = Trainer(dataclasses.replace(config, epochs=2, max_steps=3))
    init = trainer.tuning.initialisation
    start = {k: v.clone() for k, v in trainer.model.state_dict().items()}
    assert init.new == NEW_HEAD and set(init.loaded) == set(start) - set(NEW_HEAD)
    # The new head is as `build_model` initialises it with the run's seed.
    seed_everything(config.seed)
    fresh = build_model("rangeret-cir", 16, 128, 15, **dict(NET)).state_dict()
    assert all(torch.equal(start[k], fresh[k]) for k in NEW_HEAD)

    trainer.fit()
    assert trainer.step == 3
    after = trainer.model.state_dict()
    theirs = load_checkpoint(parent).state_dict()
    statistics = {k for k in init.loaded if k.endswith(("running_mean", "running_var"))}
    assert "head.norm.running_mean" in statistics and len(statistics) >= 10
    assert {k for k in init.loaded if k.endswith("num_batches_tracked")}
    for name in init.loaded:
        assert torch.equal(after[name], theirs[name]), name
    assert after["head.mlp2.weight"].shape == (15, 64) and after["head.mlp2.bias"].shape == (15,)
    assert trainer.model.config.num_classes == 15
    for name in NEW_HEAD:
        assert not torch.equal(after[name], start[name]), name


def test_the_same_class_count_loads_every_tensor_and_the_first_step_starts_from_them(
    trees, parent, tmp_path
):
    # fp32, the step the loss below is computed at (auto may be bf16 on this CPU)
    config = run_config(
        trees, "semantickitti", tmp_path / "run", init_from=str(parent), precision="fp32"
    )
    trainer = Trainer(config)
    assert trainer.tuning.initialisation.new == ()
    assert dict(trainer.config.model_overrides) == dict(NET)
    ours = trainer.model.state_dict()
    network = load_checkpoint(parent)
    theirs = network.state_dict()
    assert list(ours) == list(theirs) == list(trainer.tuning.initialisation.loaded)
    assert all(torch.equal(ours[k], theirs[k]) for k in ours)
    # Step 0 with a new optimiser and the schedule at its start, not the parent's run resumed.
    assert trainer.step == 0 and trainer.optimizer.state_dict()["state"] == {}
    assert math.isclose(trainer.optimizer.param_groups[0]["lr"], config.lr)

    batch = collate([trainer.train_set[(0, 0)]])
    network.train()
    with torch.no_grad():
        expected = float(trainer.criterion(network(batch["image"]), batch["label"])[0])
    loss = trainer.train_step(batch)[0]
    assert math.isclose(loss, expected, rel_tol=1e-6)


def test_refusals_name_the_option_or_the_tensor(trees, parent, tmp_path, capsys):
    same = run_config(trees, "semantickitti", tmp_path / "a", init_from=str(parent))
    with pytest.raises(TrainConfigError, match=r"would freeze the whole network.*20 classes"):
        Trainer(dataclasses.replace(same, freeze_backbone_steps=2))
    with pytest.raises(TrainConfigError, match="--freeze-backbone-steps 2 needs --init-from"):
        dataclasses.replace(same, init_from=None, freeze_backbone_steps=2)

    parser = train_parser()
    base = ["--dataset", str(trees["pandaset"]), "--profile", "pandaset"]
    base += ["--out", str(tmp_path / "b"), "--init-from", str(parent)]
    with pytest.raises(
        TrainConfigError,
        match=r"^--model rangeret-thesis contradicts --init-from .*last\.pt, whose network is "
        r"rangeret-cir",
    ):
        config_from_args(parser.parse_args([*base, "--model", "rangeret-thesis"]))
    with pytest.raises(TrainConfigError, match=r"--override dim=32 contradicts .*dim=16"):
        config_from_args(parser.parse_args([*base, "--override", "dim=32"]))
    repeated = config_from_args(
        parser.parse_args([*base, "--model", "rangeret-cir", "--override", "layers=1"])
    )
    assert repeated == config_from_args(parser.parse_args(base))
    assert repeated.model == "rangeret-cir" and dict(repeated.model_overrides) == dict(NET)

    content = torch.load(parent, weights_only=True)
    content["state_dict"]["backbone.norms1.0.weight"] = torch.ones(8)
    bent = tmp_path / "bent.pt"
    torch.save(content, bent)
    with pytest.raises(CheckpointError, match=r"backbone\.norms1\.0\.weight is \(8,\) there"):
        Trainer(run_config(trees, "pandaset", tmp_path / "c", init_from=str(bent)))
    argv = ["train", "-q", *base[:4], "--init-from", str(bent), "--out", str(tmp_path / "d")]
    argv += ["--train-sequences", "1", "--val-sequences", "--height", "16", "--width", "128"]
    argv += ["--loader-workers", "0", "--device", "cpu"]
    capsys.readouterr()
    assert main(argv) == 1
    err = capsys.readouterr().err
    assert len(err.strip().splitlines()) == 1 and "Traceback" not in err
    assert "backbone.norms1.0.weight" in err and "outside its head" in err


def test_checkpoints_record_parent_and_label_set_and_weights_info_prints_them(
    trees, parent, tmp_path, capsys
):
    out = tmp_path / "run"
    argv = ["train", "-q", "--dataset", str(trees["pandaset"]), "--profile", "pandaset"]
    argv += ["--init-from", str(parent), "--freeze-backbone-steps", "1", "--out", str(out)]
    argv += ["--train-sequences", "1", "--val-sequences", "--height", "16", "--width", "128"]
    argv += ["--epochs", "1", "--max-steps", "1", "--loader-workers", "0", "--device", "cpu"]
    assert main(argv) == 0, capsys.readouterr().err
    sha = hashlib.sha256(parent.read_bytes()).hexdigest()
    info = load_checkpoint(out / "last.pt").checkpoint_info
    record = info.parent
    assert record["source"] == record["path"] == str(parent) and record["sha256"] == sha
    assert record["profile"] == "semantickitti" and record["num_classes"] == 20
    assert record["new"] == list(NEW_HEAD)
    assert record["loaded"] == len(load_checkpoint(parent).state_dict()) - len(NEW_HEAD)
    names = list(load_profile("pandaset").labels.class_names)
    assert info.metadata["label_set"] == {
        "profile": "pandaset",
        "num_classes": 15,
        "class_names": names,
    }
    assert info.metadata["train_config"]["init_from"] == str(parent)
    assert info.metadata["train_config"]["freeze_backbone_steps"] == 1
    assert load_checkpoint(out / "best.pt").checkpoint_info.parent == record

    capsys.readouterr()
    assert main(["weights", "info", str(out / "last.pt")]) == 0
    facts = dict(line.split(":", 1) for line in capsys.readouterr().out.splitlines())
    facts = {k: v.strip() for k, v in facts.items()}
    assert facts["path"] == str((out / "last.pt").resolve())
    assert facts["sha256"] == hashlib.sha256((out / "last.pt").read_bytes()).hexdigest()
    assert facts["network"] == "rangeret-cir"
    assert {"num_classes=15", "layers=1", "dim=16", "heads=2", "height=16"} <= set(
        facts["config"].split()
    )
    assert facts["profile"] == "pandaset" and facts["classes"] == f"15: {', '.join(names)}"
    assert facts["parent"].startswith(f"{parent} (sha256 {sha};")
    assert "new: head.mlp2.weight, head.mlp2.bias" in facts["parent"]
    assert facts["training"].startswith("epoch 1 (complete), step 1 of 1; best: epoch 1")

    assert main(["weights", "info", str(parent)]) == 0
    facts = dict(line.split(":", 1) for line in capsys.readouterr().out.splitlines())
    assert facts["parent"].strip().startswith("none") and "20: unlabeled" in facts["classes"]
    (tmp_path / "notes.txt").write_text("not weights")
    for bad, reason in ((tmp_path / "gone.pt", "no such"), (tmp_path / "notes.txt", "not a")):
        assert main(["weights", "info", str(bad)]) == 1
        err = capsys.readouterr().err
        assert len(err.strip().splitlines()) == 1 and reason in err and str(bad) in err

    pred = tmp_path / "pred"
    predict = ["predict", "-q", "--dataset", str(trees["pandaset"]), "--sequences", "1"]
    predict += ["--out", str(pred), "--checkpoint", str(out / "last.pt"), "--device", "cpu"]
    assert main(predict) == 0, capsys.readouterr().err
    run = json.loads((pred / "run.json").read_text())
    assert run["parent"]["sha256"] == sha and run["parent"]["source"] == str(parent)
    assert run["runs"][-1]["parent"] == run["parent"]


def test_resume_continues_a_fine_tuning_run_frozen_until_step_n(trees, parent, tmp_path):
    """4 steps straight against 1, a resume to 2 (the freeze's end) and a resume to 4: the same
    losses and weights, the loaded tensors untouched until step 2 and trained after it."""
    copy = tmp_path / "parent.pt"
    copy.write_bytes(parent.read_bytes())
    changes = {"init_from": str(copy), "freeze_backbone_steps": 2, "epochs": 2, "max_steps": 4}
    straight = Trainer(run_config(trees, "pandaset", tmp_path / "straight", **changes)).fit()
    split = tmp_path / "split"
    Trainer(run_config(trees, "pandaset", split, **changes)).fit(until_step=1)
    theirs = load_checkpoint(parent).state_dict()
    resumed = Trainer(run_config(trees, "pandaset", split, resume=True, **changes))
    loaded = resumed.tuning.initialisation.loaded
    assert resumed.step == 1 and resumed.tuning.freeze.active(resumed.step)
    resumed.fit(until_step=2)
    at_two = load_checkpoint(split / "last.pt").state_dict()
    assert all(torch.equal(at_two[k], theirs[k]) for k in loaded)
    rest = Trainer(run_config(trees, "pandaset", split, resume=True, **changes)).fit()
    assert [r["step"] for r in rest.steps] == [3, 4]
    steps = [*resumed.result.steps, *rest.steps]
    for a, b in zip(straight.steps[1:], steps, strict=True):
        assert abs(a["loss"] - b["loss"]) <= 1e-6 and a["lr"] == b["lr"]
    final = load_checkpoint(split / "last.pt").state_dict()
    reference = load_checkpoint(tmp_path / "straight" / "last.pt").state_dict()
    assert all(torch.allclose(final[k], reference[k], atol=1e-6) for k in final)
    assert not torch.equal(final["head.norm.running_mean"], theirs["head.norm.running_mean"])
    assert not torch.equal(final["head.mlp1.weight"], theirs["head.mlp1.weight"])
    assert load_checkpoint(split / "last.pt").checkpoint_info.parent["sha256"] == (
        hashlib.sha256(parent.read_bytes()).hexdigest()
    )

    content = torch.load(copy, weights_only=True)
    content["state_dict"]["head.mlp1.bias"] += 1
    torch.save(content, copy)
    with pytest.raises(TrainingStateError, match=r"started from --init-from .* now has SHA-256"):
        Trainer(run_config(trees, "pandaset", split, resume=True, **changes))


def test_init_from_takes_a_published_file_or_a_published_models_name(
    trees, parent, tmp_path, monkeypatch
):
    bare = tmp_path / "tiny-cir.pt"
    torch.save(load_checkpoint(parent).state_dict(), bare)
    sha = hashlib.sha256(bare.read_bytes()).hexdigest()
    # A published file tells the blocks and width by its shapes; heads come as an override.
    config = run_config(
        trees, "pandaset", tmp_path / "file", init_from=str(bare), model_overrides=(("heads", 2),)
    )
    trainer = Trainer(config)
    assert dict(trainer.config.model_overrides) == dict(NET)
    assert trainer.tuning.initialisation.new == NEW_HEAD
    record = trainer.tuning.initialisation.record()
    assert record["published"] and record["profile"] is None and record["sha256"] == sha

    registry = tmp_path / "models.yaml"
    entry = {
        "repo": "test-org/tiny",
        "file": "tiny-cir.pt",
        "model": "rangeret-cir",
        "blocks": 1,
        "height": 16,
        "width": 128,
        "profile": "semantickitti",
        "sha256": sha,
    }
    registry.write_text(yaml.safe_dump({"tiny-cir": entry}))
    monkeypatch.setenv("RANGERET_REGISTRY", str(registry))
    monkeypatch.setattr("rangeret.models.weights.hub.cached_weights", lambda model: bare)
    (tmp_path / "cwd").mkdir()
    monkeypatch.chdir(tmp_path / "cwd")
    args = ["--dataset", str(trees["pandaset"]), "--profile", "pandaset", "--out", "named"]
    args += ["--init-from", "tiny-cir", "--override", "heads=2", "--train-sequences", "1"]
    args += ["--val-sequences", "--height", "16", "--width", "128", "--device", "cpu"]
    named = config_from_args(train_parser().parse_args(args))
    assert named.init_from == "tiny-cir" and named.model == "rangeret-cir"
    trainer = Trainer(dataclasses.replace(named, loader_workers=0, progress=False))
    record = trainer.tuning.initialisation.record()
    assert record["source"] == "tiny-cir" and record["path"] == str(bare)
    assert record["sha256"] == sha and trainer.profile.name == "pandaset"
    assert trainer.tuning.initialisation.new == NEW_HEAD


def test_print_config_and_config_files_carry_the_settled_network(trees, parent, tmp_path, capsys):
    argv = ["train", "--dataset", str(trees["pandaset"]), "--profile", "pandaset"]
    argv += ["--out", str(tmp_path / "run"), "--init-from", str(parent)]
    argv += ["--freeze-backbone-steps", "5", "--print-config"]
    assert main(argv) == 0
    printed = capsys.readouterr().out
    settings = yaml.safe_load(printed)
    assert settings["init_from"] == str(parent) and settings["freeze_backbone_steps"] == 5
    assert settings["model"] == "rangeret-cir" and settings["model_overrides"] == dict(NET)
    file = tmp_path / "run.yaml"
    file.write_text(printed)
    again = config_from_args(train_parser().parse_args(["--config", str(file)]))
    assert again == TrainConfig.from_dict(settings)
    assert TrainConfig.from_dict(again.to_dict()) == again


@pytest.mark.slow
def test_ray_train_fine_tunes_on_two_workers_with_the_backbone_frozen(trees, parent, tmp_path):
    """Data-parallel fine-tuning: every rank starts from the parent, the loaded tensors stay as
    loaded under DDP for the frozen steps, and the checkpoint records its parent."""
    ray = pytest.importorskip("ray")
    from workers.train_job import run_ray

    config = run_config(
        trees,
        "pandaset",
        tmp_path / "ray-run",
        init_from=str(parent),
        freeze_backbone_steps=2,
        epochs=2,
    )
    ray.init(address="local", num_cpus=2, num_gpus=0, include_dashboard=False)
    try:
        out = run_ray(config, workers=2)
    finally:
        ray.shutdown()
    model = load_checkpoint(out / "last.pt")
    meta = model.checkpoint_info.metadata
    assert meta["world_size"] == 2 and meta["step"] == 2
    assert meta["parent"]["sha256"] == hashlib.sha256(parent.read_bytes()).hexdigest()
    assert model.config.num_classes == 15
    after, theirs = model.state_dict(), load_checkpoint(parent).state_dict()
    loaded = set(theirs) - set(NEW_HEAD)
    assert loaded and all(torch.equal(after[k], theirs[k]) for k in loaded)
    assert after["head.mlp2.weight"].shape == (15, 64)


def test_weights_info_names_the_parents_profile_for_each_kind_of_parent(
    trees, parent, tmp_path, monkeypatch, capsys
):
    """A published model named by the registry has its registry's profile on the parent line; a
    published file given by path says it records none."""
    bare = tmp_path / "tiny-cir.pt"
    torch.save(load_checkpoint(parent).state_dict(), bare)
    entry = {"repo": "test-org/tiny", "file": "tiny-cir.pt", "model": "rangeret-cir"}
    entry |= {"blocks": 1, "height": 16, "width": 128, "profile": "semantic-poss"}
    (tmp_path / "models.yaml").write_text(yaml.safe_dump({"tiny-cir": entry}))
    monkeypatch.setenv("RANGERET_REGISTRY", str(tmp_path / "models.yaml"))
    monkeypatch.setattr("rangeret.models.weights.hub.cached_weights", lambda model: bare)
    lines = {}
    for kind, source in (("named", "tiny-cir"), ("file", str(bare))):
        out = tmp_path / kind
        argv = ["train", "-q", "--dataset", str(trees["pandaset"]), "--profile", "pandaset"]
        argv += ["--init-from", source, "--override", "heads=2", "--out", str(out)]
        argv += ["--train-sequences", "1", "--val-sequences", "--height", "16", "--width", "128"]
        argv += ["--epochs", "1", "--max-steps", "1", "--loader-workers", "0", "--device", "cpu"]
        assert main(argv) == 0, capsys.readouterr().err
        capsys.readouterr()
        assert main(["weights", "info", str(out / "last.pt")]) == 0
        facts = dict(line.split(":", 1) for line in capsys.readouterr().out.splitlines())
        lines[kind] = facts["parent"]
    assert "with 20 classes for the semantic-poss profile;" in lines["named"]
    assert "with 20 classes for a profile it does not record (a published file);" in lines["file"]
