"""slidecal.drivers."""
