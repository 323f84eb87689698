"""slidecal.routines."""
