"""Execution of plans on an Instrument; run reports."""
