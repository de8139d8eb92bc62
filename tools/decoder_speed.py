"""How fast the decoders run on one core, against the devices' real-time rates.

KVH format A at 1 kHz needs 1 000 frames/s; the target is ≥ 100× that (10⁵ frames/s). The
script builds a stream of N valid frames (fixed seed), then times:

* the streaming decoder on the whole buffer at once (replay),
* the same decoder fed in chunks of 36, 216 and 4096 bytes (one frame; the reader thread's median
  chunk at real time; a full read), as × real time of the 1 kHz IMU and µs per call,
* the vectorized CRC alone, and the one-byte-at-a-time reference CRC (for scale),
* the CAN path (cantools decode + TPDO pairing) in frames/s against 200 frames/s (100 Hz pairs).

Each figure is the best of a few repeats (time.perf_counter). Run:
``python3 tools/decoder_speed.py [--frames 200000]``.
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))  # run from a checkout without installing

from northfinder.codecs import kvh  # noqa: E402
from northfinder.codecs.canopen import AccelFrameDecoder, CanCodec  # noqa: E402


def best_of(fn, repeats: int = 3) -> float:
    best = float("inf")
    for _ in range(repeats):
        t0 = time.perf_counter()
        fn()
        best = min(best, time.perf_counter() - t0)
    return best


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--frames", type=int, default=200_000)
    ap.add_argument("--chunk-bytes", type=int, nargs="+", default=[36, 216, 4096],
                    help="chunk sizes to feed the decoder (216 B is the reader's median chunk at real time)")
    args = ap.parse_args()
    n = args.frames
    rng = np.random.default_rng(0)
    stream = kvh.encode_frames(rng.normal(scale=1e-5, size=(n, 3)), rng.normal(size=(n, 3)),
                               np.full(n, 0x77), np.arange(n), np.full(n, 25))
    print(f"stream: {n} frames, {len(stream) / 1e6:.1f} MB")

    def whole():
        out = kvh.KvhDecoder().feed(stream)
        assert len(out) == n

    t = best_of(whole)
    print(f"KVH decoder, whole buffer      : {n / t:12,.0f} frames/s  ({n / t / 1000:,.0f}× the 1 kHz rate)")

    for chunk in args.chunk_bytes:
        m = min(n, max(2000, 200 * chunk // kvh.FRAME_SIZE))  # small chunks: fewer frames, same precision
        part = stream[: m * kvh.FRAME_SIZE]

        def chunked(part=part, chunk=chunk, m=m):
            dec = kvh.KvhDecoder()
            total = 0
            for i in range(0, len(part), chunk):
                total += len(dec.feed(part[i:i + chunk]))
            assert total == m

        t = best_of(chunked)
        label = f"KVH decoder, {chunk}-byte chunks"
        print(f"{label:31s}: {m / t:12,.0f} frames/s  ({m / t / 1000:,.0f}× real time at 1 kHz; "
              f"{t / (len(part) / chunk) * 1e6:,.1f} µs per call)")

    rows = np.frombuffer(stream, np.uint8).reshape(n, kvh.FRAME_SIZE)[:, :32]
    t = best_of(lambda: kvh.crc32_mpeg2_rows(rows))
    print(f"CRC-32/MPEG-2 vectorized       : {n / t:12,.0f} frames/s")
    m = min(n, 5000)
    t = best_of(lambda: [kvh.crc32_mpeg2(stream[i * 36:i * 36 + 32]) for i in range(m)], 1)
    print(f"CRC-32/MPEG-2 byte loop (ref.) : {m / t:12,.0f} frames/s")

    codec = CanCodec()
    frames = []
    for c in range(5000):
        frames.append(codec.encode("TPDO1", {"accel_x": c, "accel_y": -c}))
        frames.append(codec.encode("TPDO2", {"accel_z": 10**6, "temperature": 2500, "counter": c % 256,
                                             "status": 7}))

    def can_path():
        dec = AccelFrameDecoder(codec)
        for can_id, data in frames:
            dec.feed(can_id, data)
        assert len(dec.drain()) == 5000

    t = best_of(can_path)
    k = len(frames)
    print(f"CAN decode + pairing (cantools): {k / t:12,.0f} frames/s  ({k / t / 200:,.0f}× the 200 frames/s "
          "of 100 Hz pairs)")


if __name__ == "__main__":
    main()
