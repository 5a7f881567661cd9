"""Piezoelectric bender physics and the PiezoBender-v0 Gymnasium environment."""
