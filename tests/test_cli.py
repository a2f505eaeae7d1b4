import subprocess
import sys

HEAVY = ("torch", "pycolmap", "kornia", "textual", "cv2", "gsplat")
HELP_HEAVY = (*HEAVY, "numpy", "h5py")  # `evcap --help` reads no file either


def test_help_lists_every_command_with_one_line():
    r = subprocess.run([sys.executable, "-m", "evcap", "--help"], capture_output=True, text=True)
    assert r.returncode == 0
    lines = r.stdout.split("commands:")[1].strip().splitlines()[1:]
    names = [line.split()[0] for line in lines]
    assert names == [
        "import",
        "info",
        "devices",
        "record",
        "monitor",
        "simulate",
        "calibrate",
        "poses",
        "reconstruct",
        "report",
        "export",
        "view",
        "batch",
        "demo",
    ]
    assert all(len(line.split()) > 2 for line in lines)


def test_help_imports_nothing_heavy():
    # Its speed is measured in bench/cli_startup.py; what keeps it fast is checked here.
    code = (
        "import sys\nfrom evcap.app.cli import main\n"
        "try:\n    main(['--help'])\nexcept SystemExit:\n    pass\n"
        f"print([m for m in {HELP_HEAVY!r} if m in sys.modules])"
    )
    r = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True)
    assert r.stdout.strip().splitlines()[-1] == "[]"


def test_info_imports_nothing_heavy(tmp_path):
    from evcap.events import Events
    from evcap.session import SensorInfo, SessionWriter

    with SessionWriter(tmp_path / "s.h5", SensorInfo("simulated", 8, 8)) as w:
        w.append_events(Events([1], [2], [3], [1], 8, 8))
    code = (
        "import sys\nfrom evcap.app.cli import main\n"
        f"main(['info', {str(tmp_path / 's.h5')!r}])\n"
        f"print([m for m in {HEAVY!r} if m in sys.modules])"
    )
    r = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True)
    assert r.stdout.strip().splitlines()[-1] == "[]", r.stderr
