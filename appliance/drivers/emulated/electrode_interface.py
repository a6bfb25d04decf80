"""Where the electrodes meet the mat, as the analogue chain sees it, and what each kind of detector reports.

Each electrode's contact is a resistance in parallel with a capacitance (charge transfer and double
layer), so at the drive frequency it is a complex impedance ``Zc = R / (1 + j w R C)``. It enters a reading
three ways: the drive pair's contacts add to the voltage the current source must reach (its compliance,
on the magnitude); the return electrode's contact lifts every electrode by ``I Zc`` (a common-mode
voltage, with a quadrature part from C); and each measuring electrode's contact forms a divider with
its input's capacitance to ground (multiplexer, cable, in-amp), so two unequal contacts turn that
common-mode voltage into a differential one, mostly in quadrature. The sheet itself (the forward
model's transfer impedances) is resistive.

What reaches the reconstruction depends on the detector (``[board.measurement] detector``):
``rms`` (the AD8436) reports the magnitude, quadrature included, with the phase comparator's sign;
``synchronous`` reports the in-phase part (less ``sin`` of its reference's phase error times the
quadrature); ``dft`` (the AD5933) measures both parts and the front end keeps the in-phase one.

>>> import numpy as np
>>> z = np.array([[60., 20, 10, 20], [20, 60, 20, 10], [10, 20, 60, 20], [20, 10, 20, 60]])   # ohm
>>> reading = np.array([[0, 1, 2, 3]])
>>> contact = ElectrodeContact.uniform(4, resistance_ohm=0.0, capacitance_f=0.0)
>>> phasors, drive_v, _ = reading_phasors(z, reading, 1e-3, contact, 1e4, 1e-10, 5.0)
>>> np.round(phasors * 1e3, 6).tolist(), np.round(drive_v, 6).tolist()   # no contact: the sheet's reading
([(-20+0j)], [(0.08+0j)])
>>> contact = ElectrodeContact(np.array([1e3, 1e3, 1e3, 1.3e3]), np.zeros(4))   # one contact 30 % high
>>> phasors, _, _ = reading_phasors(z, reading, 1e-3, contact, 5e4, 1e-10, 5.0)    # 100 pF inputs, 50 kHz
>>> [round(float(detect(phasors, kind)[0]) * 1e3, 2) for kind in ("rms", "synchronous")]   # mV, against -20
[-21.94, -19.27]
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from appliance.errors import ModelInputInvalid


@dataclass(frozen=True)
class ElectrodeContact:
    """Each electrode's contact resistance (ohm) and capacitance (farad), shape (n_electrodes,) each."""

    resistance_ohm: np.ndarray
    capacitance_f: np.ndarray

    def __post_init__(self):
        for name in ("resistance_ohm", "capacitance_f"):
            value = np.asarray(getattr(self, name), dtype=float)
            if value.ndim != 1 or not np.all(np.isfinite(value)) or np.any(value < 0):
                raise ModelInputInvalid(f"contact {name} must be finite, non-negative values, one per electrode")
            object.__setattr__(self, name, value)

    @classmethod
    def uniform(cls, n_electrodes: int, *, resistance_ohm: float, capacitance_f: float, spread: float = 0.0,
                rng: np.random.Generator | None = None) -> ElectrodeContact:
        """Every electrode at the nominal values, each scaled by a factor drawn from 1 +/- ``spread``."""
        rng = rng or np.random.default_rng(0)
        scale = 1 + spread * rng.uniform(-1, 1, (2, n_electrodes))
        return cls(resistance_ohm * scale[0], capacitance_f * scale[1])

    def impedance(self, frequency_hz: float) -> np.ndarray:
        """R parallel C at ``frequency_hz``, ohm (complex)."""
        return self.resistance_ohm / (1 + 2j * math.pi * frequency_hz * self.resistance_ohm * self.capacitance_f)


def reading_phasors(transfer: np.ndarray, readings: np.ndarray, current_a: float, contact: ElectrodeContact,
                    frequency_hz: float, input_capacitance_f: float, compliance_v: float,
                    drive_series_ohm: float = 0.0) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(differential phasors, drive-voltage phasors, whether the source hit compliance), volts rms.

    ``readings`` are 0-based rows (drive+, drive-, meas+, meas-); the current leaves through drive-,
    whose wire is the ground. ``drive_series_ohm`` is resistance in the drive path besides the contacts
    (switches). A drive whose voltage would exceed ``compliance_v`` delivers proportionally less current.
    """
    a, b, c, d = np.asarray(readings).T
    z = transfer
    zc = contact.impedance(frequency_hz)
    if len(zc) != z.shape[0]:
        raise ModelInputInvalid(f"contact values for {len(zc)} electrodes on a mat of {z.shape[0]}")
    sheet_drive = z[a, a] - z[a, b] - z[b, a] + z[b, b]
    drive_ohm = sheet_drive + zc[a] + zc[b] + drive_series_ohm
    limited = current_a * np.abs(drive_ohm) > compliance_v
    current = np.where(limited, compliance_v / np.maximum(np.abs(drive_ohm), 1e-300), current_a)
    drive_v = current * drive_ohm
    input_ohm = 1 / (2j * math.pi * frequency_hz * input_capacitance_f) if input_capacitance_f > 0 else np.inf

    def wire_v(e):
        """The potential at electrode ``e``'s measuring input, relative to the return wire."""
        sheet = current * (z[e, a] - z[e, b] - z[b, a] + z[b, b] + zc[b])
        loaded = sheet if np.isinf(input_ohm) else sheet * input_ohm / (input_ohm + zc[e])
        return np.where(e == a, drive_v, np.where(e == b, 0.0, loaded))

    return wire_v(c) - wire_v(d), drive_v, limited


def detect(phasors: np.ndarray, detector: str, phase_error_rad: float = 0.0) -> np.ndarray:
    """What a detector reports for ``phasors`` (volts rms): see the module docstring."""
    if detector == "rms":
        return np.where(phasors.real < 0, -1.0, 1.0) * np.abs(phasors)
    if detector in ("synchronous", "dft"):
        return (phasors * np.exp(-1j * phase_error_rad)).real
    raise ValueError(f"unknown detector {detector!r}")
