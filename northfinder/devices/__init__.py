"""Device roles: what the sequencer and the runs speak to (a rotary stage, an inertial stream, a tilt
sensor, a GNSS receiver), the device-neutral data they produce, and the registry of models by name.

Each role is a small abstract class in the manner of python-can's `BusABC`: a few abstract methods a
model implements, the public methods the sequencer uses built once on top of them. A model (the
SMC100, the KVH format A, our CANopen node, an NMEA receiver, a lab's own) lives in
`northfinder.models` or in a third-party package, and is found by name through
:mod:`northfinder.devices.registry`. Nothing here does I/O or imports a model.
"""
