"""Biases and camera settings from a TOML file (`evcap record --biases FILE`).

[biases]                      # any subset; the others keep the vendor defaults
OnBn = { coarse = 5, fine = 255 }         # coarse-fine (type and flags from the bias)
PadFollBn = { coarse = 7, fine = 215, enabled = false }
ApsCas = { voltage = 21, current = 6 }    # VDAC
SSP = { ref = 1, reg = 33 }               # shifted source
PrBp = 9133                                # or the raw 16-bit code

[settings]                    # any field of evcap.acquire.protocol.Settings
aps_exposure_us = 8000
"""

from __future__ import annotations

import dataclasses
from pathlib import Path

from evcap.acquire import protocol as P
from evcap.errors import InputError
from evcap.toml_file import Table, read_toml


def load_bias_file(path: str | Path) -> tuple[dict[str, int], P.Settings]:
    """(bias codes for every bias, settings), the file's values over the vendor defaults."""
    doc = Table(read_toml(path, "biases"), str(path))
    biases, settings = doc.get("biases", dict, {}), doc.get("settings", dict, {})
    unknown = set(doc.data) - doc.used
    if unknown:
        raise InputError(
            f"{path}: unknown table(s) {', '.join(sorted(unknown))}; "
            "expected [biases] and [settings]"
        )
    return bias_codes(biases, str(path)), settings_from(settings, str(path))


def bias_codes(values: dict, where: str = "biases") -> dict[str, int]:
    codes = P.default_bias_codes()
    for name, value in values.items():
        if name not in P.BIASES:
            raise InputError(f"{where}: unknown bias {name!r}; known: {', '.join(P.BIASES)}")
        if isinstance(value, int) and not isinstance(value, bool):
            if not 0 <= value <= 0xFFFF:
                raise InputError(f"{where}: bias {name} code {value} is not a 16-bit value")
            codes[name] = value
        elif isinstance(value, dict):
            try:
                codes[name] = P.BIASES[name].code(**value)
            except TypeError as e:
                raise InputError(f"{where}: bias {name}: {e}") from None
            except InputError as e:
                raise InputError(f"{where}: bias {name}: {e}") from None
        else:
            raise InputError(f"{where}: bias {name} must be a table or an integer code")
    return codes


def settings_from(values: dict, where: str = "settings") -> P.Settings:
    fields = {f.name: f for f in dataclasses.fields(P.Settings)}
    for key, value in values.items():
        if key not in fields:
            raise InputError(f"{where}: unknown setting {key!r}; known: {', '.join(fields)}")
        expected = bool if fields[key].type in ("bool", bool) else int
        if type(value) is not expected or (expected is int and value < 0):
            raise InputError(
                f"{where}: setting {key} must be a non-negative {expected.__name__}, got {value!r}"
            )
    return P.Settings(**values)
