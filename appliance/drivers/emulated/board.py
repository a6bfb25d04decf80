"""The emulated board: a profile's chips as register-level emulators, wired to one analogue chain.

It is a complete :class:`~appliance.drivers.bus.Board`: the same front end and
scan engine that run on a Raspberry Pi run here, and every transfer is logged
(``board.log``) and charged to the simulated clock: SPI at the profile's clocks, I2C at
the clock the system (the profile's, or ``system=``) runs the bus at, so the time a scan
takes is the profile's timing model on that system. It stands on a Pi 4B (:data:`HOST`)
under the kernel of the system, whose facts it enforces.

Faults for tests and demonstrations: ``board.faults.fail_next(target, count,
errno)`` for transfer errors, ``board.faults.missing`` for device files absent
at open, ``board.chain.open_electrodes`` for electrodes that lost contact,
``board.chain.pickup_v`` for a channel that saturates, and
``board.adc.stuck_code`` for a stuck converter.
"""

from __future__ import annotations

import errno

import numpy as np

from appliance.drivers.boards import HOST_BOARDS, I2C_DEFAULT_CLOCK_HZ, SYSTEMS, System
from appliance.drivers.bus import Board, LineRequest, os_error_to_bus_error
from appliance.drivers.emulated.ad5933 import EmulatedAD5933
from appliance.drivers.emulated.ad8251 import EmulatedAD8251
from appliance.drivers.emulated.ad9833 import EmulatedAD9833
from appliance.drivers.emulated.adg7xx import EmulatedADG725, EmulatedADG731
from appliance.drivers.emulated.ads1115 import EmulatedADS1115
from appliance.drivers.emulated.analogue import AnalogueChain, ChainErrors, ChainState, SensorModel
from appliance.drivers.emulated.buses import (BusTiming, EmulatedGPIOLines, EmulatedI2CBus, EmulatedSPIDevice,
                                              FaultPlan, GPIOBank, I2CChipEmulator, SPIChipEmulator,
                                              Transaction)
from appliance.drivers.emulated.clock import SimulatedClock
from appliance.drivers.emulated.mcp4017 import EmulatedMCP4017
from appliance.drivers.emulated.mcp9808 import EmulatedMCP9808
from appliance.drivers.profile import BoardProfile
from appliance.errors import ConfigError, DeviceMissing

HOST = HOST_BOARDS["pi4b"]
"""The Pi the emulated front end sits on: its lines carry that board's names and its SPI1 refuses CPHA = 1."""
POWERED_BEFORE_OPEN_S = 1.0     # the board is powered a while before software opens it (thermometer converted)


class EmulatedBoard(Board):
    """``profile``'s front end over emulated chips measuring ``sensor``; ``seed`` fixes errors and noise.

    The serial chains' board; :func:`appliance.drivers.backend.emulated_board` chooses between it and the
    parallel board (:mod:`appliance.drivers.emulated.parallel_board`) by the profile's chain.
    """

    clock: SimulatedClock

    def __init__(self, profile: BoardProfile, sensor: SensorModel, *, seed: int = 0,
                 temperature_c: float = 24.0, system: System | None = None):
        if profile.chain == "parallel" and type(self) is EmulatedBoard:
            raise ConfigError(f"profile {profile.name!r} is the parallel front end: its emulated board is "
                              "EmulatedParallelBoard (appliance.drivers.backend.emulated_board chooses it)")
        super().__init__()
        self.profile, self.sensor = profile, sensor
        self.system = system or SYSTEMS[profile.system]
        self.clock = SimulatedClock()
        self.log: list[Transaction] = []
        self.faults = FaultPlan()
        # The I2C bus runs at the clock the system's device tree gives it, whatever the profile hoped for.
        i2c_clock_hz = self.system.i2c_clock_hz.get(profile.i2c_bus, I2C_DEFAULT_CLOCK_HZ)
        self.timing = BusTiming(i2c_clock_hz, profile.timing.call_overhead_s)
        names = HOST.names(self.system.kernel)
        if names is None:
            raise ConfigError(f"the {HOST.model}'s GPIO line names under the {self.system.kernel} kernel are not "
                              "known: the emulated header needs them")
        self.bank = GPIOBank(self.clock, names, self.log)
        self.i2c_bus = EmulatedI2CBus(profile.i2c_bus, self.clock, self.timing, self.log, self.faults)
        self.spi_chips: dict[tuple[int, int], SPIChipEmulator] = {}
        self.temperature_c = temperature_c
        rng = np.random.default_rng(seed)
        self.chain = self._build_chain(rng, seed)
        self._build_chips(seed)
        self._listen()
        self.clock.sleep(POWERED_BEFORE_OPEN_S)

    # -- wiring --------------------------------------------------------------------------
    def _build_chain(self, rng, seed: int) -> AnalogueChain:
        p = self.profile
        t = p.timing
        assert p.excitation.compliance_v is not None     # board_profile sets it
        return AnalogueChain(self.clock, self.sensor, state=self._chain_state, inamp_gain=p.measurement.inamp_gain,
                             compliance_v=p.excitation.compliance_v, drive_settle_s=t.drive_settle_s,
                             settle_accuracy=t.settle_accuracy or 1e-4,
                             rms_rise_tau_s=t.rms_rise_tau_s or 0.35e-3, rms_fall_tau_s=t.rms_fall_tau_s or 0.7e-3,
                             sign_floor_v=p.measurement.sign_floor_v, errors=ChainErrors.drawn(rng), seed=seed,
                             frequency_hz=p.excitation.frequency_hz,
                             input_capacitance_f=p.measurement.input_capacitance_f or 0.0)

    def _build_chips(self, seed: int) -> None:
        p = self.profile
        gpio = p.gpio
        self.pga = EmulatedAD8251(self.bank, a0=gpio["gain_a0"], a1=gpio["gain_a1"], wr=gpio["gain_wr"])
        self.thermometer = EmulatedMCP9808(self.clock, lambda now: self.temperature_c,
                                           address=p.i2c["thermometer"])
        self.i2c_bus.attach(self.thermometer)
        self.muxes: dict[str, EmulatedADG725 | EmulatedADG731]
        if p.multiplexer == "adg725":
            self.muxes = {role: EmulatedADG725() for role in ("drive_mux", "measure_mux")}
        else:
            self.muxes = {role: EmulatedADG731() for role in ("drive_pos_mux", "drive_neg_mux", "meas_pos_mux",
                                                              "meas_neg_mux")}
        for role, mux in self.muxes.items():
            self.spi_chips[(p.spi[role].bus, p.spi[role].chip_select)] = mux
        if p.chain == "rms":
            self.dds = EmulatedAD9833()
            self.spi_chips[(p.spi["dds"].bus, p.spi["dds"].chip_select)] = self.dds
            self.digipot = EmulatedMCP4017()
            self.adc = EmulatedADS1115(self.clock, self.chain.pin_volts, address=p.i2c["adc"], seed=seed + 1)
            for chip in (self.digipot, self.adc):
                self.i2c_bus.attach(chip)
            self.bank.connect(gpio["adc_ready"], self.adc)
            self.bank.connect(gpio["phase_sign"], self.chain.phase_source())
        else:
            vin_gain = p.measurement.vin_gain
            assert vin_gain is not None         # the chain's: board_profile checked it is set
            self.impedance = EmulatedAD5933(self.clock, lambda now: self.chain.vin_phasor(now, vin_gain),
                                            seed=seed + 1)
            self.i2c_bus.attach(self.impedance)

    def _listen(self) -> None:
        listeners = [self.pga.listeners, *(mux.listeners for mux in self.muxes.values())]
        listeners += ([self.dds.listeners, self.digipot.listeners] if self.profile.chain == "rms"
                      else [self.impedance.listeners])
        for chip_listeners in listeners:
            chip_listeners.append(self.chain.state_changed)
        self.bank.watch(self.profile.gpio["source_enable"], lambda old, new: self.chain.state_changed())

    def _pair(self, pos_role: str, neg_role: str | None = None) -> tuple[int, int] | None:
        """The electrodes (0-based) a multiplexer pair connects, None while either is off."""
        if neg_role is None:
            mux = self.muxes[pos_role]
            assert isinstance(mux, EmulatedADG725)
            a, b = mux.selected("A"), mux.selected("B")
        else:
            pos, neg = self.muxes[pos_role], self.muxes[neg_role]
            assert isinstance(pos, EmulatedADG731) and isinstance(neg, EmulatedADG731)
            a, b = pos.selected(), neg.selected()
        return None if a is None or b is None else (a, b)

    def _chain_state(self) -> ChainState:
        p = self.profile
        enabled = self.bank.driven.get(p.gpio["source_enable"], 0) == 1
        if p.multiplexer == "adg725":
            drive, measure = self._pair("drive_mux"), self._pair("measure_mux")
        else:
            drive, measure = self._pair("drive_pos_mux", "drive_neg_mux"), self._pair("meas_pos_mux", "meas_neg_mux")
        return ChainState(drive=drive, measure=measure, current_a=self._current_a() if enabled else 0.0,
                          gain=float(self.pga.gain))

    def _current_a(self) -> float:
        x = self.profile.excitation
        if self.profile.chain == "rms":
            if self.dds.output_hz <= 0 or self.dds.waveform != "sine":
                return 0.0
            assert x.full_scale_current_a is not None
            return x.full_scale_current_a * self.digipot.wiper / 127
        if self.impedance.output_frequency_hz is None:
            return 0.0
        assert x.transconductance_a_per_v is not None
        return self.impedance.output_vpp / (2 * np.sqrt(2)) * x.transconductance_a_per_v

    # -- Board ---------------------------------------------------------------------------
    def _open_spi(self, bus, chip_select, mode, max_speed_hz):
        name = f"/dev/spidev{bus}.{chip_select}"
        chip = self.spi_chips.get((bus, chip_select))
        if chip is None or name in self.faults.missing:
            raise DeviceMissing(f"SPI {name}: no such device (is SPI enabled with dtparam=spi=on, and does the "
                                "board have this chip select?)")
        controller = HOST.spi.get(bus)
        if controller is not None and controller.modes is not None and mode not in controller.modes:
            raise os_error_to_bus_error(f"SPI {name}", OSError(errno.EINVAL, f"Invalid argument: mode {mode} on "
                                                                              f"{controller.driver}"))
        return EmulatedSPIDevice(name, mode, max_speed_hz, chip, self.clock, self.timing, self.log, self.faults)

    def _open_i2c(self, bus):
        name = f"/dev/i2c-{bus}"
        if bus != self.profile.i2c_bus or name in self.faults.missing:
            raise DeviceMissing(f"I2C {name}: no such device (is I2C enabled with dtparam=i2c_arm=on?)")
        return self.i2c_bus

    def _request_lines(self, request: LineRequest, consumer: str):
        return EmulatedGPIOLines(self.bank, request, consumer, self.timing)

    def reset(self) -> None:
        """Every chip to its power-on state, faults cleared, log emptied (the mat is kept)."""
        chips: list[SPIChipEmulator | I2CChipEmulator | EmulatedAD8251] = [
            *self.spi_chips.values(), *self.i2c_bus.chips.values(), self.pga]
        for chip in chips:
            chip.reset()
        self.faults.clear()
        self.log.clear()
        self.chain.open_electrodes.clear()
        self.chain.pickup_v.clear()
        self.chain.state_changed()
