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


class DataFileInvalid(ApplianceError, ValueError):
    """A data file (protocol, frame, calibration) cannot be parsed; the message names file and row."""


class ModelInputInvalid(ApplianceError, ValueError):
    """A forward-model input is out of range, such as a non-positive or non-finite conductivity."""


class SolverError(ApplianceError, ArithmeticError):
    """A linear solve did not reach the required accuracy or produced non-finite values."""


class ReconstructionError(ApplianceError, ValueError):
    """A frame cannot be reconstructed: too few usable readings, or readings that do not fit the model."""
