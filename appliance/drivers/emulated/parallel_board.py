"""The emulated board of the parallel front end: its chips as emulators, wired to the parallel analogue chain.

Built by :func:`~appliance.drivers.backend.emulated_board` when the
profile's chain is ``parallel``: AD9833, MCP4017 and MCP9808 as on the other
boards, the ADG1414 chain on its chip select (refusing any state the drive
matrix forbids), and one AD7606 per channel tile behind the chip-select
decoder, their CONVST, RESET and RANGE on the shared lines and their BUSY
outputs ORed onto one. Every transfer is charged to the simulated clock at the
profile's timing, as on the other boards.

Faults: ``board.chain.open_electrodes`` and ``board.chain.pickup_v`` as on the
other boards, ``board.adcs[k].stuck_code`` for one stuck converter, and the
shared ``board.faults`` for transfer errors.
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np

from appliance.drivers.adg1414 import DriveMatrix
from appliance.drivers.channel_map import ChannelMap
from appliance.drivers.emulated.ad7606 import AD7606Pins, EmulatedAD7606
from appliance.drivers.emulated.ad9833 import EmulatedAD9833
from appliance.drivers.emulated.adg1414 import EmulatedADG1414Chain, EmulatedChipSelectDecoder, drive_of
from appliance.drivers.emulated.board import EmulatedBoard
from appliance.drivers.emulated.buses import I2CChipEmulator, SPIChipEmulator
from appliance.drivers.emulated.mcp4017 import EmulatedMCP4017
from appliance.drivers.emulated.mcp9808 import EmulatedMCP9808
from appliance.drivers.emulated.parallel import DriveState, ParallelChain, ParallelErrors


class EmulatedParallelBoard(EmulatedBoard):
    """The parallel profile's front end over emulated chips; see the module docstring."""

    # The parallel chain is a model of its own, not an AnalogueChain: the other boards' code never reaches it.
    chain: ParallelChain    # type: ignore[assignment]

    def _build_chain(self, rng, seed: int) -> ParallelChain:     # type: ignore[override]
        p = self.profile
        m = p.measurement
        assert m.lowpass_gain is not None and m.lowpass_hz is not None      # the chain's: board_profile checked
        assert p.excitation.compliance_v is not None
        self.cmap = ChannelMap.of_profile(p)
        self.errors = ParallelErrors.drawn(rng, self.cmap.n_channels)
        return ParallelChain(self.clock, self.sensor, self.cmap, state=self._drive_state, inamp_gain=m.inamp_gain,
                             lowpass_gain=m.lowpass_gain, lowpass_hz=m.lowpass_hz,
                             compliance_v=p.excitation.compliance_v, errors=self.errors, seed=seed,
                             frequency_hz=p.excitation.frequency_hz,
                             input_capacitance_f=m.input_capacitance_f or 0.0)

    def _build_chips(self, seed: int) -> None:
        p = self.profile
        gpio = p.gpio
        self.thermometer = EmulatedMCP9808(self.clock, lambda now: self.temperature_c, address=p.i2c["thermometer"])
        self.digipot = EmulatedMCP4017()
        for chip in (self.thermometer, self.digipot):
            self.i2c_bus.attach(chip)
        self.dds = EmulatedAD9833()
        self.switches = EmulatedADG1414Chain(DriveMatrix.chips_for(p.channels), validate=drive_of)
        assert p.measurement.adc_oversampling is not None

        def inputs_of(k: int) -> Callable[[float], np.ndarray]:
            return lambda t: self.chain.adc_inputs(t)[k]

        self.adcs = [EmulatedAD7606(self.clock, inputs_of(k), oversampling=p.measurement.adc_oversampling,
                                    noise_lsb=self.errors.adc_noise_lsb, seed=seed + 2 + k)
                     for k in range(self.cmap.n_adcs)]
        self.adc_pins = AD7606Pins(self.bank, self.adcs, convst=gpio["adc_convst"], reset=gpio["adc_reset"],
                                   range_line=gpio["adc_range"])
        self.bank.connect(gpio["adc_busy"], self.adc_pins)
        self.decoder = EmulatedChipSelectDecoder(self.bank, p.adc_address_lines, dict(enumerate(self.adcs)))
        spi_chips: tuple[tuple[str, SPIChipEmulator], ...] = (
            ("dds", self.dds), ("drive_switches", self.switches), ("adc", self.decoder))
        for role, spi_chip in spi_chips:
            self.spi_chips[(p.spi[role].bus, p.spi[role].chip_select)] = spi_chip
        self.chain.before_change.append(self.adc_pins.take_due)

    def _listen(self) -> None:
        for chip in (self.dds, self.digipot, self.switches):
            chip.listeners.append(self.chain.state_changed)
        self.bank.watch(self.profile.gpio["source_enable"], lambda old, new: self.chain.state_changed())
        self.chain.power_on()

    def _drive_state(self) -> DriveState:
        enabled = self.bank.driven.get(self.profile.gpio["source_enable"], 0) == 1
        pos, neg = drive_of(self.switches.words)
        drive = None if pos is None or neg is None else (pos, neg)
        running = self.dds.output_hz > 0 and self.dds.waveform == "sine"
        assert self.profile.excitation.full_scale_current_a is not None
        current = self.profile.excitation.full_scale_current_a * self.digipot.wiper / 127 if running else 0.0
        return DriveState(drive=drive, current_a=current if enabled else 0.0)

    def reset(self) -> None:
        """Every chip to its power-on state, faults cleared, log emptied (the mat is kept)."""
        chips: list[SPIChipEmulator | I2CChipEmulator] = [*self.spi_chips.values(), *self.i2c_bus.chips.values()]
        for chip in chips:
            chip.reset()
        for adc in self.adcs:
            adc.stuck_code = None
        self.faults.clear()
        self.log.clear()
        self.chain.open_electrodes.clear()
        self.chain.pickup_v.clear()
        self.chain.power_on()

    def channel_levels(self) -> np.ndarray:
        """Each channel's settled low-pass output now, volts (for tests and the benchmark's dynamic range)."""
        return self.chain.target_v(self.clock.monotonic())
