import shutil
from pathlib import Path

import pytest

FIXTURES = Path(__file__).resolve().parents[2] / "hw-fixtures"


@pytest.fixture
def fixture_copy(tmp_path):
    """A writable copy of a hardware-replay fixture, to add faults or edit its registers."""

    def copy(name: str) -> Path:
        dst = tmp_path / name
        shutil.copytree(FIXTURES / name, dst)
        return dst

    return copy
