"""Charting: the bed's events and pressures in the forms a hospital's record systems read (HL7 v2)."""
