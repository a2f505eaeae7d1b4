import os
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parent.parent
# Compiled loops check their indexing under test: a bug raises IndexError, not a segfault.
# numba's cache does not tell such builds from the normal ones: keep them apart.
os.environ.setdefault("NUMBA_BOUNDSCHECK", "1")
os.environ.setdefault("NUMBA_CACHE_DIR", str(ROOT / ".numba-test-cache"))

SHARED = Path(os.environ.get("EVCAP_SHARED", ROOT.parent / "shared"))
SAMPLE_AEDAT4 = SHARED / "data" / "davis346-sample" / "davis346_test_data.aedat4"


@pytest.fixture(scope="session")
def sample_aedat4() -> Path:
    if not SAMPLE_AEDAT4.exists():
        pytest.skip(f"the real DAVIS346 sample is not at {SAMPLE_AEDAT4} (set EVCAP_SHARED)")
    return SAMPLE_AEDAT4
