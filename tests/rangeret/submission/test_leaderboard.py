"""The leaderboard's lines in description.txt: written first by every runner, checked by the
validator, and a value on two lines refused with one sentence."""

from __future__ import annotations

import zipfile

import pytest

from rangeret.cli.main import build_parser, main
from rangeret.dataset.labels import semantickitti
from rangeret.dataset.layout import KITTI_LAYOUT, discover, prediction_path
from rangeret.io.run_info import write_run_info
from rangeret.io.scans import read_labels, write_labels
from rangeret.options import leaderboard_from_args
from rangeret.submission.archives import TEST_SEQUENCES, validate_submission
from rangeret.submission.leaderboard import (
    LeaderboardEntry,
    LeaderboardError,
    description_problems,
    description_text,
)
from tests.support.trees import make_tree

SHA = "ab" * 32


def _fields(text: str) -> list[tuple[str, str]]:
    """`key: value` pairs of each line, in order."""
    return [tuple(part.strip() for part in line.split(":", 1)) for line in text.splitlines()]


@pytest.fixture
def tree(tmp_path):
    """A partial test set, predictions equal to its labels, and the run.json of a checkpoint."""
    data, preds = tmp_path / "data", tmp_path / "pred"
    make_tree(data, {"11": [20], "12": [30]})
    cfg = semantickitti()
    for entry in discover(
        data, TEST_SEQUENCES, missing_ok=True, with_labels=True, layout=KITTI_LAYOUT
    ).scans:
        write_labels(
            prediction_path(preds, entry.sequence, entry.name),
            cfg.to_raw(cfg.to_class(read_labels(entry.label_path))),
        )
    write_run_info(
        preds,
        {"model": "rangeret-cir", "checkpoint_sha256": SHA, "demo_weights": False},
        runner="rangeret predict",
        dataset=data,
        sequences=["11", "12"],
        batch_size=1,
    )
    return data, preds


def _submission(tree, out, *extra: str) -> int:
    data, preds = tree
    args = ["submission", "-q", "--predictions", str(preds), "--dataset", str(data)]
    return main([*args, "--out", str(out), "--allow-partial", *extra])


def _description(archive) -> str:
    with zipfile.ZipFile(archive) as zf:
        return zf.read("description.txt").decode()


def test_submission_writes_the_given_name_and_links_then_the_checkpoint(tree, tmp_path):
    out = tmp_path / "s.zip"
    extra = ["--method-name", "RangeRet (ours)", "--pdf-url", "https://arxiv.org/abs/1"]
    code = _submission(
        tree, out, *extra, "--code-url", "https://github.com/a/b", "--description", "x"
    )
    assert code == 0
    fields = _fields(_description(out))
    assert fields[:4] == [
        ("name", "RangeRet (ours)"),
        ("pdf url", "https://arxiv.org/abs/1"),
        ("code url", "https://github.com/a/b"),
        ("checkpoint sha256", SHA),
    ]
    assert ("model", "rangeret-cir") in fields and fields[-1] == ("x",)
    check = validate_submission(out, tree[0], allow_partial=True, labels=semantickitti())
    assert check.ok and check.warnings == []


def test_submission_without_values_writes_the_benchmark_defaults(tree, tmp_path):
    out = tmp_path / "s.zip"
    assert _submission(tree, out) == 0
    fields = _fields(_description(out))
    assert fields[:4] == [
        ("name", "Anonymous"),
        ("pdf url", "n/a"),
        ("code url", "n/a"),
        ("checkpoint sha256", SHA),
    ]


def test_a_tree_without_run_json_records_an_unknown_checkpoint(tree, tmp_path):
    (tree[1] / "run.json").unlink()
    out = tmp_path / "s.zip"
    assert _submission(tree, out, "--method-name", "M") == 0
    assert _fields(_description(out))[3] == ("checkpoint sha256", "unknown")


@pytest.mark.parametrize("option", ["--method-name", "--pdf-url", "--code-url"])
def test_a_value_on_two_lines_is_refused_in_one_sentence(tree, tmp_path, capsys, option):
    out = tmp_path / "s.zip"
    assert _submission(tree, out, option, "https://a.org/x\nname: other") == 1
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and option in err and "line break" in err
    assert not out.exists()


def test_a_link_that_is_not_a_url_is_refused(tree, tmp_path, capsys):
    assert _submission(tree, tmp_path / "s.zip", "--pdf-url", "arxiv.org/abs/1") == 1
    err = capsys.readouterr().err
    assert "--pdf-url 'arxiv.org/abs/1' is neither an http(s) URL nor n/a" in err


def test_the_validator_warns_about_missing_or_malformed_lines(tree, tmp_path, capsys):
    data, _ = tree
    good = tmp_path / "good.zip"
    assert _submission(tree, good, "--method-name", "M") == 0
    cases = {
        "none.zip": None,
        "free.zip": "my method, see the paper\n",
        "order.zip": "pdf url: n/a\nname: M\ncode url: n/a\n",
        "link.zip": "name: M\npdf url: somewhere\ncode url: n/a\n",
    }
    with zipfile.ZipFile(good) as zin:
        for name, text in cases.items():
            with zipfile.ZipFile(tmp_path / name, "w") as zout:
                for info in zin.infolist():
                    if info.filename != "description.txt":
                        zout.writestr(info, zin.read(info))
                if text is not None:
                    zout.writestr("description.txt", text)
    capsys.readouterr()
    for name, expected in [
        ("none.zip", "has no description.txt"),
        ("free.zip", "line 1 should be 'name: ...'"),
        ("order.zip", "line 1 should be 'name: ...'"),
        ("link.zip", "line 2 'pdf url: somewhere': the value is neither an http(s) URL"),
    ]:
        check = validate_submission(
            tmp_path / name, data, allow_partial=True, labels=semantickitti()
        )
        assert check.ok and len(check.warnings) == 1 and expected in check.warnings[0], name
        args = ["validate-submission", "-q", str(tmp_path / name), "--dataset", str(data)]
        assert main([*args, "--allow-partial"]) == 0
        assert f"warning: {check.warnings[0]}" in capsys.readouterr().out
    args = ["validate-submission", "-q", str(good), "--dataset", str(data), "--allow-partial"]
    assert main(args) == 0
    assert "warning" not in capsys.readouterr().out


def test_description_text_is_the_leaderboard_lines_then_the_run():
    text = description_text(
        LeaderboardEntry("N", "https://p.org/a", "n/a"),
        written_by="the rangeret gateway",
        checkpoint_sha256=None,
        profile="pandaset",
        notes=["first\nsecond"],
    )
    assert text.splitlines() == [
        "name: N",
        "pdf url: https://p.org/a",
        "code url: n/a",
        "checkpoint sha256: unknown",
        "profile: pandaset",
        "written by: the rangeret gateway",
        "first",
        "second",
    ]
    assert description_problems(text) == []
    assert "simulated street scenes" in description_text(
        LeaderboardEntry(), written_by="x", checkpoint_sha256=SHA, demo_weights=True
    )


def test_empty_values_are_refused():
    with pytest.raises(LeaderboardError, match="--method-name '  ' is empty"):
        LeaderboardEntry(name="  ")


def test_the_ray_job_and_the_demo_take_the_same_options():
    pytest.importorskip("ray")
    from workers.predict_job import build_parser as job_parser

    given = ["--method-name", "M", "--pdf-url", "https://p.org", "--code-url", "https://c.org"]
    job = job_parser().parse_args(["--dataset", "d", "--out", "o", "--split", "test", *given])
    demo = build_parser("demo").parse_args(["demo", *given])
    expected = LeaderboardEntry("M", "https://p.org", "https://c.org")
    assert leaderboard_from_args(job) == leaderboard_from_args(demo) == expected


def test_the_ray_job_refuses_a_value_on_two_lines_before_it_starts(tmp_path, capsys):
    pytest.importorskip("ray")
    from workers.predict_job import main as job_main

    args = ["-q", "--dataset", str(tmp_path), "--out", str(tmp_path / "p"), "--split", "test"]
    assert job_main([*args, "--method-name", "a\nb"]) == 1
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "--method-name" in err and "line break" in err
    assert not (tmp_path / "p").exists()
