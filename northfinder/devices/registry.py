"""Models by name, per role — python-can's interface registry for northfinder's devices.

`bench.toml` names each device's model (`model = "smc100"` in `[turntable]`; the defaults are
today's models, so a file without the key still works); the run records it, and replay asks
:func:`decoder_for` for that model's decoder, so nothing above this module names a model.

The built-in models are listed by import path and loaded on first use (opening a bench loads only
its own models). A lab adds its own from its own package through the entry-point group
``northfinder.models``: each entry point names a :class:`ModelSpec`, e.g. in its pyproject.toml::

    [project.entry-points."northfinder.models"]
    acme-rot = "acme_stage:SPEC"
"""

from __future__ import annotations

import importlib
from collections.abc import Callable
from dataclasses import dataclass, field
from importlib import metadata
from typing import Any

from northfinder.errors import ConfigError

ENTRY_POINT_GROUP = "northfinder.models"
ROLES = ("turntable", "imu", "accelerometer", "gnss")
"""The roles, named as bench.toml's sections: rotary stage, inertial stream, tilt sensor, GNSS."""
DEFAULT_MODELS = {"turntable": "smc100", "imu": "kvh", "accelerometer": "nf-accel", "gnss": "nmea"}
"""The model of a section without `model =` (and of a run recorded before models had names)."""


@dataclass(frozen=True)
class ModelSpec:
    """One model of one role.

    `open(section, log_path, options)` opens the device from its bench.toml section (a config
    dataclass, or any object with the model's keys) with its raw log at `log_path`; `options` are
    what the run adds (e.g. `can_kwargs`, `eds_path`). `decoder()` returns the role's decoder
    (devices.imu.ImuDecoder, devices.tilt.TiltDecoder, devices.gnss.GnssDecoder); None for a stage."""

    role: str
    name: str
    open: Callable[[Any, Any, dict[str, Any]], Any]
    decoder: Callable[[], Any] | None = None
    description: str = ""
    simulated: dict[str, Any] = field(default_factory=dict)
    """What firmware-sim needs to emulate it (empty: firmware-sim has no emulation of this model)."""


BUILTIN: dict[str, str] = {
    "turntable/smc100": "northfinder.models.smc100:SPEC",
    "imu/kvh": "northfinder.models.kvh:SPEC",
    "accelerometer/nf-accel": "northfinder.models.nf_accel:SPEC",
    "gnss/nmea": "northfinder.models.nmea:SPEC",
    "turntable/apt": "northfinder.models.apt:SPEC",
    "imu/stim": "northfinder.models.stim:SPEC",
    "accelerometer/cia410": "northfinder.models.cia410:SPEC",
}

_loaded: dict[str, ModelSpec] = {}
_third_party: dict[str, metadata.EntryPoint] | None = None


def _entry_points() -> dict[str, metadata.EntryPoint]:
    global _third_party
    if _third_party is None:
        _third_party = {ep.name: ep for ep in metadata.entry_points(group=ENTRY_POINT_GROUP)}
    return _third_party


def refresh() -> None:
    """Forget the entry points read so far (after a package was installed in this process)."""
    global _third_party
    _third_party = None
    for key in [k for k in _loaded if k not in BUILTIN]:
        del _loaded[key]


def _load(target: str) -> ModelSpec:
    module, _, attr = target.partition(":")
    return getattr(importlib.import_module(module), attr)


def is_builtin(role: str, name: str) -> bool:
    return f"{role}/{name}" in BUILTIN


def available(role: str) -> list[str]:
    """The model names of a role: the built-in ones, then the installed packages' (sorted)."""
    builtin = [k.split("/", 1)[1] for k in BUILTIN if k.startswith(role + "/")]
    others = sorted(spec.name for spec in (ep.load() for ep in _entry_points().values()) if spec.role == role)
    return builtin + [n for n in others if n not in builtin]


def spec(role: str, name: str | None = None) -> ModelSpec:
    """The ModelSpec of `name` (default: the role's default model); ConfigError naming the choices."""
    if role not in ROLES:
        raise ConfigError(f"unknown device role {role!r} (one of {', '.join(ROLES)})")
    name = name or DEFAULT_MODELS[role]
    key = f"{role}/{name}"
    if key not in _loaded:
        if key in BUILTIN:
            _loaded[key] = _load(BUILTIN[key])
        else:
            loaded = (ep.load() for ep in _entry_points().values())
            found = [s for s in loaded if (s.role, s.name) == (role, name)]
            if not found:
                raise ConfigError(f"[{role}] model = {name!r}: no such model (installed: "
                                  f"{', '.join(available(role))}) — fix the name or install its package")
            _loaded[key] = found[0]
    return _loaded[key]


def model_of(section: Any, role: str) -> str:
    """The model a bench.toml section (or a run's recorded entry) names, or the role's default."""
    name = section.get("model") if isinstance(section, dict) else getattr(section, "model", "")
    return str(name or DEFAULT_MODELS[role])


def open_device(role: str, section: Any, log_path: Any = None, **options: Any) -> Any:
    """Open the device of a bench.toml section with the model it names (its `model_name` says which)."""
    name = model_of(section, role)
    device = spec(role, name).open(section, log_path, options)
    device.model_name = name
    return device


def decoder_for(role: str, model: str | None) -> Any:
    """The decoder of a recorded model (None or "" for a run recorded before models had names)."""
    s = spec(role, model or None)
    if s.decoder is None:
        raise ConfigError(f"the {role} model {s.name!r} has no raw-log decoder")
    return s.decoder()
