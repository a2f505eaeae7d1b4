"""The replay backend behaves like a DAVIS346 to pyusb."""

import errno
from pathlib import Path

import numpy as np
import pytest
import usb.core
import usb.util

from evcap.acquire import protocol as P
from evcap.acquire.replay import ReplayBackend
from evcap.errors import InputError

FIXTURES = Path(__file__).resolve().parents[2] / "hw-fixtures"


def open_replay(path):
    backend = ReplayBackend(path)
    dev = usb.core.find(idVendor=0x152A, idProduct=0x841A, backend=backend)
    dev.set_configuration()
    return backend, dev


def test_enumerates_with_the_fixture_descriptor():
    backend, dev = open_replay(FIXTURES / "color-scene")
    assert (dev.idVendor, dev.idProduct, dev.bcdDevice & 0xFF) == (0x152A, 0x841A, 6)
    assert usb.util.get_string(dev, dev.iSerialNumber) == "00000042"
    assert usb.util.get_string(dev, dev.iProduct) == "DAVIS FX3"
    endpoints = [e.bEndpointAddress for e in dev.get_active_configuration()[(0, 0)]]
    assert endpoints == [0x81, 0x82]
    assert "DEVICE ID 152a:841a" in str(dev)


def test_registers_answer_like_the_protocol_says():
    backend, dev = open_replay(FIXTURES / "color-scene")
    # Read the logic version: setup C0 BF 06 00 00 00 04 00; a logic-18 device answers 00 00 00 12
    assert bytes(dev.ctrl_transfer(0xC0, 0xBF, 6, 0, 4)) == bytes([0, 0, 0, 0x12])
    assert bytes(dev.ctrl_transfer(0xC0, 0xBF, 2, 3, 4)) == bytes(
        [0, 0, 0, 1]
    )  # the fixture's RGBG
    dev.ctrl_transfer(0x40, 0xBF, 1, 3, bytes([0, 0, 0, 1]))  # DVS RUN = 1
    assert backend.registers[(1, 3)] == 1
    assert bytes(dev.ctrl_transfer(0xC0, 0xBF, 1, 3, 4)) == bytes([0, 0, 0, 1])
    dev.ctrl_transfer(0x40, 0xC2, 2, 0, P.pack_multiple([(0, 2, 1), (0, 2, 0)]))
    assert backend.writes[-2:] == [(0, 2, 1), (0, 2, 0)]
    dev.ctrl_transfer(0x40, 0xBF, 6, 0, bytes([0, 0, 0, 5]))  # SYSINFO is read-only
    assert backend.registers[(6, 0)] == 18
    with pytest.raises(usb.core.USBError) as e:
        dev.ctrl_transfer(0x40, 0x99, 0, 0, bytes(4))  # unknown request: the device stalls
    assert e.value.errno == errno.EPIPE


def test_streams_only_while_running_in_recorded_transfer_sizes():
    backend, dev = open_replay(FIXTURES / "color-scene")
    with pytest.raises(usb.core.USBTimeoutError):
        dev.read(0x82, 8192, 10)
    backend.registers[P.USB_RUN] = backend.registers[P.MUX_RUN] = 1
    sizes = np.fromfile(FIXTURES / "color-scene" / "transfers.u32", "<u4")
    got = [len(dev.read(0x82, 16384, 10)) for _ in range(5)]
    assert got == sizes[:5].tolist()
    while not backend.exhausted:
        dev.read(0x82, 16384, 10)
    assert backend.bytes_served == (FIXTURES / "color-scene" / "bulk.bin").stat().st_size
    with pytest.raises(usb.core.USBTimeoutError):  # idle once exhausted
        dev.read(0x82, 16384, 10)


def test_faults_play_at_their_byte(fixture_copy):
    path = fixture_copy("timeouts-stall")
    (path / "faults.toml").write_text(
        '[[fault]]\nat_byte = 8192\nkind = "timeout"\ncount = 2\n\n'
        '[[fault]]\nat_byte = 8192\nkind = "stall"\n\n'
        '[[fault]]\nat_byte = 20000\nkind = "disconnect"\n'
    )
    backend, dev = open_replay(path)
    backend.registers[P.USB_RUN] = backend.registers[P.MUX_RUN] = 1
    assert len(dev.read(0x82, 8192, 10)) == 8192
    for _ in range(2):
        with pytest.raises(usb.core.USBTimeoutError):
            dev.read(0x82, 8192, 10)
    with pytest.raises(usb.core.USBError) as e:
        dev.read(0x82, 8192, 10)
    assert e.value.errno == errno.EPIPE
    with pytest.raises(usb.core.USBError):  # halted until cleared
        dev.read(0x82, 8192, 10)
    dev.clear_halt(0x82)
    assert len(dev.read(0x82, 8192, 10)) == 8192
    assert len(dev.read(0x82, 8192, 10)) == 20000 - 16384  # cut at the fault
    with pytest.raises(usb.core.USBError) as e:
        dev.read(0x82, 8192, 10)
    assert e.value.errno == errno.ENODEV
    assert usb.core.find(idVendor=0x152A, backend=backend) is None  # gone from the bus


USB = "[usb]\nidVendor = 1\nidProduct = 2\nbcdDevice = 6\n"


@pytest.mark.parametrize(
    "files, message",
    [
        ({}, "not a replay fixture"),
        ({"device.toml": "[usb]\nidVendor = 1\n", "bulk.bin": ""}, "missing idProduct"),
        ({"device.toml": "[usb", "bulk.bin": ""}, "device.toml is not valid TOML"),
        ({"device.toml": b"[usb]\nserial = '\xff'\n", "bulk.bin": ""}, "not valid TOML"),
        ({"device.toml": USB + 'serial = 42\nproduct = "x"\n'}, "serial must be a string"),
        ({"faults.toml": '[[fault]]\nat_byte = 1\nkind = "fire"\n'}, "unknown fault kind"),
        ({"faults.toml": '[[fault]]\nkind = "stall"\n'}, "missing at_byte"),
        ({"faults.toml": '[[fault]]\nat_byte = "ten"\nkind = "stall"\n'}, "at_byte must be"),
        ({"faults.toml": '[[fault]]\nat_byte = 9\nkind = "timeout"\ncount = -1\n'}, "count"),
        ({"faults.toml": '[[fault]]\nat_byte = 9\nkind = "stall"\nwhen = 2\n'}, "unknown key"),
        ({"faults.toml": "[[fault]"}, "faults.toml is not valid TOML"),
    ],
)
def test_bad_fixtures_are_refused(tmp_path, files, message):
    if files:  # a good fixture's other files
        files = {
            "device.toml": (FIXTURES / "color-scene" / "device.toml").read_text(),
            "bulk.bin": "",
            **files,
        }
    for name, text in files.items():
        (tmp_path / name).write_bytes(text if isinstance(text, bytes) else text.encode())
    with pytest.raises(InputError, match=message):
        ReplayBackend(tmp_path)
