"""The virtual bed read frame by frame through the whole-frame analogue chain.

What a settled scan of the emulated board would return, without running the
chips one transfer at a time: fast enough for a bed-size mat, and the same
interface (``acquire()`` giving volts, flags, temperature and time) the
calibration procedures and the monitor use with a real scan engine. ``profile``
chooses the front end; by default the board that reads such a mat
(:func:`virtual_board`): the reference board on the small sensors, the parallel
board, sized to the grid, on a bed.
"""

from __future__ import annotations

from collections.abc import Iterable
from dataclasses import dataclass

import numpy as np

from appliance.core.protocols import Protocol
from appliance.drivers.adaptive import AdaptivePlan
from appliance.drivers.profile import BoardProfile, board_profile
from appliance.drivers.scan import UNUSABLE, Flag, TechnicalCondition, saturation_condition
from appliance.errors import ConfigError
from appliance.sim.bed import VirtualBed
from appliance.sim.chain import FrameChain
from appliance.sim.scene_base import ElectrodeFault

# The mat's liquid layer (7 mm at 1.25 S/m, 0.0094 S) conducts half as well as the
# saline sheet the board's 2 mA was chosen for; 1 mA keeps an empty mat's largest
# readings in range. Heavy loads still saturate a few, as they would on the bench.
VIRTUAL_MAT_BOARD = {"excitation": {"current_a": 0.001}}

SPARE_ADDRESS_LINES = ("GPIO7", "GPIO8", "GPIO9")
"""Header lines free on the parallel board, for the decoder address bits a larger grid's ADCs need."""


def virtual_board(layout) -> dict:
    """The board a virtual mat of ``layout`` is read with: a serial board where its multiplexers reach
    every electrode, else the parallel board built for the layout's grid (more ADCs, and as many decoder
    address lines as they need)."""
    from appliance.core.protocols import SERIAL_ELECTRODES

    if not layout.is_grid or layout.n_electrodes <= SERIAL_ELECTRODES:
        return VIRTUAL_MAT_BOARD
    from appliance.drivers.channel_map import ChannelMap

    rows, cols = layout.grid_shape
    table = {"profile": "parallel", "grid": {"rows": rows, "cols": cols}}
    base = board_profile({"profile": "parallel"})
    assert base.measurement.adc_tile_rows is not None      # the parallel profile's: board_profile checked it
    adcs = ChannelMap(rows, cols, base.measurement.adc_tile_rows).n_adcs
    lines = len(base.adc_address_lines)
    extra = {f"adc_cs_a{lines + k}": pin
             for k, pin in enumerate(SPARE_ADDRESS_LINES[:max(0, (adcs - 1).bit_length() - lines)])}
    return {**table, "gpio": extra} if extra else table


@dataclass(frozen=True)
class VirtualFrame:
    """One frame: readings (NaN where unusable), their flags, the liquid's temperature, the scene time,
    and the technical conditions found, as a scan engine's frame carries them."""

    volts: np.ndarray
    flags: np.ndarray
    temperature_c: float
    time_s: float
    conditions: tuple[TechnicalCondition, ...] = ()


class VirtualFrontEnd:
    """``bed`` measured with ``protocol`` every ``frame_interval_s`` of scene time from ``start_s``."""

    def __init__(self, bed: VirtualBed, protocol: Protocol, *, profile: BoardProfile | None = None, seed: int = 0,
                 frame_interval_s: float = 1.0, start_s: float = 0.0):
        if protocol.n_electrodes != bed.n_electrodes:
            raise ValueError(f"protocol for {protocol.n_electrodes} electrodes on a {bed.n_electrodes}-electrode mat")
        self.bed, self.protocol = bed, protocol
        self.chain = FrameChain(profile or board_profile(virtual_board(bed.layout)), seed=seed)
        self.chain.check(protocol)
        grid = getattr(self.chain.profile, "grid", None)
        self.plan = AdaptivePlan(protocol, grid.rows, grid.cols) if grid is not None else None
        self._last: tuple[np.ndarray, np.ndarray] | None = None     # the last frame's readings and flags
        self.seed = seed
        self._noise_key: tuple[int, int] = (-1, -1)        # (scene ms, frames already taken at that instant)
        self.frame_interval_s = frame_interval_s
        self.time_s = start_s
        self.open_electrodes: set[int] = set()
        self.pending_faults: list[ElectrodeFault] = []

    def disconnect(self, electrode: int) -> None:
        """Lose an electrode's contact (a lead pulled off): from the next frame its readings are flagged
        and left out, as the scan engine's contact check leaves them out."""
        self.open_electrodes.add(self._checked(electrode))

    def reconnect(self, electrode: int) -> None:
        """Restore an electrode's contact: from the next frame its readings are used again."""
        self.open_electrodes.discard(self._checked(electrode))

    def schedule_faults(self, faults: Iterable[ElectrodeFault]) -> None:
        """Play ``faults`` (a scene's electrode faults) as scene time passes, in place of any earlier
        schedule and with every electrode connected; an electrode beyond the mat is refused."""
        faults = sorted(faults, key=lambda f: f.at_s)
        for fault in faults:
            self._checked(fault.electrode)
        self.pending_faults = faults
        self.open_electrodes.clear()

    def _seed_noise(self, t: float) -> None:
        """Noise drawn from the frame's scene time (and how many frames came before it at that instant),
        so a monitor restarted mid-scene reads the very frames an uninterrupted one would have."""
        ms = round(t * 1000)
        repeat = self._noise_key[1] + 1 if self._noise_key[0] == ms else 0
        self._noise_key = (ms, repeat)
        self.chain.rng = np.random.default_rng([self.seed, ms, repeat])

    def _checked(self, electrode: int) -> int:
        if not 1 <= electrode <= self.bed.n_electrodes:
            raise ValueError(f"electrode {electrode} is not on this {self.bed.n_electrodes}-electrode mat")
        return electrode

    @property
    def adaptive(self) -> bool:
        """Whether the board reads adaptively: a parallel board on a grid (:mod:`appliance.drivers.adaptive`)."""
        return self.plan is not None

    def acquire(self, loaded=None) -> VirtualFrame:
        """The next frame, after the scheduled faults due by its time; scene time moves on by one frame
        interval. With ``loaded`` electrodes (an adaptive board) only the coarse drives and the fine
        ones near them are taken; the other readings keep the last frame's values, flagged HELD, as
        the scan engine keeps them."""
        t = self.time_s
        while self.pending_faults and self.pending_faults[0].at_s <= t:
            fault = self.pending_faults.pop(0)
            (self.reconnect if fault.connected else self.disconnect)(fault.electrode)
        self._seed_noise(t)
        volts, flags = self.chain.readings(self.bed.transfer_ohm(t), self.protocol)
        if loaded is not None and self._last is not None:
            if self.plan is None:
                raise ConfigError("adaptive frames need a front end built for a grid ([board.grid], the parallel "
                                  "profile)")
            held = ~np.isin(self.protocol.drive_index, self.plan.drives_for(loaded))
            volts[held], flags[held] = self._last[0][held], self._last[1][held] | Flag.HELD
        self._last = (volts.copy(), flags.copy())
        conditions = []
        for electrode in sorted(self.open_electrodes):
            flags[(self.protocol.readings == electrode).any(axis=1)] |= Flag.OPEN_ELECTRODE
            conditions.append(TechnicalCondition(f"electrode {electrode}", "no contact: its readings are left out"))
        saturation = saturation_condition(flags, self.protocol)
        if saturation is not None:
            conditions.append(saturation)
        volts = np.where((flags & int(UNUSABLE)) == 0, volts, np.nan)
        self.time_s += self.frame_interval_s
        return VirtualFrame(volts, flags, self.bed.temperature_at(t), t, tuple(conditions))
