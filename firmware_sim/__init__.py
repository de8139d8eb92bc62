"""firmware_sim: the north-finding bench emulated with true physics over ptys and CAN.

An independent implementation: it imports nothing from `northfinder`. Physics from
docs/CONVENTIONS.md, byte formats from docs/PROTOCOLS.md, both written again here.
"""

import os as _os

__version__ = "0.1.0"

# One BLAS thread unless the user set otherwise, before anything loads numpy (OpenBLAS reads these
# once). The simulator's numpy work is elementwise or on small matrices; OpenBLAS's own threads only
# spin against the device loop and the client process on a shared host (a QR of 8 k × 9 took 99 ms
# with them on the loaded 2-core bench host, 2.5 ms with one; issue 27).
for _var in ("OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
    _os.environ.setdefault(_var, "1")
