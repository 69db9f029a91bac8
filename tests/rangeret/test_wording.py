"""The counted words of the commands' sentences."""

from rangeret.wording import plural


def test_one_is_singular_and_every_other_count_plural():
    assert plural(1, "epoch") == "1 epoch"
    assert [plural(n, "epoch") for n in (0, 2)] == ["0 epochs", "2 epochs"]
    assert plural(3, "process", "processes") == "3 processes"
