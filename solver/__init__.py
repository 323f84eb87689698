"""slidecal.solver."""
