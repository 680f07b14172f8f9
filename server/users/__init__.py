"""Clinician accounts (admin, therapist); managed by admins."""
