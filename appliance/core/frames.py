"""Frame files: one set of readings as CSV, one row per reading in protocol order.

Header ``drive_pos,drive_neg,meas_pos,meas_neg,volts``; electrode numbers 1-based.

>>> import numpy as np
>>> from appliance.core.protocols import adjacent_protocol
>>> print(frame_to_csv(adjacent_protocol(4), np.array([0.5, -0.25, 0.125, 1.0])).splitlines()[1])
1,2,3,4,5.000000000e-01
"""

from __future__ import annotations

import io

import numpy as np

from appliance.core.protocols import CSV_HEADER, Protocol
from appliance.errors import ModelInputInvalid

FRAME_HEADER = CSV_HEADER + ("volts",)


def frame_to_csv(protocol: Protocol, volts: np.ndarray) -> str:
    """CSV text of a frame: the protocol's rows with their readings (volts, 10 significant digits)."""
    volts = np.asarray(volts, dtype=float)
    if volts.shape != (len(protocol),):
        raise ModelInputInvalid(f"a frame of protocol {protocol.name!r} needs {len(protocol)} readings, "
                                f"got shape {volts.shape}")
    out = io.StringIO()
    out.write(",".join(FRAME_HEADER) + "\n")
    for row, v in zip(protocol.readings.tolist(), volts.tolist()):
        out.write(f"{row[0]},{row[1]},{row[2]},{row[3]},{v:.9e}\n")
    return out.getvalue()
