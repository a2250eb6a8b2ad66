"""Labelled synthetic scenes: polyhedral scenes seen by a simulated range sensor, outdoor scenes seen by a stereo-like sensor."""
