"""The golden file is what tools/make_golden_vectors.py writes, and its CRC check value holds."""

from __future__ import annotations

import importlib.util
import json
from pathlib import Path

from conftest import GOLDEN_PATH


def _generator():
    path = Path(__file__).parent.parent / "tools" / "make_golden_vectors.py"
    spec = importlib.util.spec_from_file_location("make_golden_vectors", path)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def test_golden_file_is_up_to_date():
    assert json.loads(GOLDEN_PATH.read_text()) == json.loads(json.dumps(_generator().build()))


def test_crc_check_value_from_protocols_md():
    gen = _generator()
    assert gen.crc32_mpeg2_via_zlib(b"123456789") == 0x0376E6E7
    assert gen.crc32_mpeg2_via_zlib(b"") == 0xFFFFFFFF  # init, no final xor
