"""firmware_sim: the north-finding bench emulated with true physics over ptys and CAN.

An independent implementation: it imports nothing from `northfinder`. Physics from
docs/CONVENTIONS.md, byte formats from docs/PROTOCOLS.md, both written again here.
"""

__version__ = "0.1.0"
