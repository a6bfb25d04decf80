"""The ward station: every bed of a ward seen together, from what each bed's monitor publishes over MQTT."""
