"""slidecal.mocks."""
