"""The built-in models, one module per model: the model's driver implementing its role (on the driver
in `northfinder.drivers`, the bytes in `northfinder.codecs`) and its registry entry `SPEC`.
Only `northfinder.devices.registry` names these modules (by import path); no run or sequencer
imports them (import-linter contract `no-models-above-roles`)."""
