"""The one write-then-rename of the package: a file is seen whole or not at all."""

import pytest

from evcap.atomic_write import atomic_path, write_text_atomic


def test_a_file_takes_its_name_when_whole(tmp_path):
    path = tmp_path / "deep" / "state.json"
    write_text_atomic(path, "first")
    assert path.read_text() == "first"
    write_text_atomic(path, "second")
    assert path.read_text() == "second" and sorted(p.name for p in path.parent.iterdir()) == [
        "state.json"
    ]


@pytest.mark.parametrize("error", [RuntimeError, KeyboardInterrupt])
def test_an_error_mid_write_keeps_what_was_there(tmp_path, error):
    path = tmp_path / "checkpoint.pt"
    path.write_text("previous")
    with pytest.raises(error), atomic_path(path) as partial:
        partial.write_text("half")
        raise error
    assert path.read_text() == "previous" and [p.name for p in tmp_path.iterdir()] == [path.name]
