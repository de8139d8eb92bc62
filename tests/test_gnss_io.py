"""NMEA on both sides, without ports: golden vectors through northfinder's decoder and
firmware_sim's formatter, the two checksums and the two ENU maps against each other, epoch
assembly when sentences are lost, and property tests that bad bytes are counted, never raised
and never turned into a fix."""

from __future__ import annotations

import datetime as dt
import math

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from firmware_sim.devices import gnss as sim
from firmware_sim.physics.vehicle import VehicleTrajectory
from firmware_sim.physics.world import Site, World
from northfinder.align.strapdown import LocalLevel
from northfinder.codecs import nmea
from northfinder.codecs.nmea import LocalEnu, NmeaDecoder, fixes_to_arrays
from northfinder.drivers.gnss import decode_nmea_log

# one unit of the last printed digit of a 7-decimal-minute field, in degrees
LAT_LSB_DEG = 1e-7 / 60.0
PYNMEAGPS_ROUND_DEG = 1e-10  # pynmeagps rounds degrees to 10 decimals


def _decode(data: bytes):
    dec = NmeaDecoder()
    return dec.feed(data), dec.stats


# -- golden vectors ----------------------------------------------------------------------------
def test_golden_good_sentences_decode_to_their_values(golden):
    good = golden["nmea"]["good"]
    fixes, stats = _decode(b"".join(v["sentence"].encode() for v in good))
    gga, rmc, vtg, nofix = good
    assert len(fixes) == 1 and stats.fixes == 1
    f = fixes[0]
    assert abs(f.lat_deg - gga["lat_deg"]) <= PYNMEAGPS_ROUND_DEG
    assert abs(f.lon_deg - gga["lon_deg"]) <= PYNMEAGPS_ROUND_DEG
    assert f.alt_m == gga["alt_m"] and f.fix_quality == gga["fix_quality"] and f.num_sv == gga["num_sv"]
    assert f.geoid_sep_m == -8.2 and f.height_m == pytest.approx(45.4 - 8.2, abs=1e-12) and f.hdop == 0.8
    assert f.date == dt.date(2026, 11, 22) and f.utc_sod_s == 12 * 3600 + 35 * 60 + 19
    assert f.time_s == dt.datetime(2026, 11, 22, 12, 35, 19, tzinfo=dt.UTC).timestamp()
    # velocity from RMC: speed in knots, course clockwise from north
    assert f.speed_m_s == pytest.approx(rmc["speed_knots"] * 1852 / 3600, rel=1e-15)
    assert f.course_deg == rmc["course_deg"] == vtg["course_deg"]
    c = math.radians(rmc["course_deg"])
    assert f.vel_enu_m_s == pytest.approx((f.speed_m_s * math.sin(c), f.speed_m_s * math.cos(c), 0.0))
    assert vtg["speed_kmh"] == pytest.approx(rmc["speed_knots"] * 1.852, abs=5e-4)
    assert nofix["fix_quality"] == 0 and stats.no_fix == 1 and stats.sentences == 4
    assert (
        stats.bad_checksum == stats.truncated == stats.malformed == stats.unknown == stats.garbage_bytes == 0
    )


def test_golden_bad_sentences_are_counted_and_skipped(golden):
    good = "".join(v["sentence"] for v in golden["nmea"]["good"][:3]).encode()
    for bad in golden["nmea"]["bad"]:
        dec = NmeaDecoder()
        assert dec.feed(bad.encode()) == []
        s = dec.stats
        assert s.bad_checksum + s.truncated + s.malformed + s.unknown == 1, (bad, s)
        assert s.sentences == 0 and s.fixes == 0
        assert len(dec.feed(good)) == 1  # the decoder goes on after it


def test_a_wrong_checksum_is_counted_as_such(golden):
    line = golden["nmea"]["good"][0]["sentence"]
    fixes, s = _decode(line.replace("*5A", "*5B").encode())
    assert fixes == [] and s.bad_checksum == 1 and s.truncated == 0


def test_firmware_sim_formats_the_golden_sentences_byte_for_byte(golden):
    gga, rmc, vtg, nofix = golden["nmea"]["good"]
    utc = dt.datetime(2026, 11, 22, 12, 35, 19, tzinfo=dt.UTC)
    assert (
        sim.format_gga(
            utc,
            gga["lat_deg"],
            gga["lon_deg"],
            gga["alt_m"],
            num_sv=gga["num_sv"],
            hdop=0.8,
            geoid_sep_m=-8.2,
        ).decode()
        == gga["sentence"]
    )
    assert (
        sim.format_rmc(utc, gga["lat_deg"], gga["lon_deg"], rmc["speed_knots"], rmc["course_deg"]).decode()
        == rmc["sentence"]
    )
    assert sim.format_vtg(rmc["speed_knots"], vtg["course_deg"]).decode() == vtg["sentence"]
    midnight = dt.datetime(2026, 11, 22, tzinfo=dt.UTC)
    assert sim.format_gga(midnight, 0.0, 0.0, 0.0, quality=0, hdop=99.9).decode() == nofix["sentence"]


@settings(max_examples=200, deadline=None)
@given(st.binary(min_size=0, max_size=90))
def test_both_checksums_agree(body):
    assert nmea.checksum(body) == sim.nmea_checksum(body)


# -- formatting round trip (firmware_sim writes, northfinder reads) ----------------------------
@settings(max_examples=150, deadline=None)
@given(
    lat=st.floats(-89.999, 89.999),
    lon=st.floats(-179.999, 179.999),
    alt=st.floats(-400.0, 9000.0),
    speed=st.floats(0.0, 80.0),
    course=st.floats(0.0, 359.99),
)
def test_sim_sentences_decode_to_what_was_formatted(lat, lon, alt, speed, course):
    utc = dt.datetime(2026, 11, 22, 23, 59, 59, 990000, tzinfo=dt.UTC)
    kn = speed / nmea.KNOT_M_S
    data = (
        sim.format_gga(utc, lat, lon, alt)
        + sim.format_rmc(utc, lat, lon, kn, course)
        + sim.format_vtg(kn, course)
    )
    (fix,), stats = _decode(data)
    tol = LAT_LSB_DEG / 2 + PYNMEAGPS_ROUND_DEG + 1e-12
    assert abs(fix.lat_deg - lat) <= tol and abs(fix.lon_deg - lon) <= tol
    assert abs(fix.alt_m - alt) <= 0.0005 + 1e-9
    assert abs(fix.speed_m_s - speed) <= 0.0005 * nmea.KNOT_M_S + 1e-9
    assert abs((fix.course_deg - course + 180) % 360 - 180) <= 0.005 + 1e-9
    assert fix.utc_sod_s == 86399.99 and stats.fixes == 1


def test_minutes_that_round_up_carry_into_the_degrees():
    lat = 40.0 - 1e-11  # 39°59.99999999′ prints as 40°00.0000000′, never 39°60′
    assert sim.format_lat(lat) == "4000.0000000,N"
    assert sim.format_lon(-(116.0 - 1e-11)) == "11600.0000000,W"


# -- local ENU ---------------------------------------------------------------------------------
def test_local_enu_is_the_ins_map_and_the_receivers_inverse():
    ref = LocalEnu(40.0, 116.3, 100.0)
    ll = LocalLevel(math.radians(40.0), math.radians(116.3), 100.0)
    enu = np.random.default_rng(0).uniform(-20e3, 20e3, size=(500, 3)) * [1, 1, 0.01]
    lat, lon, h = ref.from_enu(enu)
    ins = ll.to_enu(np.deg2rad(lat), np.deg2rad(lon), h)
    assert np.max(np.abs(ins - enu)) < 1e-6  # metres: the same map as the strapdown's LocalLevel
    assert np.max(np.abs(ref.to_enu(lat, lon, h) - enu)) < 1e-6
    rx = sim.GnssReceiver(VehicleTrajectory(duration_s=1.0), site=Site(40.0, 100.0), longitude_deg=116.3)
    try:  # firmware_sim's own map (its own WGS-84 radii) inverts northfinder's
        lat2, lon2, h2 = rx.enu_to_geodetic(enu)
    finally:
        rx.close()
    assert np.max(np.abs(ref.to_enu(lat2, lon2, h2) - enu)) < 1e-6


def test_wgs84_radii_of_curvature():
    # textbook values at the equator: R_M = a(1−e²), R_N = a; at the pole both a/√(1−e²)
    r_m, r_n = nmea.radii_of_curvature_m(0.0)
    assert r_m == pytest.approx(6335439.327, abs=1e-3) and r_n == 6378137.0
    r_m, r_n = nmea.radii_of_curvature_m(90.0)
    assert r_m == pytest.approx(r_n) == pytest.approx(6399593.626, abs=1e-3)


def test_longitude_difference_wraps_across_the_antimeridian():
    ref = LocalEnu(0.0, 179.9999, 0.0)
    e = ref.to_enu(0.0, -179.9999, 0.0)[0]
    assert e == pytest.approx(math.radians(0.0002) * 6378137.0, rel=1e-9)


# -- epochs ------------------------------------------------------------------------------------
def _epochs(n: int, start: dt.datetime | None = None, rate_hz: int = 10) -> list[list[bytes]]:
    """n epochs of [GGA, RMC, VTG] from the sim formatter, moving north-east."""
    start = start or dt.datetime(2026, 11, 22, 12, 0, tzinfo=dt.UTC)
    out = []
    for k in range(n):
        utc = start + dt.timedelta(microseconds=k * 1_000_000 // rate_hz)
        lat, lon, kn = 40.0 + k * 1e-6, 116.0 + k * 1e-6, 10.0 + 0.01 * k
        out.append(
            [
                sim.format_gga(utc, lat, lon, 50.0 + k),
                sim.format_rmc(utc, lat, lon, kn, 45.0),
                sim.format_vtg(kn, 45.0),
            ]
        )
    return out


def _join(epochs) -> bytes:
    return b"".join(b"".join(e) for e in epochs)


def test_lost_sentences_cost_what_they_carried():
    ep = _epochs(6)
    clean, _ = _decode(_join(ep))
    ep[1][2] = b""  # VTG lost: the next GGA closes the epoch, velocity from RMC
    ep[2][0] = b""  # GGA lost: no position, no fix
    ep[3][1] = ep[3][2] = b""  # RMC and VTG lost: position without velocity
    ep[4][1] = b""  # RMC lost: velocity from VTG, date from the last RMC
    fixes, s = _decode(_join(ep))
    assert [f.utc_sod_s for f in fixes] == [clean[i].utc_sod_s for i in (0, 1, 3, 4, 5)]
    assert fixes[1] == clean[1] and fixes[3] == clean[4] and fixes[4] == clean[5]
    assert fixes[2].vel_enu_m_s is None and fixes[2].speed_m_s is None
    assert fixes[2].lat_deg == clean[3].lat_deg and fixes[2].time_s == clean[3].time_s
    assert s.incomplete_epochs == 1 and s.no_velocity == 1 and s.missed_epochs == 1 and s.fixes == 5


def test_midnight_rolls_the_date_over_even_without_rmc():
    ep = _epochs(4, start=dt.datetime(2026, 11, 22, 23, 59, 59, 800000, tzinfo=dt.UTC))
    ep[2][1] = ep[3][1] = b""  # no RMC (no date) after midnight
    fixes, s = _decode(_join(ep))
    assert [f.date for f in fixes] == [dt.date(2026, 11, 22)] * 2 + [dt.date(2026, 11, 23)] * 2
    assert np.allclose(np.diff([f.time_s for f in fixes]), 0.1) and s.missed_epochs == 0


def test_fixes_wait_for_a_date_then_get_it():
    ep = _epochs(3)
    ep[0][1] = ep[1][1] = b""  # the first two epochs have no RMC
    fixes, _ = _decode(_join(ep))
    clean, _ = _decode(_join(_epochs(3)))
    assert [f.time_s for f in fixes] == [f.time_s for f in clean]


def test_a_receiver_that_never_sends_a_date_gives_seconds_of_day():
    ep = [[e[0]] for e in _epochs(nmea.MAX_UNDATED_FIXES + 5)]  # GGA only
    fixes, s = _decode(_join(ep))
    assert len(fixes) == s.fixes == nmea.MAX_UNDATED_FIXES + 5 - 1  # the last epoch is still open
    assert fixes[0].date is None and fixes[0].time_s == 12 * 3600.0 and s.no_velocity == s.fixes


def test_unknown_sentence_types_are_counted_not_used():
    gsv = sim.sentence("GP", "GSV", "1,1,01,05,40,083,46")
    txt = sim.sentence("P", "UBX", "00,1,2")
    fixes, s = _decode(gsv + txt + _join(_epochs(1)))
    assert len(fixes) == 1 and s.unknown == 2


def test_fixes_to_arrays_converts_all_at_once():
    fixes, _ = _decode(_join(_epochs(5)))
    a = fixes_to_arrays(fixes)
    assert a.pos_enu_m.shape == (5, 3) and np.all(a.pos_enu_m[0] == 0.0)
    k_e, k_n = a.ref.scale_m_per_rad
    assert np.allclose(np.diff(a.pos_enu_m[:, 1]), math.radians(1e-6) * k_n, atol=2e-4)
    assert np.allclose(np.diff(a.pos_enu_m[:, 2]), 1.0)
    assert np.allclose(a.vel_enu_m_s[:, 0], a.vel_enu_m_s[:, 1]) and np.all(a.vel_enu_m_s[:, 2] == 0)


# -- property tests: bad bytes never raise and never become a fix ------------------------------
@settings(max_examples=150, deadline=None)
@given(st.binary(max_size=600))
def test_random_bytes_never_raise_and_never_fix(data):
    fixes, s = _decode(data)
    assert fixes == [] and s.bytes == len(data)
    fixes, s = _decode(b"$GNGGA," + data)
    assert fixes == []


@settings(max_examples=60, deadline=None)
@given(st.text(max_size=300))
def test_any_text_replays_without_raising(text):
    fixes, s = decode_nmea_log(text)
    assert fixes == [] and s.bytes == len(text)


_CLEAN = _join(_epochs(4))
_CLEAN_FIXES = decode_nmea_log(_CLEAN)[0]


_NL = np.frombuffer(_CLEAN, np.uint8) == ord("\n")
_LINE_OF = np.cumsum(_NL) - _NL  # the sentence each byte belongs to (its line end included)


@settings(max_examples=200, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(st.lists(st.tuples(st.integers(0, len(_CLEAN) - 1), st.sampled_from(["set", "delete", "insert"]),
                          st.integers(1, 255)), min_size=1, max_size=8))
def test_mutated_stream_yields_only_true_fixes(mutations):
    """At most one changed byte per sentence: an 8-bit XOR catches every single-byte substitution,
    deletion or insertion (of a non-zero byte) but not every pair, so that is the guarantee."""
    seen, edits = set(), []
    for pos, op, value in mutations:
        if _LINE_OF[pos] not in seen:
            seen.add(_LINE_OF[pos])
            edits.append((pos, op, value))
    data = bytearray(_CLEAN)
    for pos, op, value in sorted(edits, reverse=True):  # from the end: earlier offsets stay valid
        if op == "set":
            data[pos] = value if value != data[pos] else (value % 255) + 1
        elif op == "delete":
            del data[pos]
        else:
            data.insert(pos, value)
    dec = NmeaDecoder()
    fixes, s = dec.feed(bytes(data)), dec.stats
    by_time = {f.time_s: f for f in _CLEAN_FIXES}
    for f in fixes:  # every fix is one of the clean stream's, at most without its velocity
        ref = by_time[f.time_s]
        assert f == ref or (f.vel_enu_m_s is None and f.lat_deg == ref.lat_deg and f.alt_m == ref.alt_m)
    damaged = s.bad_checksum + s.truncated + s.unknown + s.malformed + s.garbage_bytes
    # any loss is counted (or still waiting: the last line end was hit)
    assert damaged > 0 or dec.pending_bytes > 0 or (fixes == _CLEAN_FIXES and s.sentences == 12)


@settings(max_examples=60, deadline=None)
@given(st.lists(st.integers(0, len(_CLEAN)), max_size=20))
def test_chunking_does_not_change_the_result(cuts):
    dec = NmeaDecoder()
    fixes = []
    edges = [0, *sorted(cuts), len(_CLEAN)]
    for a, b in zip(edges[:-1], edges[1:], strict=True):
        fixes += dec.feed(_CLEAN[a:b])
    assert fixes == _CLEAN_FIXES and dec.stats == decode_nmea_log(_CLEAN)[1]


def test_an_endless_sentence_is_cut_the_same_way_in_any_chunking():
    data = b"$GNGGA," + b"1" * 600 + b"\r\n" + _join(_epochs(1))
    whole = decode_nmea_log(data)
    dec = NmeaDecoder()
    parts = [dec.feed(data[i : i + 7]) for i in range(0, len(data), 7)]
    assert [f for p in parts for f in p] == whole[0] and dec.stats == whole[1]
    assert whole[1].truncated == 1 and len(whole[0]) == 1


# -- the receiver without a port ---------------------------------------------------------------
def _receiver(**kw):
    traj = VehicleTrajectory(duration_s=30.0)
    return sim.GnssReceiver(World(Site(40.0, 100.0), traj), **kw), traj


def test_receiver_bytes_do_not_depend_on_how_time_is_split():
    a, _ = _receiver(rng=5, faults={"gnss-bad-checksum-rate": 0.1, "gnss-truncate-rate": 0.1}, fault_seed=9)
    b, _ = _receiver(rng=5, faults={"gnss-bad-checksum-rate": 0.1, "gnss-truncate-rate": 0.1}, fault_seed=9)
    try:
        whole = a.epoch_bytes(np.arange(0, 50))
        parts = b"".join(
            b.epoch_bytes(np.arange(i, i + 7)[np.arange(i, i + 7) < 50]) for i in range(0, 50, 7)
        )
    finally:
        a.close()
        b.close()
    assert whole == parts


def test_receiver_faults_are_what_the_decoder_counts():
    rx, _ = _receiver(
        rng=1,
        faults={"gnss-bad-checksum-rate": 0.05, "gnss-truncate-rate": 0.05, "gnss-nofix": "5:2"},
        fault_seed=3,
    )
    try:
        data = rx.epoch_bytes(np.arange(0, 300))
    finally:
        rx.close()
    fixes, s = decode_nmea_log(data)
    assert s.bad_checksum == rx.sentences_corrupted > 0
    assert s.truncated == rx.sentences_truncated > 0
    # 20 epochs in [5 s, 7 s): 3 no-fix sentences each unless a fault hit one of them
    assert 0 < s.no_fix <= 60 and s.no_fix >= 60 - rx.sentences_corrupted - rx.sentences_truncated
    t = np.array([f.utc_sod_s for f in fixes]) - 12 * 3600
    assert not np.any((t >= 5.0 - 1e-9) & (t < 7.0 - 1e-9))
    assert s.missed_epochs >= 20 and s.fixes + s.missed_epochs == 300


def test_receiver_rejects_bad_settings():
    traj = VehicleTrajectory(duration_s=1.0)
    with pytest.raises(ValueError, match="rate 7"):
        sim.GnssReceiver(traj, rate_hz=7)
    with pytest.raises(ValueError, match="gnss-nofix"):
        sim.GnssReceiver(traj, faults={"gnss-nofix": "5"})
    with pytest.raises(ValueError, match="gnss-truncate-rate"):
        sim.GnssReceiver(traj, faults={"gnss-truncate-rate": 2.0})
    with pytest.raises(TypeError, match="antenna_enu"):
        sim.GnssReceiver(object())


def test_a_static_bench_reports_a_fixed_antenna_position():
    world = World.static(heading_deg=30.0, latitude_deg=-33.9) if hasattr(World, "static") else None
    if world is None:
        pytest.skip("World.static not available")
    rx = sim.GnssReceiver(world, rng=2, sigma_h_m=0.0, sigma_v_m=0.0, sigma_vel_m_s=0.0, longitude_deg=-70.6)
    try:
        fixes, _ = decode_nmea_log(rx.epoch_bytes(np.arange(3)))
    finally:
        rx.close()
    a = fixes_to_arrays(fixes, LocalEnu(-33.9, -70.6, world.site.height_m))
    r = np.array([0.5, 1.5, 1.2])  # antenna = C_p^n r: heading 30°, level
    psi = math.radians(30.0)
    expect = [r[0] * math.cos(psi) + r[1] * math.sin(psi), -r[0] * math.sin(psi) + r[1] * math.cos(psi), r[2]]
    assert np.allclose(a.pos_enu_m, expect, atol=2e-4)  # 7-decimal minutes and mm altitude
    assert np.all(a.vel_enu_m_s == 0.0) and fixes[0].lat_deg < 0 and fixes[0].lon_deg < 0
