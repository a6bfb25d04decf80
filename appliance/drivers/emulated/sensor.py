"""The mat behind the emulated front end: the core forward model of a layout at a fixed conductivity.

The sheet's conductance defaults to the thesis's tanks: saline of 1 S/m
(10 mS/cm) 20 mm deep, 0.02 S per square, which puts two-electrode impedances
of the 100 mm grid at 45 to 80 ohm, as Table 3.2.2.1 measured. The virtual bed
replaces this with a mat that changes under a patient.

>>> from appliance.core.named_layouts import get_layout
>>> sensor = ForwardSensor.of_layout(get_layout("grid-4x4"))
>>> sensor.n_electrodes, sensor.transfer_ohm(0.0).shape
(16, (16, 16))
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from appliance.core.layouts import Layout
from appliance.drivers.emulated.electrode_interface import ElectrodeContact

SALINE_SHEET_S = 0.02


@dataclass(frozen=True)
class ForwardSensor:
    """A mat that does not change: one transfer-impedance matrix, ohm, and optionally its electrodes' contacts."""

    transfer: np.ndarray
    contact: ElectrodeContact | None = None

    @property
    def n_electrodes(self) -> int:
        return self.transfer.shape[0]

    def transfer_ohm(self, now_s: float) -> np.ndarray:
        return self.transfer

    @classmethod
    def of_layout(cls, layout: Layout, *, inclusions=(), sheet_conductance_s: float = SALINE_SHEET_S,
                  density: float = 1.0, contact: ElectrodeContact | None = None) -> ForwardSensor:
        """Solve the layout's finite-element model once; ``inclusions`` scale the sheet locally."""
        from appliance.core.fem import build_fem_model
        from appliance.core.forward import solve_electrodes
        from appliance.core.phantoms import conductivity

        model = build_fem_model(layout, density=density)
        sigma = conductivity(model, inclusions, background=sheet_conductance_s)
        return cls(solve_electrodes(model, sigma).transfer, contact)
