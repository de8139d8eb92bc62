"""`northfinder check` probes the GNSS receiver of a bench.toml with a [gnss] port: the receiver's
line (model, its next fix, the NMEA counters) on a real pty fed golden-format sentences, and one
line naming the port when nothing NMEA comes."""

from __future__ import annotations

import os
import threading
import time

from northfinder.cli import main
from northfinder.codecs.nmea import checksum


def _sentence(body: str) -> bytes:
    return f"${body}*{checksum(body.encode()):02X}\r\n".encode()


def _epoch(k: int) -> bytes:
    """One 1 Hz epoch (GGA, RMC, VTG) at 12:35:k, the golden vectors' position."""
    t = f"1235{k % 60:02d}.00"
    return b"".join((
        _sentence(f"GNGGA,{t},4007.0380000,N,11631.0000000,E,1,12,0.8,45.400,M,-8.2,M,,"),
        _sentence(f"GNRMC,{t},A,4007.0380000,N,11631.0000000,E,0.000,0.00,221126,,,A"),
        _sentence("GNVTG,0.00,T,,M,0.000,N,0.000,K,A"),
    ))


def _feed(master: int, stop: threading.Event) -> None:
    k = 0
    while not stop.is_set():
        os.write(master, _epoch(k))
        k += 1
        time.sleep(0.1)  # 10 epochs per second of host time; the receiver's clock is in the sentences


def test_check_prints_the_gnss_receivers_model_and_fix(tmp_path, pty_pair, capsys):
    master, port = pty_pair
    bench = tmp_path / "bench.toml"
    bench.write_text(f'[gnss]\nport = "{port}"\n')
    stop = threading.Event()
    feeder = threading.Thread(target=_feed, args=(master, stop), daemon=True)
    feeder.start()
    try:
        rc = main(["check", "--config", str(bench)])
    finally:
        stop.set()
        feeder.join(timeout=10)
    out = capsys.readouterr().out
    gnss = [line for line in out.splitlines() if line.startswith(("ok    gnss", "FAIL  gnss"))]
    assert len(gnss) == 1, out
    line = gnss[0]
    assert line.startswith(f"ok    gnss on {port}: model nmea; fix quality 1, 12 satellites, HDOP 0.8"), line
    assert "40.117300° 116.516667°" in line and "[model nmea]" in line and " 0 bad checksum" in line, line
    assert rc == 3  # the turntable, IMU and accelerometer of this bench have no port


def test_a_silent_gnss_port_is_one_line_naming_it(tmp_path, pty_pair, capsys):
    _, port = pty_pair
    bench = tmp_path / "bench.toml"
    bench.write_text(f'[gnss]\nport = "{port}"\n')
    assert main(["check", "--config", str(bench)]) == 3
    out = capsys.readouterr().out
    line = next(line for line in out.splitlines() if port in line)
    assert line.startswith("FAIL  ") and "no NMEA sentences" in line, line


def test_a_bench_without_gnss_port_is_not_probed_for_one(tmp_path, capsys):
    bench = tmp_path / "bench.toml"
    bench.write_text("[site]\nlatitude_deg = 40.0\n")
    assert main(["check", "--config", str(bench)]) == 3
    lines = capsys.readouterr().out.splitlines()
    assert [line.split()[1] for line in lines if line.startswith(("ok", "FAIL"))] == [
        "turntable:", "imu:", "accelerometer:"]
