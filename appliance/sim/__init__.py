"""The virtual bed: patient scenes, the mat's mechanics, and the sensor model the emulated front end measures.

Data flows scene -> pressure field -> mat mechanics -> sheet conductance -> forward
model -> transfer impedances, which the emulated board's analogue chain reads.
"""
