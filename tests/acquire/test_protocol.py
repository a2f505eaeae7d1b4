"""The protocol tables against the byte-exact values of docs/davis346-protocol.md (libcaer's)."""

import pytest

from evcap.acquire import protocol as P
from evcap.acquire.bias_file import bias_codes, load_bias_file
from evcap.errors import InputError

# libcaer's default DAVIS346 bias codes (docs/davis346-protocol.md section 2.5).
DEFAULT_CODES = {
    "ApsOverflowLevel": 0x019B,
    "ApsCas": 0x0195,
    "AdcRefHigh": 0x01E0,
    "AdcRefLow": 0x01C1,
    "AdcTestVoltage": 0x01D5,
    "LocalBufBn": 0x5A4F,
    "PadFollBn": 0x7D7E,
    "DiffBn": 0x427F,
    "OnBn": 0x5FFF,
    "OffBn": 0x401F,
    "PixInvBn": 0x690F,
    "PrBp": 0x23AD,
    "PrSFBp": 0x110D,
    "RefrBp": 0x419D,
    "ReadoutBufBp": 0x614D,
    "APSROSFBn": 0x6DBF,
    "ADCCompBp": 0x514D,
    "ColSelLowBn": 0x001F,
    "DACBufBp": 0x63CD,
    "LcolTimeoutBn": 0x531F,
    "AEPdBn": 0x65BF,
    "AEPuXBp": 0x450D,
    "AEPuYBp": 0x798D,
    "IFRefrBn": 0x5FFF,
    "IFThrBn": 0x5FFF,
    "BiasBuffer": 0x5FEF,
    "SSP": 0x8410,
    "SSN": 0x8410,
}


def test_default_bias_codes_match_libcaer():
    assert P.default_bias_codes() == DEFAULT_CODES
    assert list(P.BIASES) == list(DEFAULT_CODES)  # the send order
    params = [b.param for b in P.BIASES.values()]
    assert params == [0, 1, 2, 3, 4, *range(8, 28), 34, 35, 36]


def test_bias_encodings():
    assert P.vdac_code(27, 6) == 411
    assert P.coarse_fine_code(5, 255, n_type=True) == 24575
    assert P.coarse_fine_code(7, 215, n_type=True, enabled=False) == 0x7D7E
    assert P.coarse_fine_code(2, 58, n_type=False) == 0x23AD
    assert P.coarse_fine_code(0, 1, n_type=True, cascode=True) & 0xF == 0xB  # N-cascode
    assert P.coarse_fine_code(0, 1, n_type=False, enabled=False) & 0xF == 0xC  # P-type off
    assert P.shifted_source_code(1, 33) == 33808
    with pytest.raises(InputError, match="fine must be an integer in 0..255"):
        P.coarse_fine_code(1, 256, n_type=True)
    with pytest.raises(InputError, match="voltage"):
        P.vdac_code(64, 0)


def test_multiple_write_packing_matches_the_timestamp_reset_example():
    # the timestamp reset of docs/davis346-protocol.md section 2.1 (MUX param 2: 1, then 0)
    data = P.pack_multiple([(0, 2, 1), (0, 2, 0)])
    assert data == bytes.fromhex("000200000001000200000000")


def test_default_config_follows_libcaer():
    has = {name: 1 for name in P.DEVICE_CAPABILITIES}
    has["imu_type"] = 1
    writes = P.default_config(has, P.Clocks(90.0, 30.0, 80.0), P.default_bias_codes(), P.Settings())
    as_dict = {(m, p): v for m, p, v in writes}
    assert writes[0] == (5, 0, 0x019B) and writes[27] == (5, 36, 0x8410)
    assert as_dict[(2, 12)] == 4000 * 30 and as_dict[(2, 13)] == 40000 * 30  # ADC cycles
    assert as_dict[(1, 31)] == 1 and as_dict[(1, 32)] == 8  # background filter, 2 ms
    assert as_dict[(1, 33)] == 0 and as_dict[(1, 34)] == 1
    assert as_dict[(1, 11)] == 260 and as_dict[(1, 12)] == 346  # pixel filter slots disabled
    assert as_dict[(5, 142)] == 1 and as_dict[(2, 7)] == 1  # global shutter
    assert as_dict[(3, 7)] == 1 and as_dict[(3, 10)] == 1 and (3, 9) not in as_dict
    assert as_dict[(4, 5)] == 900  # 10 us pulse length at 90 MHz
    assert writes[-1] == (9, 1, 8 * 125 * 80)  # early packet delay: 8 slices of 125 us
    assert (5, 139) not in as_dict  # skipped on the DAVIS346


def test_bias_file(tmp_path):
    f = tmp_path / "b.toml"
    f.write_text(
        "[biases]\nOnBn = { coarse = 6, fine = 255 }\nPrBp = 9000\n"
        "ApsCas = { voltage = 20, current = 5 }\n[settings]\naps_exposure_us = 8000\n"
    )
    codes, settings = load_bias_file(f)
    assert codes["OnBn"] == P.coarse_fine_code(6, 255, n_type=True)
    assert codes["PrBp"] == 9000 and codes["ApsCas"] == P.vdac_code(20, 5)
    assert codes["OffBn"] == DEFAULT_CODES["OffBn"]
    assert settings.aps_exposure_us == 8000 and settings.aps_frame_interval_us == 40000


@pytest.mark.parametrize(
    "text, message",
    [
        ("[biases]\nOnnBn = 5\n", "unknown bias 'OnnBn'"),
        ("[biases]\nOnBn = { coarse = 9, fine = 1 }\n", "coarse must be an integer in 0..7"),
        ("[biases]\nOnBn = { volts = 9 }\n", "bias OnBn"),
        ("[settings]\nexposure = 5\n", "unknown setting 'exposure'"),
        ("[settings]\naps_exposure_us = -5\n", "aps_exposure_us must be a non-negative int"),
        ("[settings]\naps_exposure_us = 5000000\n", "aps_exposure_us = 5000000 is outside"),
        ("[settings]\nimu_gyro_full_scale = 4\n", "imu_gyro_full_scale = 4 is outside 0..3"),
        ("[bias]\n", "unknown table"),
        ("biases = 5\n", "biases must be a table, got 5"),
        ("settings = [1]\n", "settings must be a table"),
        ("not toml [", "not valid TOML"),
    ],
)
def test_bad_bias_files_say_what_is_wrong(tmp_path, text, message):
    f = tmp_path / "b.toml"
    f.write_text(text)
    with pytest.raises(InputError, match=message):
        load_bias_file(f)


def test_raw_bias_code_range():
    with pytest.raises(InputError, match="16-bit"):
        bias_codes({"OnBn": 70000})
