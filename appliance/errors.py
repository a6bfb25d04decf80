"""Every error the appliance raises, in one hierarchy.

Each leaf is also the builtin a caller would expect (``LayoutInvalid`` is a
``ValueError``), so ``except ValueError`` keeps working, while
``except ApplianceError`` catches everything of ours. Messages name the input
that is wrong: the electrode, the row of a file, the element.
"""


class ApplianceError(Exception):
    """Root of every error raised by the appliance."""


class ConfigError(ApplianceError):
    """A description given to the appliance (layout, protocol, settings) is unusable."""


class LayoutInvalid(ConfigError, ValueError):
    """A sensor-mat layout is malformed: bad geometry, overlapping or misplaced electrodes."""


class ProtocolInvalid(ConfigError, ValueError):
    """A measurement protocol names unknown electrodes or uses one electrode twice in a pair."""


class CurveInvalid(ConfigError, ValueError):
    """A tolerance curve is unknown or its points are not positive and monotone; the message names the point."""


class BoardMismatch(ConfigError, ValueError):
    """A board profile asks of the host what it cannot give: a line it lacks, a pin taken, a mode, a bus not enabled."""


class AnalogueMismatch(ConfigError, ValueError):
    """A profile's analogue chain cannot do what it states: a part on rails it is not specified for, a current
    source that drives an electrode beyond what its multiplexers pass, a detector other than the chain's."""


class DataFileInvalid(ApplianceError, ValueError):
    """A data file (protocol, frame, calibration) cannot be parsed; the message names file and row."""


class ModelInputInvalid(ApplianceError, ValueError):
    """A forward-model input is out of range, such as a non-positive or non-finite conductivity."""


class SolverError(ApplianceError, ArithmeticError):
    """A linear solve did not reach the required accuracy or produced non-finite values."""


class ReconstructionError(ApplianceError, ValueError):
    """A frame cannot be reconstructed: too few usable readings, or readings that do not fit the model."""


class BusError(ApplianceError):
    """A bus (GPIO, SPI, I2C) could not be opened or a transfer on it failed; the message names it."""


class BackendUnavailable(BusError, ImportError):
    """The Python binding a Linux bus needs (gpiod, spidev, smbus2) is not installed."""


class DeviceMissing(BusError, FileNotFoundError):
    """A device file (/dev/spidevB.C, /dev/i2c-N, a GPIO chip) or a named GPIO line does not exist."""


class BusInUse(BusError, RuntimeError):
    """A chip select, I2C address or GPIO line is already held by another part of the appliance."""


class TransferFailed(BusError, OSError):
    """One transfer failed (I2C no-acknowledge, SPI I/O error); transient, so callers may retry it.

    ``errno`` is the operating system's error number (121 for an I2C device that
    does not acknowledge its address).
    """


class ChipError(ApplianceError):
    """A chip on the front end misbehaves: wrong read-back, no answer, a stuck or saturated value."""


class ChipNotResponding(ChipError, OSError):
    """A chip failed every retry of a transfer, or never reached the state it was commanded to."""


class ChipReadbackMismatch(ChipError, ValueError):
    """A register read back a value other than the one written; the message gives both."""


class ScanError(ApplianceError, RuntimeError):
    """A whole frame could not be acquired (the excitation failed, or no reading was usable)."""


class StoreError(ApplianceError):
    """The store cannot be opened or used; the message names the file."""


class StoreCorrupt(StoreError, ValueError):
    """The file is not an SQLite database (or is damaged); it is left as found so it can be examined."""


class SchemaTooNew(StoreError, RuntimeError):
    """The file was written by a newer appliance; migrating it down could lose data, so it is refused."""


class StoreClosed(StoreError, RuntimeError):
    """A write or query reached a store after ``close()``: it would silently be lost."""


class DataDirInUse(ApplianceError, RuntimeError):
    """Another monitor holds the data folder: two writers of one store and one live view would mix two beds."""
