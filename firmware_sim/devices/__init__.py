"""Emulated devices, each speaking its protocol from docs/PROTOCOLS.md."""
