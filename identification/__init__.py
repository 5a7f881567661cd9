"""Hammerstein identification of the piezo bender: ARX under bounded noise, neural NLS."""
