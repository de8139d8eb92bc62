"""The KVH decoder's plain-Python path for small chunks of whole good frames (issue 27 item 2)
gives exactly what the vectorized path gives: every output array and every counter."""

from __future__ import annotations

import numpy as np
import pytest

from northfinder.codecs import kvh


def _stream(seed: int, n: int = 3000) -> bytes:
    """Frames with the mishaps a line has: sequence gaps (dropped frames, some > 128), bad CRCs,
    garbage and ASCII lines between frames, a byte dropped inside a frame, invalid status bits."""
    rng = np.random.default_rng(seed)
    seq = np.cumsum(rng.choice([1, 1, 1, 1, 1, 1, 2, 5, 130], size=n))
    status = np.where(rng.random(n) < 0.05, 0x33, 0x77)
    raw = kvh.encode_frames(rng.normal(size=(n, 3)), rng.normal(size=(n, 3)), status, seq, np.full(n, 25))
    out = bytearray()
    for i in range(n):
        frame = bytearray(raw[i * 36:(i + 1) * 36])
        u = rng.random()
        if u < 0.01:
            frame[33] ^= 0x40  # bad CRC
        elif u < 0.02:
            del frame[int(rng.integers(0, 36))]  # a byte lost
        out += frame
        if rng.random() < 0.02:
            bit_message = b"\xfe\x81\x00\xaa\x7f\x7f\x7f\x7f\x7f\x7f\xfa"
            garbage = bytes(rng.integers(0, 256, int(rng.integers(1, 50))).astype(np.uint8))
            out += rng.choice([b"DR,1000\r\n", b"INVALID,=FOO\r\n", bit_message, garbage])
    return bytes(out)


def _decode(data: bytes, sizes: list[int]) -> tuple:
    dec = kvh.KvhDecoder()
    outs, p, lost, i = [], 0, 0, 0
    while p < len(data):
        size = sizes[i % len(sizes)]
        out = dec.feed(data[p:p + size])
        outs.append(out)
        lost += out.lost_samples
        p += size
        i += 1
    index = np.concatenate([o.sample_index for o in outs])
    frames = np.concatenate([o.frames for o in outs])
    return index, frames, lost, dec.stats, list(dec.unknown_gap_indices), dec.pending_bytes


@pytest.mark.parametrize("seed", [0, 1, 2])
@pytest.mark.parametrize("sizes", [[36], [216], [37, 200, 5, 216, 1000], [4096], [72, 36, 108, 3]])
def test_small_chunks_decode_as_the_whole_buffer(seed, sizes):
    data = _stream(seed)
    whole = _decode(data, [len(data)])  # one call: the vectorized path only
    parts = _decode(data, sizes)
    np.testing.assert_array_equal(parts[0], whole[0])
    assert parts[1].tobytes() == whole[1].tobytes()
    assert parts[2] == whole[2]
    assert parts[3] == whole[3]
    assert parts[4] == whole[4]
    assert parts[5] == whole[5]
    assert whole[3].bad_crc > 0 and whole[3].resyncs > 0 and whole[3].unknown_gaps > 0  # mishaps there


def test_a_clean_real_time_chunk_takes_the_plain_path():
    """Six good frames back to back (216 B) are decoded without the vectorized path."""
    n = 100
    zeros = np.zeros((n, 3))
    raw = kvh.encode_frames(zeros, zeros, np.full(n, 0x77), np.arange(n), np.full(n, 25))
    dec = kvh.KvhDecoder()
    assert dec._feed_chain(raw[:216]) is not None
    assert dec._feed_chain(raw[216:216 + 35] + b"x") is None  # not whole frames: the general path decides


def test_crc_through_zlib_matches_the_reference():
    rng = np.random.default_rng(5)
    for n in (0, 1, 9, 32, 33, 100):
        data = bytes(rng.integers(0, 256, n).astype(np.uint8))
        assert kvh.crc32_mpeg2_fast(data) == kvh.crc32_mpeg2(data)
    assert kvh.crc32_mpeg2_fast(b"123456789") == 0x0376E6E7
