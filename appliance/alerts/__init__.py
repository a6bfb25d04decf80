"""Pressure-sore alerts: regions, pressure-time dose, turn clock, alarm engine."""
