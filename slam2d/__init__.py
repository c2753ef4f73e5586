"""slam2d."""
