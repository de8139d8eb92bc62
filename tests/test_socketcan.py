"""The bench on a kernel CAN bus, each process its own, as a user runs it (issue 21):

- firmware-sim in its own process with its node on a vcan (`firmware-sim --can socketcan:vcan-…`),
  `northfinder find --config bench.toml` with `interface = "socketcan"`, then `northfinder replay`;
- firmware-sim's emulated USB-CAN adapter with the kernel's slcan driver attached (`slcand -o -c -s6
  PTY slcan-…`), the find on socketcan over it, then replay;
- `northfinder find --simulate --can socketcan:vcan-…`.

Each on a bus of its own (tests/socketcan_bus.py). They need a kernel with CAN and root: CI runs them
in a User-Mode Linux guest (`python3 tools/vcan_guest.py`), which fails when any is skipped.
"""

from __future__ import annotations

import json
from pathlib import Path

import pytest
from helpers import run_cli
from socketcan_bus import interface_stats, kernel_slcan, own_vcan

from northfinder.rundir import RESULT
from northfinder.simulate import SimSettings, SimulatorProcess

pytestmark = [pytest.mark.socketcan, pytest.mark.slow]

POSITIONS = 3
DWELL_S = 2.0
TIME_SCALE = 10.0  # lossless in the guest at 10× and 20× (3 × 4 s, IMU 100 Hz: tools/socketcan_speed.py);
# 30× re-measured positions. The finds' wall time is mostly process start-up: 20× saved nothing
LATITUDE_DEG = 40.0
# the stiffer stage, and the IMU at 100 Hz: the guest has one slow CPU (issue 21 is about the CAN bus)
FAST_STAGE_TOML = ("stage_speed_dps = 90.0\nstage_accel_dps2 = 360.0\nstage_ringing_decay_s = 0.1\n"
                   "imu_rate_hz = 100\n")
FIND_TIMEOUT_S = 300.0


def _bench_toml(endpoints: dict, interface: str, channel: str) -> str:
    return (f'[turntable]\nport = "{endpoints["turntable"]}"\nspeed_deg_s = 90.0\n'
            f'[imu]\nport = "{endpoints["imu"]}"\nrate_hz = 100\n'
            f'[accelerometer]\ninterface = "{interface}"\nchannel = "{channel}"\n'
            f'[site]\nlatitude_deg = {LATITUDE_DEG}\n')


def _losses(result: dict) -> str:
    """What the find lost and measured again: a find that loses samples measures the position again
    and still passes, so the log says it (the time scale above is chosen for none)."""
    f = result["faults"]
    imu, acc = f["imu"], f["accel"]
    return (f"lost: IMU {imu['lost_samples']}, accelerometer {acc['lost_samples']} (kernel drops "
            f"{acc.get('kernel_drops', 0)}); positions measured again {len(f['remeasured'])}")


def _find_and_replay(tmp_path: Path, endpoints: dict, interface: str, channel: str) -> tuple[str, str]:
    """`find --config` on the bus, then `replay`: both complete, the replay identical; their lines."""
    bench = tmp_path / "bench.toml"
    bench.write_text(_bench_toml(endpoints, interface, channel))
    run = tmp_path / "run"
    found = run_cli("find", "--config", str(bench), "--positions", str(POSITIONS), "--dwell", str(DWELL_S),
                    "--no-report", "--out", str(run), cwd=tmp_path, timeout_s=FIND_TIMEOUT_S)
    assert found.returncode == 0, found.stderr[-3000:]
    live = json.loads((run / RESULT).read_text())
    assert len(live["positions"]) == POSITIONS
    assert (run / "can.asc").exists()
    replayed = run_cli("replay", "--quiet", str(run), cwd=tmp_path, timeout_s=FIND_TIMEOUT_S)
    assert replayed.returncode == 0, replayed.stdout + replayed.stderr
    line = replayed.stdout.strip().splitlines()[-1]
    assert "identical to the live result.json" in line, line
    assert f"complete run, {POSITIONS} of {POSITIONS} positions" in line, line
    print(f"\n{interface}:{channel} find: heading {live['heading_deg']:.6f}° ± {live['heading_std_deg']:.6f}°"
          f"\n{interface}:{channel} find {_losses(live)}\n{interface}:{channel} replay: {line}")
    return found.stdout, line


def _sim(tmp_path: Path, can: str | None) -> SimulatorProcess:
    config = tmp_path / "sim.toml"
    config.write_text(FAST_STAGE_TOML)
    return SimulatorProcess(SimSettings(latitude_deg=LATITUDE_DEG, time_scale=TIME_SCALE, seed=21,
                                        config=str(config), can=can))


def test_firmware_sim_on_socketcan_and_find_config_replay_bit_for_bit(tmp_path):
    with own_vcan("vcan-xfind") as channel, _sim(tmp_path, f"socketcan:{channel}") as endpoints:
        assert endpoints["can"]["interface"] == "socketcan" and endpoints["can"]["channel"] == channel
        _find_and_replay(tmp_path, endpoints, "socketcan", channel)
        stats = interface_stats(channel)
        print(f"{channel} statistics: rx_packets {stats['rx_packets']}, rx_dropped {stats['rx_dropped']}")


def test_find_through_the_kernel_slcan_driver_on_firmware_sims_adapter(tmp_path):
    with _sim(tmp_path, None) as endpoints:
        assert endpoints["can"]["interface"] == "slcan"
        with kernel_slcan(endpoints["can"]["channel"], "slcan-xfind") as channel:
            _find_and_replay(tmp_path, endpoints, "socketcan", channel)


def test_find_simulate_can_socketcan(tmp_path):
    with own_vcan("vcan-sim") as channel:
        sim_config = tmp_path / "sim.toml"
        sim_config.write_text(FAST_STAGE_TOML)
        run = tmp_path / "run"
        found = run_cli("find", "--simulate", "--can", f"socketcan:{channel}", "--positions", str(POSITIONS),
                        "--dwell", str(DWELL_S), "--time-scale", str(TIME_SCALE), "--sim-config",
                        str(sim_config), "--no-report", "--out", str(run), cwd=tmp_path,
                        timeout_s=FIND_TIMEOUT_S)
        assert found.returncode == 0, found.stderr[-3000:]
        config = json.loads((run / "config.json").read_text())
        assert config["bench"]["accelerometer"]["interface"] == "socketcan"
        assert config["bench"]["accelerometer"]["channel"] == channel
        assert config["simulate"]["can"] == f"socketcan:{channel}"
        result = json.loads((run / RESULT).read_text())
        assert len(result["positions"]) == POSITIONS
        print(f"\nfind --simulate --can socketcan:{channel}: {_losses(result)}")


def test_frames_the_kernel_drops_on_a_full_socket_are_counted():
    """SO_RXQ_OVFL through the driver's socket wrapper: a reader that does not read while 1000 frames
    arrive keeps what fits its (here smallest) receive buffer; received + counted drops = sent."""
    import socket

    import can

    from northfinder.drivers.accelerometer import _count_kernel_drops

    with own_vcan("vcan-drops") as channel:
        reader = can.Bus(interface="socketcan", channel=channel)
        sender = can.Bus(interface="socketcan", channel=channel)
        try:
            counting = _count_kernel_drops(reader)
            assert counting is not None and counting.receive_buffer_bytes >= 4 * 1024 * 1024
            counting.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, 0)  # the kernel's minimum
            sent = 1000
            for k in range(sent):
                sender.send(can.Message(arbitration_id=0x190, data=k.to_bytes(2, "little"),
                                        is_extended_id=False))
            received = 0
            while reader.recv(timeout=0.5) is not None:
                received += 1
            assert 0 < received < sent
            # the count rides on the next frame queued after the drops (socket(7), SO_RXQ_OVFL)
            sender.send(can.Message(arbitration_id=0x190, data=b"\xff\xff", is_extended_id=False))
            assert reader.recv(timeout=5) is not None
            assert received + counting.kernel_drops == sent
            print(f"\n{sent} sent, {received} received, {counting.kernel_drops} dropped by the kernel")
        finally:
            reader.shutdown()
            sender.shutdown()
