"""`evcap import` tells the container by its content."""

import subprocess
import sys

import pytest

from evcap.errors import InputError
from evcap.importers.detect import detect, import_recording


@pytest.mark.parametrize(
    "head, container",
    [
        (b"#!AER-DAT4.0\r\n", "aedat4"),
        (b"#!AER-DAT3.1\r\n#Format: RAW\r\n", "aedat3"),
        (b"#!AER-DAT2.0\r\n# AEChip: DVS128\r\n", "aedat2"),
        (b"#ROSBAG V2.0\n", "ros1"),
        (b"\x89MCAP0\r\n", "ros2"),
        (b"SQLite format 3\x00", "ros2"),
        (b"0.000001 10 20 1\n0.000002 11 20 0\n", "text"),
        (b"# t x y p\n1468940145.246984 3 4 1\n", "text"),
    ],
)
def test_files_are_told_by_their_content(tmp_path, head, container):
    path = tmp_path / "recording.bin"  # the name says nothing
    path.write_bytes(head + b"\x00" * 16 if container != "text" else head)
    assert detect(path) == container


def test_folders(tmp_path):
    (tmp_path / "bag").mkdir()
    (tmp_path / "bag" / "metadata.yaml").write_text("rosbag2_bagfile_information: {}\n")
    (tmp_path / "seq").mkdir()
    (tmp_path / "seq" / "events.txt").write_text("0.1 1 2 1\n")
    (tmp_path / "empty").mkdir()
    assert detect(tmp_path / "bag") == "ros2" and detect(tmp_path / "seq") == "text"
    with pytest.raises(InputError, match="without metadata.yaml .* or events.txt"):
        detect(tmp_path / "empty")


@pytest.mark.parametrize(
    "content, message",
    [
        (b"#!AER-DAT1.0\r\n", "is AEDAT 1.0; evcap imports AEDAT 4"),
        (b"\x00\x01\x02 binary", "not a recording evcap knows"),
        (b"1 2 3\n4 5 6\n", "not a recording evcap knows"),
    ],
)
def test_unknown_containers_are_named(tmp_path, content, message):
    path = tmp_path / "x.dat"
    path.write_bytes(content)
    with pytest.raises(InputError, match=message):
        detect(path)


def test_an_option_for_another_container_is_refused(tmp_path):
    path = tmp_path / "x.aedat"
    path.write_bytes(b"#!AER-DAT2.0\r\n")
    with pytest.raises(InputError, match="--topic is not for .* container: aedat2"):
        import_recording(path, tmp_path / "s.h5", topic="/dvs/events")


def test_the_cli_names_a_missing_file(tmp_path):
    r = subprocess.run(
        [sys.executable, "-m", "evcap", "import", str(tmp_path / "nope"), "-o", "s.h5"],
        capture_output=True,
        text=True,
    )
    assert r.returncode != 0 and "no such file" in r.stderr and "Traceback" not in r.stderr
