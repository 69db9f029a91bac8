"""The training configuration as the schema: options derived from `TrainConfig`'s fields, the
YAML file of `--config`, `--print-config`, and the named optimiser and schedules."""

from __future__ import annotations

import argparse
import dataclasses
from pathlib import Path

import pytest
import torch
import yaml

from rangeret.cli.main import main
from rangeret.cli.train import add_train_arguments
from rangeret.train_options import add_dataclass_options, config_from_args
from rangeret.training import TrainConfig
from rangeret.training.config import TrainConfigError, setting
from rangeret.training.config_file import config_yaml, read_config_file
from rangeret.training.schedule import OPTIMIZERS, SCHEDULES, build_optimizer, build_scheduler
from rangeret.training.state import run_record

REQUIRED = ["--dataset", "d", "--out", "o", "--model", "rangeret-thesis"]

#: Every option of `rangeret train` before the settings became a schema, and those added since.
EARLIER_OPTIONS = {
    "--dataset", "--profile", "--train-sequences", "--val-sequences", "--label-config",
    "--height", "--width", "--fov-up", "--fov-down", "--no-augment", "--mixes",
    "--mix-probability", "--loader-workers", "--model", "--override", "--epochs", "--max-steps",
    "--batch-size", "--lr", "--max-lr", "--weight-decay", "--schedule", "--warmup", "--loss",
    "--class-weights", "--focal-gamma", "--clip-grad", "--precision", "--no-amp", "--seed",
    "--out", "--resume", "--checkpoint-every", "--device", "--ray", "--workers",
}  # fmt: skip
NEW_OPTIONS = {
    "--config",
    "--print-config",
    "--optimizer",
    "--init-from",
    "--freeze-backbone-steps",
}


def train_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser()
    add_train_arguments(parser)
    return parser


def parse(argv: list[str]) -> TrainConfig:
    return config_from_args(train_parser().parse_args(argv))


def write(path: Path, settings: dict) -> Path:
    path.write_text(yaml.safe_dump(settings))
    return path


def test_the_options_are_the_earlier_ones_and_the_files():
    options = {s for a in train_parser()._actions for s in a.option_strings if s != "-h"}
    assert options - {"--help"} == EARLIER_OPTIONS | NEW_OPTIONS


def test_the_builder_derives_type_choices_default_and_help_from_the_fields():
    @dataclasses.dataclass(frozen=True)
    class Example:
        size: int = setting(3, help="how many", group="g", metavar="N")
        mode: str = setting("a", help="which", group="g", choices=("a", "b"))
        names: tuple[str, ...] | None = setting(None, help="names", group="h")
        fast: bool = setting(True, help="slow down", group="h", flag="--slow", negate=True)
        hidden: int = setting(0, help="none", group="h", flag=None)

    parser = argparse.ArgumentParser()
    groups = add_dataclass_options(parser, Example)
    assert list(groups) == ["g", "h"]
    by_dest = {a.dest: a for a in parser._actions}
    assert "hidden" not in by_dest
    assert by_dest["size"].type is int and by_dest["size"].help == "how many (default: 3)"
    assert by_dest["mode"].choices == ["a", "b"] and by_dest["names"].nargs == "+"
    assert by_dest["fast"].option_strings == ["--slow"]
    args = parser.parse_args(["--size", "5", "--slow"])
    assert (args.size, args.mode, args.names, args.fast) == (5, None, None, True)
    with pytest.raises(SystemExit):
        parser.parse_args(["--mode", "c"])


def test_a_config_file_sets_the_fields_and_flags_override_it(tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    file = write(
        tmp_path / "run.yaml",
        {
            "dataset": "data",
            "out": "runs/a",
            "model": "rangeret-cir",
            "epochs": 3,
            "lr": "2e-3",
            "fov_up": 3,
            "train_sequences": ["00", "02"],
            "model_overrides": {"layers": 2, "patch_size": [4, 4]},
            "schedule": "cosine",
            "precision": "fp16",
        },
    )
    config = parse(["--config", str(file)])
    assert config.dataset == str(tmp_path / "data") and config.out == str(tmp_path / "runs/a")
    assert (config.model, config.epochs, config.lr, config.fov_up) == ("rangeret-cir", 3, 2e-3, 3.0)
    assert config.train_sequences == ("00", "02") and config.schedule == "cosine"
    assert config.overrides == {"layers": 2, "patch_size": (4, 4)}
    assert config.max_lr == 1e-2 and config.precision == "fp16"

    more = ["--override", "dim=16", "--train-sequences", "01", "--no-amp"]
    flags = parse(
        [
            "--config",
            str(file),
            "--epochs",
            "5",
            "--out",
            "elsewhere",
            "--override",
            "layers=3",
            *more,
        ]
    )
    assert flags.epochs == 5 and flags.out == str(tmp_path / "elsewhere")
    assert flags.overrides == {"layers": 3, "patch_size": (4, 4), "dim": 16}
    assert flags.train_sequences == ("01",) and flags.precision == "fp32"
    assert (flags.lr, flags.model, flags.schedule) == (config.lr, config.model, config.schedule)
    assert parse([*REQUIRED, "--config", str(file)]).model == "rangeret-thesis"


def test_print_config_reads_back_to_the_same_config(tmp_path, monkeypatch, capsys):
    monkeypatch.chdir(tmp_path)
    argv = [
        "train", "-q", *REQUIRED, "--profile", "pandaset", "--train-sequences", "1",
        "--val-sequences", "--fov-up", "4.5", "--mixes", "rangemix", "--override", "layers=1",
        "--override", "patch_size=4x4", "--loss", "ce", "focal", "--lr", "5e-4",
        "--precision", "bf16", "--schedule", "cosine", "--max-steps", "7", "--no-augment",
        "--label-config", "labels.yaml", "--print-config",
    ]  # fmt: skip
    assert main(argv) == 0
    printed = capsys.readouterr().out
    file = tmp_path / "printed.yaml"
    file.write_text(printed)
    expected = dataclasses.replace(parse(argv[2:]), progress=False)
    assert read_config_file(file) == vars(expected)
    again = parse(["--config", str(file)])
    assert again == expected and again.progress is False and again.val_sequences == ()
    assert again.label_config == str(tmp_path / "labels.yaml")
    assert config_yaml(again) == printed
    monkeypatch.chdir(tmp_path.parent)
    assert main(["train", "--config", str(file), "--print-config"]) == 0
    assert capsys.readouterr().out == printed


@pytest.mark.parametrize(
    ("settings", "message"),
    [
        ({"lrr": 0.1}, "unknown setting 'lrr' in {file} (did you mean lr?)"),
        ({"amp": True}, "unknown setting 'amp' in {file}"),
        ({"epochs": "ten"}, "setting epochs in {file} must be an integer, got 'ten'"),
        ({"batch_size": 1.5}, "setting batch_size in {file} must be an integer, got 1.5"),
        ({"augment": "yes"}, "setting augment in {file} must be true or false, got 'yes'"),
        ({"height": "tall"}, "setting height in {file} must be an integer, got 'tall'"),
        ({"epochs": None}, "setting epochs in {file} needs a value"),
        ({"schedule": "linear"}, "setting schedule in {file} must be one of onecycle, cosine"),
        ({"optimizer": "sgd"}, "setting optimizer in {file} must be one of adamw, got 'sgd'"),
        ({"losses": ["ce", "dice"]}, "setting losses in {file} must be one of ce, lovasz, focal"),
        ({"train_sequences": [0]}, "setting train_sequences in {file} must be a list of strings"),
        ({"model": "resnet"}, "setting model in {file} must be one of rangeret-cir"),
        ({"model_overrides": {"depth": 3}}, "setting model_overrides in {file} must be a mapping"),
    ],
)
def test_a_bad_setting_in_the_file_is_one_line_naming_key_and_file(
    settings, message, tmp_path, capsys
):
    file = write(tmp_path / "bad.yaml", settings)
    assert main(["train", "--config", str(file), *REQUIRED, "--print-config"]) == 1
    captured = capsys.readouterr()
    assert captured.out == ""
    lines = captured.err.splitlines()
    assert len(lines) == 1 and lines[0].startswith("rangeret train: error: ")
    assert message.format(file=file) in lines[0]
    with pytest.raises(TrainConfigError):
        read_config_file(file)


def test_a_file_that_is_no_mapping_or_missing_is_one_line(tmp_path, capsys):
    listed = tmp_path / "list.yaml"
    listed.write_text("- epochs\n")
    for file, message in (
        (listed, "must map setting names"),
        (tmp_path / "none.yaml", "cannot read"),
    ):
        assert main(["train", "--config", str(file), *REQUIRED]) == 1
        err = capsys.readouterr().err.splitlines()
        assert len(err) == 1 and message in err[0] and str(file) in err[0]


def test_required_settings_come_from_the_file_or_the_flags(tmp_path, capsys):
    assert main(["train", "--model", "rangeret-thesis", "--print-config"]) == 1
    err = capsys.readouterr().err.splitlines()
    assert err == [
        "rangeret train: error: the following settings are required: --dataset, --out "
        "(or give --config FILE)"
    ]
    file = write(tmp_path / "part.yaml", {"dataset": str(tmp_path), "model": "rangeret-cir"})
    assert main(["train", "--config", str(file), "--print-config"]) == 1
    assert f"required: --out (on the command line or in {file})" in capsys.readouterr().err
    assert main(["train", "--config", str(file), "--out", "o", "--print-config"]) == 0
    assert yaml.safe_load(capsys.readouterr().out)["model"] == "rangeret-cir"


def test_a_value_out_of_range_in_the_file_is_one_line(tmp_path, capsys):
    file = write(tmp_path / "range.yaml", {"warmup": 1.5})
    assert main(["train", "--config", str(file), *REQUIRED, "--print-config"]) == 1
    assert capsys.readouterr().err.splitlines() == [
        "rangeret train: error: warmup must lie in (0, 1), got 1.5"
    ]


def test_the_job_takes_the_same_settings(tmp_path, capsys):
    from workers.train_job import main as job_main

    file = write(tmp_path / "job.yaml", {"dataset": "d", "out": "o", "model": "rangeret-cir"})
    assert job_main(["--config", str(file), "--epochs", "2", "--print-config", "-q"]) == 0
    printed = yaml.safe_load(capsys.readouterr().out)
    assert (printed["model"], printed["epochs"], printed["progress"]) == ("rangeret-cir", 2, False)
    assert job_main(["--config", str(write(tmp_path / "bad.yaml", {"epoch": 2}))]) == 1
    assert "unknown setting 'epoch'" in capsys.readouterr().err


def test_the_optimiser_and_schedule_are_named_in_the_config():
    assert tuple(OPTIMIZERS) == ("adamw",) and SCHEDULES == ("onecycle", "cosine")
    defaults = TrainConfig(dataset="d", out="o")
    assert (defaults.optimizer, defaults.schedule) == ("adamw", "onecycle")
    assert parse([*REQUIRED, "--optimizer", "adamw"]) == parse(REQUIRED)
    with pytest.raises(ValueError, match="optimizer must be one of"):
        TrainConfig(dataset="d", out="o", optimizer="sgd")
    with pytest.raises(ValueError, match="unknown optimizer 'sgd'"):
        build_optimizer([torch.nn.Parameter(torch.zeros(1))], name="sgd")
    record = run_record(
        dataclasses.replace(defaults, schedule="cosine"),
        losses=("ce",),
        world_size=1,
        train_scans=2,
        val_scans=1,
    )
    assert record["optimizer"] == {"name": "AdamW", "lr": 1e-3, "weight_decay": 0.05}
    assert record["scheduler"] == {"name": "warmup-cosine", "max_lr": 1e-2, "warmup": 0.3}
    assert run_record(defaults, losses=(), world_size=1, train_scans=1, val_scans=0)["scheduler"][
        "name"
    ] == ("OneCycleLR")


def test_the_named_adamw_steps_as_the_thesis_adamw():
    """The optimiser named adamw is torch's fused AdamW with the thesis's settings and takes the
    same steps, bit for bit, under the onecycle schedule."""
    start = torch.randn(6, generator=torch.Generator().manual_seed(1))
    params = [torch.nn.Parameter(start.clone()), torch.nn.Parameter(start.clone())]
    named = build_optimizer([params[0]], lr=1e-3, weight_decay=0.05, name="adamw")
    plain = torch.optim.AdamW([params[1]], lr=1e-3, weight_decay=0.05, fused=True)
    assert type(named) is torch.optim.AdamW
    settings = [
        {k: v for k, v in o.param_groups[0].items() if k != "params"} for o in (named, plain)
    ]
    assert settings[0] == settings[1]
    schedules = [build_scheduler(o, "onecycle", 10, 1e-2, 0.3) for o in (named, plain)]
    for step in range(10):
        for p, opt, sched in zip(params, (named, plain), schedules, strict=True):
            p.grad = torch.full_like(p, 0.1 * (step + 1))
            opt.step()
            sched.step()
    assert torch.equal(params[0], params[1])
