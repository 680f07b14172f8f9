"""Prescriptions: ordered exercise segments (cue, duration, washout, limits); editing adds a version."""
