"""Reflective tags (issue 43): which robot is which, from the laser alone. :mod:`.codes` designs the
codes, :mod:`.band` draws the bands to print."""
