"""The front end's drivers: bus interfaces, Linux buses, one module per chip, the scan engine.

Data flows one way: a :class:`~appliance.drivers.bus.Board` hands out buses, chip
drivers take them by injection, the front end composes the chips, and the scan
engine turns a protocol into a frame of readings with quality flags.
:func:`~appliance.drivers.backend.open_board` is the one place that chooses between the
real board and the emulated one. This package module imports nothing, so its modules never import
their own package's code back.
"""
